"""The camera layer every camera tracker shares: a calibrated camera model and its files
(``model``), frames with capture times from devices, files and URLs (``capture``), and a
camera simulator that renders what a camera would see from a ground-truth trajectory
(``simulator``)."""

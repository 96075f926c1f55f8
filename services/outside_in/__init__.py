"""Outside-in marker tracking: cameras around a volume, retro-reflective markers on bodies.

Dorfmüller-Ulhaas, *Robust Optical User Motion Tracking Using a Kalman Filter*, §2: blob
segmentation, matching between cameras and triangulation, identification of each body's
structure in the 3D points, refinement against the marker images, an EKF that smooths and
predicts, the prediction projected back into the images.  ``rig`` holds the cameras,
``blobs`` finds markers in images, ``triangulation`` matches and triangulates them,
``bodies`` identifies bodies, ``pose`` fits and refines poses, ``motion`` is the filter,
``tracker`` runs them per frame set, ``simulator`` renders infrared views of a rig,
``calibration`` calibrates a rig from a waved wand.
"""

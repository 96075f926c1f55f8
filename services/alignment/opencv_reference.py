"""``cv2.calibrateHandEye`` on uma's stations: the independent baseline of tests and eval.

Mapping (see ``solvers``): gripper = sensor a, base = world_a, camera = sensor b,
target = world_b.  ``R/t_gripper2base`` are the poses ``A_k`` as given;
``R/t_target2cam`` are ``B_k^-1`` (world_b in sensor b); ``R/t_cam2gripper`` is ``X``.
OpenCV forms motions from every two stations, unselected and without outlier handling.
"""

from __future__ import annotations

import cv2
import numpy as np

from agent import geometry as geo
from services.alignment.solvers import AlignmentError, Pose

METHODS = {"tsai": cv2.CALIB_HAND_EYE_TSAI, "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS}


def calibrate_hand_eye(pa: np.ndarray, qa: np.ndarray, pb: np.ndarray, qb: np.ndarray,
                       method: str = "daniilidis") -> Pose:
    """X by OpenCV from stations ``A_k = (pa, qa)[k]``, ``B_k = (pb, qb)[k]``."""
    if not hasattr(cv2, "calibrateHandEye"):
        raise AlignmentError(f"OpenCV {cv2.__version__} has no calibrateHandEye (the 5.0 "
                             "wheels dropped it); install opencv-python-headless<5")
    pbi, qbi = geo.inverse(np.asarray(pb, float), np.asarray(qb, float))
    R, t = cv2.calibrateHandEye(list(geo.quat_to_matrix(qa)), list(np.asarray(pa, float)),
                                list(geo.quat_to_matrix(qbi)), list(pbi),
                                method=METHODS[method])
    return Pose(np.asarray(t, float).reshape(3), geo.matrix_to_quat(R))

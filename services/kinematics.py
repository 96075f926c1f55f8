"""A frame's exact kinematics over time: the shape of ground truth (the simulator's head
trajectory, the rig's test motions) that the dead reckoner is reset from and measured
against.  Shared by the simulator and the services, so real-hardware code needs no
simulator for it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agent import geometry as geo


@dataclass(frozen=True)
class KinematicState:
    """Exact kinematics of a frame at times ``t`` (arrays with a leading time axis)."""

    t: np.ndarray  # (n,) seconds
    position: np.ndarray  # (n, 3) in world
    quaternion: np.ndarray  # (n, 4) xyzw, frame in world
    velocity: np.ndarray  # (n, 3) world
    acceleration: np.ndarray  # (n, 3) world, kinematic (gravity not included)
    omega_body: np.ndarray  # (n, 3) angular velocity in the frame's own axes
    alpha_body: np.ndarray  # (n, 3) angular acceleration in the frame's own axes

    def rigid_offset(self, p_off: np.ndarray, q_off: np.ndarray) -> KinematicState:
        """Kinematics of a frame rigidly attached at pose ``(p_off, q_off)`` in this frame."""
        R = geo.quat_to_matrix(self.quaternion)
        r_w = R @ np.asarray(p_off, float)
        w_w = np.einsum("nij,nj->ni", R, self.omega_body)
        al_w = np.einsum("nij,nj->ni", R, self.alpha_body)
        p, q = geo.compose(self.position, self.quaternion, p_off, q_off)
        R_off_T = geo.quat_to_matrix(geo.quat_conjugate(q_off))
        return KinematicState(
            t=self.t,
            position=p,
            quaternion=q,
            velocity=self.velocity + np.cross(w_w, r_w),
            acceleration=self.acceleration + np.cross(al_w, r_w)
            + np.cross(w_w, np.cross(w_w, r_w)),
            omega_body=self.omega_body @ R_off_T.T,
            alpha_body=self.alpha_body @ R_off_T.T,
        )

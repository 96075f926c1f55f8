"""The stray-blob check's early end (``tracker._longest_passing_moves``): on plain floats,
per dot the squared length of the longest move along its wall that changes the fourth
dot's miss by one sigma of ``S``; it decides which frame sets skip the check, so it must
be numpy's eigenvalue answer, and inf where the miss does not see a move at all."""

from __future__ import annotations

import math

import numpy as np

from services.laser_camera.tracker import _longest_passing_moves


def _reference(Jm: np.ndarray, S: np.ndarray) -> np.ndarray:
    """One over the least eigenvalue of ``B = Jm S^-1 Jm^T`` per dot (Jm: dot, wall axis,
    miss component), by numpy."""
    B = np.einsum("kai,ij,kbj->kab", Jm, np.linalg.inv(S), Jm)
    return 1.0 / np.linalg.eigvalsh(B)[:, 0]


def test_the_longest_passing_moves_are_numpys_least_eigenvalues() -> None:
    rng = np.random.default_rng(4)
    for _ in range(300):
        scale = 10.0 ** rng.uniform(-2, 2)
        Jm = rng.normal(size=(3, 2, 2)) * scale
        A = rng.normal(size=(2, 2)) * 10.0 ** rng.uniform(-4, -2)
        S = A @ A.T + 1e-10 * np.eye(2)
        got = np.array(_longest_passing_moves(Jm, S))
        assert np.allclose(got, _reference(Jm, S), rtol=1e-6, atol=0)


def test_a_move_the_miss_does_not_see_is_infinitely_long() -> None:
    """A dot whose Jacobian is singular (its rows parallel), or all but singular, has a
    move that leaves the miss alone; the others keep their lengths."""
    Jm = np.array([[[1.0, 0.5], [2.0, 1.0]],  # singular: row 2 = 2 x row 1
                   [[1.0, 0.0], [0.0, 1.0]],
                   [[1.0, 0.5], [2.0, 1.0 + 1e-12]]])  # condition about 1e13
    S = np.diag([1e-6, 4e-6])
    got = _longest_passing_moves(Jm, S)
    assert got[0] == math.inf and got[2] == math.inf
    assert np.isclose(got[1], _reference(Jm[1:2], S)[0], rtol=1e-12, atol=0)


def test_a_miss_covariance_that_is_not_positive_definite_defines_no_move() -> None:
    """``S`` singular, indefinite or not finite: no move has ``m^T S^-1 m = 1`` to measure
    (a ZeroDivisionError or a negative length otherwise); the stray check refuses on it."""
    Jm = np.tile(np.eye(2), (3, 1, 1))
    for S in (np.zeros((2, 2)), np.array([[1e-6, 1e-6], [1e-6, 1e-6]]),
              np.diag([1e-6, -1e-6]), np.diag([-1e-6, -1e-6]), np.diag([np.nan, 1e-6])):
        assert _longest_passing_moves(Jm, S) is None, S

"""Linear algebra over stacks of small systems, shared by the trackers' batched
Gauss-Newton and Levenberg-Marquardt steps (one system per tag pose or per blob)."""

from __future__ import annotations

import contextlib

import numpy as np


def solve_stack(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``A[i]⁻¹ b[i]`` for a stack of square systems (n, k, k) and (n, k); zero where
    one is singular, so that a fit with nothing left to fit takes no step."""
    with np.errstate(all="ignore"):
        try:
            return np.linalg.solve(A, b[..., None])[..., 0]
        except np.linalg.LinAlgError:
            out = np.zeros_like(b)
            for i in range(len(A)):
                with contextlib.suppress(np.linalg.LinAlgError):
                    out[i] = np.linalg.solve(A[i], b[i])
            return out

"""The alignment's stations (``pipeline.station_times``): one sample from each equal run of
the samples both streams cover, the one of the run's median noise, so that a pose its
tracker widened does not become a station."""

from __future__ import annotations

import numpy as np

from services.alignment.pipeline import station_times
from services.alignment.timesync import PoseSeries


def _stream(name: str, n: int, covariance: np.ndarray | None = None,
            systematic: np.ndarray | None = None) -> PoseSeries:
    t = np.arange(n) / 30.0
    q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    return PoseSeries(t, np.zeros((n, 3)), q, name, covariance, systematic=systematic)


def test_a_widened_pose_is_passed_over_for_the_runs_median_noise() -> None:
    """Runs of ten samples whose noise grows slowly, two of each run widened tenthousandfold
    (among them the runs' middles and their evenly spread ends): each run's station is the
    sample of its median noise, never a widened one."""
    n, count = 40, 4
    noise = np.eye(6) * 1e-8 * (1.0 + 0.01 * np.arange(n))[:, None, None]
    widened = [0, 5, 13, 15, 25, 26, 35, 39]
    noise[widened] *= 1e4
    held = np.tile(np.eye(6) * 1e-6, (n, 1, 1))  # larger than the noise, alike everywhere
    a = _stream("a", n, noise + held, held)
    picked = np.rint(station_times(a, _stream("b", n), 0.0, count) * 30.0).astype(int)
    assert picked.tolist() == [6, 16, 24, 34]


def test_without_covariances_the_stations_are_the_runs_middles() -> None:
    a, b = _stream("a", 40), _stream("b", 40)
    picked = np.rint(station_times(a, b, 0.0, 4) * 30.0).astype(int)
    assert picked.tolist() == [5, 15, 25, 35]
    assert len(station_times(a, b, 0.0, 100)) == 40  # no more stations than samples

"""`uma demo --cameras`: two simulated cameras on two agents, a need that follows the camera
seeing the tag best, and world-frame queries across the agents."""

from __future__ import annotations

from services.fiducials.demo import run_demo


def test_camera_demo_follows_the_better_camera_and_answers_in_the_world_frame():
    report = run_demo(seconds=10.0, seed=1, live=False)
    assert report["samples_received"] > 30
    assert report["queries"] >= 5
    assert report["world_error_mm"]["median"] < 10.0
    assert {s["to"] for s in report["switches"]} >= {"cam-right"}  # it moved at least once
    assert not report["errors"], report["errors"]

"""The alignment service: offline on recorded pose pairs, its command line, and live under
an agent (two pose streams in, the static edge and calibration file out, re-calibration)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time
import tomllib
from types import SimpleNamespace

import numpy as np
import pytest
from agent_helpers.harness import agent
from conftest import endpoint, free_port

from agent import geometry as geo
from agent.cli import main
from agent.cli.agent import load_config
from agent.daemon.settings import check_static_edge
from schemas.codec import SYSTEMATIC_COVARIANCE, pack_covariance
from services import frames
from services.alignment import records
from services.alignment.service import StreamBuffer
from services.alignment.simulate import StreamConfig, simulate_streams
from services.alignment.solvers import Pose
from services.sim import mounts

WORLD_B = "lab/world_b"
A_EDGE = f"{frames.WORLD}:{frames.LASER_RIG}"
B_EDGE = f"{WORLD_B}:{frames.ACCEL_RIG}"
#: the truth: accelerometer rig in the laser rig (both on the simulated head)
TRUE_X = Pose(*geo.compose(*geo.inverse(*mounts.HEAD_TO_LASER_RIG), *mounts.HEAD_TO_ACCEL_RIG))
TRUE_WORLD_B = Pose(np.array([0.4, -1.2, 0.9]), geo.rotvec_to_quat([0.2, -0.3, 1.7]))


def _streams(seconds: float, offset_s: float, seed: int = 4):
    return simulate_streams(seed, Pose(*mounts.HEAD_TO_LASER_RIG), TRUE_X, TRUE_WORLD_B,
                            StreamConfig(seconds=seconds, offset_s=offset_s))


def _uma(capsys, *args: str) -> SimpleNamespace:
    """``uma ARGS`` in this process (same code as the console script, no start-up cost)."""
    code = main(list(args))
    out = capsys.readouterr()
    return SimpleNamespace(returncode=code, stdout=out.out, stderr=out.err)


def _check_calibration_file(path) -> dict:
    edge = check_static_edge(load_config(str(path))["static"][0], 0)  # the agent's loader
    assert (edge["parent"], edge["child"]) == (frames.LASER_RIG, frames.ACCEL_RIG)
    dp, dr = geo.pose_error(np.array(edge["position"]), np.array(edge["quaternion"]), *TRUE_X)
    assert dp < 5e-3 and np.degrees(dr) < 0.5, (dp, np.degrees(dr))
    return edge


def test_from_file_aligns_recorded_streams_and_writes_the_agent_config(tmp_path,
                                                                       capsys) -> None:
    a, b = _streams(30.0, 0.045)
    n = min(len(a), len(b))  # one sample of each stream per row
    csv_path = tmp_path / "pairs.csv"
    records.write_pose_pairs(csv_path, *(
        type(s)(s.t[:n], s.position[:n], s.quaternion[:n], s.name) for s in (a, b)))
    out = tmp_path / "calib.toml"
    r = _uma(capsys, "service", "run", "alignment", "--a", A_EDGE, "--b", B_EDGE, "--from-file",
             str(csv_path), "--output", str(out), "--bootstrap", "20", "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert abs(summary["time_offset_s"] - 0.045) < 2e-3
    edge = _check_calibration_file(out)
    assert edge["pos_std_m"] == pytest.approx(summary["pos_std_m"])
    # the same stations, declared synchronous: no offset estimated
    k = np.arange(0, n, 40)
    pb, qb, _ = b.at(a.t[k] + 0.045)
    stations = tmp_path / "stations.csv"
    records.write_pose_pairs(stations, *(
        type(a)(a.t[k], p, q, "s") for p, q in ((a.position[k], a.quaternion[k]), (pb, qb))))
    r = _uma(capsys, "service", "run", "alignment", "--a", A_EDGE, "--b", B_EDGE, "--from-file",
             str(stations), "--stations", "--output", str(out), "--bootstrap", "20")
    assert r.returncode == 0, r.stderr
    assert "time_offset_s: 0.0" in r.stdout
    _check_calibration_file(out)


@pytest.mark.parametrize("args, msg", [
    (["--a", "ivy/world", "--b", B_EDGE, "--from-file", "x.csv"], "expected PARENT:CHILD"),
    (["--a", A_EDGE, "--b", B_EDGE, "--from-file", "/nonexistent.csv"], "cannot read"),
    (["--a", A_EDGE, "--b", "x:*/rig", "--from-file", "x.csv"], "must be a concrete frame"),
    (["--a", A_EDGE, "--b", B_EDGE, "--from-file", "x.csv", "--min-angle-deg", "95"],
     "--min-angle-deg must lie in"),
    (["--a", A_EDGE, "--b", B_EDGE, "--from-file", "NAN"], "qa_w is nan"),
    (["--a", A_EDGE, "--b", B_EDGE, "--from-file", "x.csv", "--bootstrap", "5"],
     "--bootstrap must be >= 9 .*got 5"),
])
def test_bad_command_lines_give_clear_errors(tmp_path, capsys, args, msg) -> None:
    if "NAN" in args:
        path = tmp_path / "nan.csv"
        path.write_text(",".join(records.COLUMNS) + "\n" + ",".join(["0"] * 7 + ["nan"] +
                                                                     ["0"] * 8) + "\n")
        args = [str(path) if x == "NAN" else x for x in args]
    r = _uma(capsys, "service", "run", "alignment", *args)
    assert r.returncode == 1, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr and re.search(msg, r.stderr), r.stderr


def test_help_needs_no_network() -> None:
    r = subprocess.run([sys.executable, "-m", "agent.cli", "service", "run", "alignment",
                        "--help"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "--from-file" in r.stdout and "PARENT:CHILD" in r.stdout
    assert "Traceback" not in r.stderr


def test_stream_buffer_drops_bad_samples_and_restarts_on_a_new_edge() -> None:
    buf = StreamBuffer("stream a", window_s=1.0)
    edge = ("ivy/world", "x/rig")

    def m(t: int, p=(0.0, 0.0, 0.0), q=(0.0, 0.0, 0.0, 1.0), e=edge) -> SimpleNamespace:
        return SimpleNamespace(t_ns=t, position=np.array(p), quaternion=np.array(q), edge=e)

    for t in range(0, 2_000_000_000, 100_000_000):
        buf.add(m(t))
    assert len(buf.samples) == 11  # the last second only
    buf.add(m(1_000_000_000))  # out of order
    buf.add(m(2_000_000_000, p=(np.nan, 0, 0)))
    buf.add(m(2_100_000_000, q=(0, 0, 0, 2.0)))
    assert sum(buf.dropped.values()) == 3 and len(buf.samples) == 11
    buf.add(m(2_200_000_000, e=("ivy/world", "y/rig")))
    assert len(buf.samples) == 1 and buf.edge == ("ivy/world", "y/rig")


def test_stream_buffer_keeps_the_systematic_part_a_tracker_sends() -> None:
    """A laser pose carries the part of its covariance that persists (``extra``); the
    series holds it so that the alignment holds only that part, not the pose's noise too."""
    buf = StreamBuffer("stream a", window_s=10.0)
    held = np.diag([1e-6] * 3 + [1e-8] * 3)

    def m(t: int, extra: dict) -> SimpleNamespace:
        return SimpleNamespace(t_ns=t, position=np.zeros(3), quaternion=np.array(
            [0.0, 0.0, 0.0, 1.0]), edge=None, covariance=2 * held, extra=extra)

    for t in range(3):
        buf.add(m(t * 100_000_000, {SYSTEMATIC_COVARIANCE: pack_covariance(held)}))
    buf.add(m(300_000_000, {SYSTEMATIC_COVARIANCE: [1.0, "x"]}))  # malformed: dropped
    buf.add(m(300_000_000, {SYSTEMATIC_COVARIANCE: [float("nan")] * 21}))  # dropped too
    assert sum(buf.dropped.values()) == 2
    series = buf.series(0)
    np.testing.assert_allclose(series.held_at(np.array([0.1])), held[None])
    buf.add(m(400_000_000, {}))  # one sample without it: nothing is known to persist less
    np.testing.assert_allclose(buf.series(0).held_at(np.array([0.1])), 2 * held[None])


def _feed(realm: str, ep: str, stop: threading.Event, speed: float = 20.0) -> None:
    """Publish simulated streams of both rigs, ``speed`` times faster than real time
    (enough for two minutes, however slow the machine)."""
    from agent import Service

    a, b = _streams(1200.0, 0.06, seed=9)
    merged = sorted([(t, 0, k) for k, t in enumerate(a.t)] + [(t, 1, k) for k, t in
                                                              enumerate(b.t)])
    t0_ns = 1_700_000_000_000_000_000
    with Service("feeder", realm=realm, agent="lab", connect=[ep]) as svc:
        outs = [svc.ability("a", type="pose6d", edge=(frames.WORLD, frames.LASER_RIG),
                            frequency_hz=60.0),
                svc.ability("b", type="pose6d", edge=(WORLD_B, frames.ACCEL_RIG),
                            frequency_hz=100.0)]
        svc.start()
        start = time.monotonic()
        for t, which, k in merged:
            if stop.is_set():
                return
            ahead = t / speed - (time.monotonic() - start)
            if ahead > 0:
                time.sleep(ahead)
            s = (a, b)[which]
            outs[which].publish(t0_ns + int(t * 1e9), s.position[k], s.quaternion[k])


def test_live_service_publishes_the_static_edge_and_recalibrates(processes, realm,
                                                                 tmp_path) -> None:
    from agent import Client

    ep = endpoint(free_port())
    out = tmp_path / "alignment.toml"
    agent(processes, realm, "lab", ep)  # up before its services start
    svc = processes.start("service", "run", "alignment", "--realm", realm, "--agent", "lab",
                          "--connect", ep, "--a", A_EDGE, "--b", B_EDGE, "--output", str(out),
                          "--max-offset-ms", "200", "--bootstrap", "20",
                          "--min-seconds", "40")
    stop = threading.Event()
    feeder = threading.Thread(target=_feed, args=(realm, ep, stop), daemon=True)
    feeder.start()
    try:
        deadline = time.monotonic() + 60
        while not out.exists():
            assert svc.poll() is None, svc.stderr.read()
            assert time.monotonic() < deadline, "no calibration within 60 s"
            time.sleep(0.2)
        first = _check_calibration_file(out)
        with Client(realm=realm, connect=[ep]) as client:  # the edge is in the SRG
            while True:
                try:
                    r = client.pose(frames.LASER_RIG, frames.ACCEL_RIG)
                    break
                except (LookupError, ValueError) as exc:
                    assert time.monotonic() < deadline, f"edge not in the SRG: {exc}"
                    time.sleep(0.2)
        assert np.allclose(r.position, first["position"], atol=1e-9)
        assert r.attributes.get("pos_std_m") == pytest.approx(first["pos_std_m"])
        written = out.stat().st_mtime_ns
        # what a user types: the command asks the service through request_recalibration
        asked = subprocess.run(
            [sys.executable, "-m", "agent.cli", "service", "recalibrate", "--agent", "lab",
             "--realm", realm, "--connect", ep, "--timeout", "10", "--json"],
            capture_output=True, text=True, timeout=60)
        assert asked.returncode == 0, asked.stderr
        ack = json.loads(asked.stdout)
        assert ack["ok"] and ack["previous"]["pairs_inlier"] > 0
        while out.stat().st_mtime_ns == written:
            assert svc.poll() is None, svc.stderr.read()
            assert time.monotonic() < deadline + 30, "no re-calibration"
            time.sleep(0.2)
        _check_calibration_file(out)
        assert tomllib.loads(out.read_text())["static"][0]["parent"] == frames.LASER_RIG
    finally:
        stop.set()
        feeder.join(timeout=10)


def test_recalibrate_command_names_what_it_could_not_reach(realm) -> None:
    base = [sys.executable, "-m", "agent.cli", "service", "recalibrate", "--agent", "lab",
            "--realm", realm, "--timeout", "1"]
    down = subprocess.run([*base, "--connect", endpoint(free_port())], capture_output=True,
                          text=True, timeout=60)
    assert down.returncode == 1 and "cannot reach tcp/127.0.0.1:" in down.stderr
    bad = subprocess.run([*base[:-1], "0"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1 and "--timeout must be positive" in bad.stderr
    assert "Traceback" not in down.stderr + bad.stderr

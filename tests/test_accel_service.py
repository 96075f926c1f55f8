"""The accel-rig service: its sample loop without a network, its command line, and the
service under a real agent (abilities in ``uma services``, pose through ``Client.pose``).

Hogue 2003: Hogue, *MARVIN: a Mobile Automatic Realtime Visual and INertial tracking
system*, MSc thesis, York University 2003.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np
import pytest
from agent_helpers.harness import agent
from conftest import endpoint, free_port

from agent import geometry as geo
from agent.errors import UmaError
from services import frames
from services.accel_rig.calibration import THESIS_POSES
from services.accel_rig.service import LiveRig, parse_mount
from services.accel_rig.simulator import (
    axis_down_quaternion,
    default_device,
    simulate,
    simulate_static,
)
from services.accel_rig.sources import LineSource, parse_line
from services.sim import mounts
from services.sim.trajectory import HeadTrajectory
from services.sim.world import SIM_EPOCH_NS, sim_time_s

RATE = 300.0


class _Out:
    """Stands in for an ability handle: records what would be published."""

    def __init__(self) -> None:
        self.items: list = []

    def publish(self, *args, **kw) -> None:
        self.items.append((args, kw))

    def publish_measurement(self, m) -> None:
        self.items.append(m)


def _head_sample(traj: HeadTrajectory, t_ns: int) -> SimpleNamespace:
    p, q = traj.pose(sim_time_s(t_ns))
    return SimpleNamespace(t_ns=t_ns, position=p[0], quaternion=q[0], covariance=None)


def test_live_rig_resets_from_head_poses_and_tracks_the_rig():
    device = default_device()
    cal = device.calibration(RATE)
    traj = HeadTrajectory(1)
    t0 = 40.0
    sim = simulate(traj, 3.0, RATE, seed=3, t0=t0, sensor=device)
    live = LiveRig(cal, RATE, mounts.HEAD_TO_ACCEL_RIG, reset_every_s=1.0)
    live.raw_out, live.pose_out = _Out(), _Out()
    t_ns = SIM_EPOCH_NS + np.round(sim.t * 1e9).astype(np.int64)
    errors = []
    for k in range(len(sim.t)):
        if k % 10 == 0:  # 30 Hz absolute head poses, arriving with the samples
            live.on_reset(_head_sample(traj, int(t_ns[k] - 5_000_000)))
        live.process(int(t_ns[k]), sim.volts[k])
        if live.pose_out.items:
            (stamp, p, q), kw = live.pose_out.items[-1]
            true = traj.state(sim_time_s(stamp)).rigid_offset(*mounts.HEAD_TO_ACCEL_RIG)
            dp, dq = geo.pose_error(p, q, true.position[0], true.quaternion[0])
            since = (stamp - SIM_EPOCH_NS) * 1e-9 - t0 - live.last_reset
            errors.append((since, float(dp), float(np.degrees(dq))))
            geo.check_covariance(kw["covariance"])
    assert len(live.raw_out.items) == len(sim.t)  # every sample's accelerations go out
    m = live.raw_out.items[0]
    assert m.type == "accel_raw" and m.values.shape == (6,)
    assert live.counts["resets"] == 3  # once a second, not at every absolute pose
    err = np.array(errors)
    fresh = err[err[:, 0] < 0.05]  # just after a reset: the absolute pose itself
    assert len(fresh) > 20 and fresh[:, 1].max() < 0.002 and fresh[:, 2].max() < 0.1
    # then inertial drift, within a second (Hogue 2003, ch. 4: reliable for about a second)
    assert err[:, 1].max() < 0.05 and err[:, 2].max() < 2.5, err.max(axis=0)


def test_live_rig_counts_bad_samples_and_keeps_running():
    device = default_device()
    live = LiveRig(device.calibration(RATE), RATE, None, reset_every_s=1.0)
    live.raw_out, live.pose_out = _Out(), _Out()
    good = simulate_static(axis_down_quaternion("-z"), 0.1, RATE, sensor=device)
    for dt_ns in range(-50_000_000, 1, 10_000_000):  # 50 ms of poses of a rig at rest
        live.on_reset(SimpleNamespace(t_ns=SIM_EPOCH_NS + dt_ns, position=np.zeros(3),
                                      quaternion=geo.rotvec_to_quat([np.pi, 0, 0]),
                                      covariance=None))
    live.process(SIM_EPOCH_NS, good[0])
    bad = good[1].copy()
    bad[3] = np.nan
    live.process(SIM_EPOCH_NS + 3_333_333, bad)
    live.process(SIM_EPOCH_NS + 6_666_666, np.full(6, 3.0))
    live.process(SIM_EPOCH_NS + 10_000_000, good[2])
    assert live.counts["accelerometer sample refused"] == 2
    assert len(live.pose_out.items) == 2 and len(live.raw_out.items) == 2  # the good ones


def test_recorded_lines_are_parsed_or_refused_with_the_line(tmp_path):
    t, v = parse_line("12.5, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6", 6, "x")
    assert t == 12.5 and v.tolist() == [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    assert parse_line("# comment", 6, "x") is None
    with pytest.raises(ValueError, match=r"rec\.csv line 3: expected a timestamp and 6"):
        parse_line("1 2 3", 6, "rec.csv line 3")
    with pytest.raises(ValueError, match="not a number"):
        parse_line("1 a 2 3 4 5 6", 6, "x")
    path = tmp_path / "rec.csv"
    path.write_text("t,v1,v2,v3,v4,v5,v6\n0.0 0 0 0 0 0 0\nbroken\n0.01 1 1 1 1 1 1\n")
    src = LineSource.open(f"csv:{path}", 6, speed=0.0)
    items = list(src.samples())
    src.close()
    assert isinstance(items[1], ValueError) and "line 3" in str(items[1])
    (t0, _), (t1, v1) = items[0], items[2]
    assert t1 - t0 == 10_000_000 and v1.tolist() == [1.0] * 6
    with pytest.raises(ValueError, match="expected sim, csv:FILE or serial:DEVICE"):
        LineSource.open("usb:x", 6, 1.0)
    with pytest.raises(ValueError, match="cannot open"):
        LineSource.open(f"csv:{tmp_path / 'none.csv'}", 6, 1.0)


def test_mount_option():
    p, q = parse_mount("0.1,0,0,0,0,0,1")
    assert p.tolist() == [0.1, 0, 0] and q.tolist() == [0, 0, 0, 1]
    with pytest.raises(ValueError, match="expected 7 numbers"):
        parse_mount("1,2,3")
    with pytest.raises(ValueError, match="not a unit quaternion"):
        parse_mount("0,0,0,0,0,0,2")


def _uma(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "agent.cli", *args], capture_output=True,
                          text=True, timeout=timeout)


def test_calibrate_command_with_simulator_and_with_recordings(tmp_path):
    out = tmp_path / "cal.json"
    r = _uma("service", "run", "accel-rig", "--calibrate", "--pose-seconds", "0.5",
             "--calibration", str(out))
    assert r.returncode == 0, r.stderr
    assert "pose 6/6" in r.stdout and "error: bias" in r.stdout
    assert json.loads(out.read_text())["format"].startswith("uma.accel_rig.calibration")
    # recorded static poses (the thesis' four), as files of 't v1 .. v6' lines
    device = default_device()
    args = []
    for i, label in enumerate(THESIS_POSES):
        v = simulate_static(axis_down_quaternion(label), 1.0, RATE, seed=i, sensor=device)
        f = tmp_path / f"pose{i}.csv"
        f.write_text("".join(f"{k / RATE:.6f} " + " ".join(f"{x:.3f}" for x in row) + "\n"
                             for k, row in enumerate(v)))
        args.append(f"--pose={label}={f}")  # "=": labels like -x are not options
    out2 = tmp_path / "cal2.json"
    r = _uma("service", "run", "accel-rig", "--calibrate", *args, "--calibration", str(out2))
    assert r.returncode == 0, r.stderr
    assert "pose +x: 300 samples" in r.stdout
    cal = json.loads(out2.read_text())
    assert abs(np.array(cal["bias_v"]) - device.bias_v).max() < 1e-3


@pytest.mark.parametrize("args, msg", [
    (["--source", "csv:/nonexistent.csv"], "real input needs --calibration"),
    (["--calibration", "/nonexistent.json"], "No such file"),
    (["--rate-hz", "0"], "--rate-hz must be within"),
    (["--calibrate", "--pose", "+x=/nonexistent.csv"], "cannot read"),
    (["--calibrate", "--pose", "up=/x.csv"], "expected one of"),
    (["--pose", "+x=a.csv"], "--pose is for --calibrate"),
    (["--mount", "1,2"], "expected 7 numbers"),
])
def test_bad_options_are_refused_with_the_reason(args, msg):
    import argparse
    import threading

    from agent.runtime import plugins
    from services.accel_rig.plugin import ACCEL_RIG

    parser = argparse.ArgumentParser()
    plugins.add_service_arguments(parser, ACCEL_RIG)
    with pytest.raises(ValueError, match=re.escape(msg)):
        plugins.runner(ACCEL_RIG.run)(parser.parse_args(args), threading.Event())


def test_the_command_line_prints_errors_without_traceback():
    r = _uma("service", "run", "accel-rig", "--source", "serial:/nonexistent/tty",
             "--calibration", "/nonexistent.json")
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert "calibration file '/nonexistent.json'" in r.stderr


def test_service_runs_under_an_agent_and_is_listed(processes, realm):
    from agent import Client

    ep = endpoint(free_port())
    agent(processes, realm, "lab", ep)  # up before its services start
    processes.start("service", "run", "sim", "--realm", realm, "--agent", "lab", "--connect",
                    ep, "--seed", "2")
    acc = processes.start("service", "run", "accel-rig", "--realm", realm, "--agent", "lab",
                          "--connect", ep, "--seed", "2", "--reset-every", "0.5")
    deadline = time.monotonic() + 60
    with Client(realm=realm, connect=[ep]) as client:
        while True:
            assert acc.poll() is None, acc.stderr.read()
            try:
                r = client.pose(frames.WORLD, frames.ACCEL_RIG)
                break
            except (UmaError, LookupError) as exc:
                assert time.monotonic() < deadline, f"no accel-rig pose: {exc}"
                time.sleep(0.3)
    true = HeadTrajectory(2).state(sim_time_s(r.stamps[0][0])).rigid_offset(
        *mounts.HEAD_TO_ACCEL_RIG)
    dp, dq = geo.pose_error(r.position, r.quaternion, true.position[0], true.quaternion[0])
    assert dp < 0.05 and np.degrees(dq) < 2.0, (dp, np.degrees(dq))
    services: dict = {}
    while "accel-rig" not in services:  # under heavy load a listing can miss a service
        assert time.monotonic() < deadline + 30, f"accel-rig never listed: {services}"
        listing = _uma("services", "--realm", realm, "--connect", ep, "--json", timeout=60)
        assert listing.returncode == 0, listing.stderr
        services = {s["service_id"]: s for a in json.loads(listing.stdout)["agents"]
                    for s in a["services"]}
    rig = services["accel-rig"]
    kinds = {a["name"]: (a["type"], tuple(a["edge"])) for a in rig["abilities"]}
    assert kinds == {"accel": ("accel_raw", (frames.WORLD, frames.ACCEL_RIG)),
                     "pose": ("pose6d", (frames.WORLD, frames.ACCEL_RIG))}
    accel = next(a for a in rig["abilities"] if a["name"] == "accel")
    assert len(accel["attributes"]["axes"]) == 6 and accel["attributes"]["frequency_hz"] == 300
    reset = rig["needs"][0]
    assert reset["name"] == "reset" and reset["matches"][0]["service_id"] == "sim"


def test_the_sample_loop_logs_an_internal_error_and_goes_on(monkeypatch, caplog):
    """Whatever goes wrong on one sample (here a simulated bug), the service keeps serving."""
    import argparse
    import logging
    import threading

    import agent
    from services.accel_rig import service

    class FakeService:
        def __init__(self, *args, **kw) -> None:
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc) -> None:
            pass

        def ability(self, *args, **kw):
            return _Out()

        def need(self, *args, **kw) -> None:
            pass

        def start(self) -> None:
            pass

    device = default_device()
    volts = simulate_static(axis_down_quaternion("-z"), 0.1, RATE, sensor=device)
    source = SimpleNamespace(name="test", samples=lambda: iter(
        [(SIM_EPOCH_NS + round(k * 1e9 / RATE), v) for k, v in enumerate(volts)]))
    processed = []
    real_process = service.LiveRig.process

    def process(self, t_ns, v):
        if len(processed) == 3:
            processed.append("bug")
            raise KeyError("simulated bug")
        processed.append(t_ns)
        real_process(self, t_ns, v)

    monkeypatch.setattr(agent, "Service", FakeService)
    monkeypatch.setattr(service.LiveRig, "process", process)
    caplog.set_level(logging.WARNING, logger="uma.accel_rig")
    args = argparse.Namespace(reset_frame="*/head", rate_hz=RATE, mount=None, reset_every=1.0,
                              id="accel-rig", realm="r", agent=None, connect=[], listen=[],
                              ttl_s=1.0)
    assert service._serve(args, device.calibration(RATE), source, threading.Event()) == 0
    assert len(processed) == len(volts)  # every sample after the failing one as well
    bug = [r.getMessage() for r in caplog.records if "internal error" in r.getMessage()]
    assert len(bug) == 1 and "KeyError" in bug[0] and "simulated bug" in bug[0]

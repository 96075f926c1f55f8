"""Recording throughput against the raw ``mcap`` writer, and replay timing, in one run.

1. Throughput: ``--samples`` pose samples (the exact msgpack bytes ``AbilityHandle.publish``
   sends) on ``--keys`` data keys go through ``RecordingSink`` (the writer of ``uma record``:
   queue, writer thread, sample-time peek, chunking, zstd, indexes; with and without the
   ROS 2 ``/tf`` channel) and, as the anchor, straight into ``mcap.writer.Writer``
   (``add_message`` on the same channels, same chunk size and compression).  Each of
   ``--rounds`` rounds times every writer on the same samples; the figures are the cost per
   sample (median and p99 over rounds) and the samples/s and MB/s that follow from the
   median, with the ratio to the raw writer.
2. Replay timing: a recording of 3 streams at 100 Hz for ``--play-s`` seconds is played by
   ``uma play --rate 1`` (a real process) into a real ``uma agent`` on loopback; ``uma
   play`` measures |actual - scheduled| publish time of every sample.  The anchor is the
   same schedule kept by a bare ``time.sleep`` loop in this process.

Usage: python bench/bench_record.py [--samples N] [--keys K] [--rounds R] [--play-s S] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType, Writer
from summary import cpu_model, median_p99, report

from agent import geometry as geo
from agent.protocol import keys
from agent.protocol.registration import snapshot_message
from agent.record.sink import CHUNK_BYTES, QUEUE_SIZE, RecordingSink
from agent.runtime.processes import stop_processes
from schemas.codec import encode_descriptor, encode_pose
from schemas.models import Ability, ServiceDescriptor

REALM = "bench"
ROOT = Path(__file__).resolve().parents[1]


def _snapshot(n_keys: int) -> tuple[str, bytes, list[str]]:
    abilities = [Ability(name=f"p{i}", type="pose6d", edge=("lab/world", f"obj{i}/body"),
                         attributes={"frequency_hz": 100.0}) for i in range(n_keys)]
    desc = ServiceDescriptor(service_id="src", agent_id="a1", abilities=abilities)
    data = snapshot_message({"agent_id": "a1", "realm": REALM}, 1, 1,
                            [{"descriptor": encode_descriptor(desc), "instance": "i"}])
    data_keys = [keys.data(REALM, "a1", "src", a.name) for a in abilities]
    return keys.agent_services(REALM, "a1"), data, data_keys


def _samples(n: int, data_keys: list[str], rate_hz: float = 100.0) -> list[tuple[str, bytes,
                                                                            int]]:
    rng = np.random.default_rng(0)
    t0 = time.time_ns()
    out = []
    for i in range(n):
        t = t0 + int(i / len(data_keys) / rate_hz * 1e9)
        out.append((data_keys[i % len(data_keys)],
                    encode_pose(t, rng.normal(size=3), geo.rotvec_to_quat(rng.normal(size=3)),
                                seq=i // len(data_keys) + 1), t))
    return out


def _uma(path: str, snap: tuple[str, bytes], samples: list, ros: bool) -> float:
    t0 = time.perf_counter()
    sink = RecordingSink(path, REALM, [], ros=ros, queue_size=max(QUEUE_SIZE, len(samples) + 1))
    sink.offer(snap[0], snap[1], samples[0][2])
    for key, data, t in samples:
        sink.offer(key, data, t)
    stats = sink.close()
    took = time.perf_counter() - t0
    if stats.error or sum(stats.dropped.values()):
        raise SystemExit(f"the recording lost samples: {stats.error or dict(stats.dropped)}")
    return took


def _raw(path: str, samples: list, data_keys: list[str]) -> float:
    t0 = time.perf_counter()
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        w.start(profile="", library="bench")
        channels = {k: w.register_channel(k, "msgpack", 0) for k in data_keys}
        for key, data, t in samples:
            w.add_message(channels[key], log_time=t, data=data, publish_time=t)
        w.finish()
    return time.perf_counter() - t0


def throughput(n: int, n_keys: int, rounds: int) -> dict[str, object]:
    topic, snap, data_keys = _snapshot(n_keys)
    samples = _samples(n, data_keys)
    mb = sum(len(d) for _, d, _ in samples) / 1e6
    us: dict[str, list[float]] = {"raw_mcap": [], "uma_record": [], "uma_record_no_ros": []}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(rounds):
            us["raw_mcap"].append(_raw(f"{tmp}/raw.mcap", samples, data_keys) / n * 1e6)
            us["uma_record"].append(_uma(f"{tmp}/uma.mcap", (topic, snap), samples, True)
                                    / n * 1e6)
            us["uma_record_no_ros"].append(_uma(f"{tmp}/noros.mcap", (topic, snap), samples,
                                                False) / n * 1e6)
    out: dict[str, object] = {"samples": n, "keys": n_keys, "rounds": rounds,
                              "payload_bytes_per_sample": mb * 1e6 / n}
    for name, values in us.items():
        med = float(np.median(values))
        out.update({f"{name}_{k}": v for k, v in median_p99(values, "us_per_sample").items()})
        out[f"{name}_samples_per_s"] = 1e6 / med
        out[f"{name}_mb_per_s"] = mb / (med * n / 1e6)
    base = float(np.median(us["raw_mcap"]))
    out["ratio_uma_record_to_raw"] = float(np.median(us["uma_record"])) / base
    out["ratio_uma_record_no_ros_to_raw"] = float(np.median(us["uma_record_no_ros"])) / base
    return out


def _free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _sleep_anchor(period_s: float, n: int) -> list[float]:
    """The timing error of a bare sleep loop keeping the same schedule (ms)."""
    start = time.monotonic()
    errors = []
    for i in range(n):
        due = start + i * period_s
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        errors.append(abs(time.monotonic() - due) * 1e3)
    return errors


def replay_timing(play_s: float) -> dict[str, object]:
    topic, snap, data_keys = _snapshot(3)
    samples = _samples(int(play_s * 300), data_keys)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    with tempfile.TemporaryDirectory() as tmp:
        path = f"{tmp}/play.mcap"
        sink = RecordingSink(path, REALM, [], ros=False)
        sink.offer(topic, snap, samples[0][2])
        for key, data, t in samples:
            sink.offer(key, data, t)    # log time = sample time: the schedule is 100 Hz each
        sink.close()
        ep = _free_endpoint()
        agent = subprocess.Popen([sys.executable, "-m", "agent.cli", "agent", "--realm",
                                  "benchplay", "--id", "a1", "--listen", ep], env=env,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            time.sleep(3.0)   # the agent's start-up
            out = subprocess.run([sys.executable, "-m", "agent.cli", "play", path, "--realm",
                                  "benchplay", "--agent", "a1", "--connect", ep, "--json"],
                                 env=env, capture_output=True, text=True, timeout=play_s + 120)
        finally:
            stop_processes([agent], 5.0)
    if out.returncode != 0:
        raise SystemExit(f"uma play failed: {out.stderr[-500:]}")
    played = json.loads(out.stdout.strip().splitlines()[-1])
    anchor = median_p99(_sleep_anchor(1.0 / 300, len(samples)), "ms")
    e = played["timing_error_ms"]
    return {"replay_samples": played["published"], "replay_recorded_s": played["recorded_s"],
            "replay_pass_s": played["pass_s"][0],
            "replay_timing_error_median_ms": e["median"], "replay_timing_error_p99_ms": e["p99"],
            "sleep_loop_error_median_ms": anchor["median_ms"],
            "sleep_loop_error_p99_ms": anchor["p99_ms"],
            "ratio_replay_to_sleep_loop_median": e["median"] / anchor["median_ms"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=50_000)
    ap.add_argument("--keys", type=int, default=10)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--play-s", type=float, default=10.0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    figures: dict[str, object] = {"cpu": cpu_model()}
    figures.update(throughput(args.samples, args.keys, args.rounds))
    figures.update(replay_timing(args.play_s))
    report(figures, args.json)


if __name__ == "__main__":
    main()

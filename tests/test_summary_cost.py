"""Supernode summaries computed by shortest-path trees describe
the same best local paths as a query plan per frame, boundary frame and error function did,
on random graphs with cycles, parallel and measured edges; they build no query plan."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from conftest import seeds

from agent import geometry as geo
from agent.attributes import SUMMARY_ERRORS
from agent.protocol.query import attributes_from_wire
from agent.srg import Graph, paths
from agent.srg.errorfn import error_function
from agent.srg.supernode import Topology, summarize


def random_attributes(rng: random.Random) -> dict[str, float]:
    """Attributes that make the error functions disagree (a few left out on purpose)."""
    attrs = {"latency_s": rng.uniform(0.0, 0.05), "confidence": rng.uniform(0.5, 1.0),
             "cost": rng.uniform(0.0, 3.0), "pos_std_m": rng.uniform(0.0005, 0.01),
             "rot_std_rad": rng.uniform(0.0, 0.01), "frequency_hz": rng.uniform(10, 200),
             "ttl_s": rng.uniform(0.05, 1.0)}
    return {k: v for k, v in attrs.items() if rng.random() < 0.85}


def random_graph(seed: int, frames: int, extra: int) -> tuple[Graph, list[str]]:
    """A random tree of ``frames`` frames plus ``extra`` more edges (cycles, and parallel
    edges when they join two neighbours), static and measured, with rotations; and a few
    boundary frames (with one name the graph does not know)."""
    rng = random.Random(seed)
    names = [f"s{seed}/f{i}" for i in range(frames)]
    pairs = [(names[rng.randrange(i)], names[i]) for i in range(1, frames)]
    pairs += [tuple(rng.sample(names, 2)) for _ in range(extra)]
    g = Graph()
    for k, (a, b) in enumerate(pairs):
        parent, child = (a, b) if rng.random() < 0.5 else (b, a)
        p = [rng.uniform(-2, 2) for _ in range(3)]
        q = geo.rotvec_to_quat(np.array([rng.uniform(-1, 1) for _ in range(3)]))
        attrs = random_attributes(rng)
        if rng.random() < 0.5:
            g.add_static(parent, child, p, q, source=f"e{k}",
                         **{n: v for n, v in attrs.items() if n != "frequency_hz"})
        else:
            g.add_measurement(parent, child, 1, p, q, source=f"e{k}", **attrs)
    return g, [*rng.sample(names, 3), "elsewhere/x"]


def close(a: object, b: object) -> bool:
    if isinstance(a, float) or isinstance(b, float):
        return a == b or math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-15)
    return a == b


@pytest.mark.parametrize("seed", seeds(6))
@pytest.mark.parametrize("extra", [0, 4])
def test_links_describe_the_best_paths_a_query_would_take(seed: int, extra: int) -> None:
    g, boundary = random_graph(seed, 14, extra)
    s = summarize(g, boundary)
    assert g.plans_built == 0  # no query plan (nor its cache entries) for a summary
    assert len(s["links"]) == sum(1 for part in s["components"] for b in s["boundary"]
                                  if b in part for a in part
                                  if a != b and not (a in s["boundary"] and a < b))
    for link in s["links"]:
        for e in SUMMARY_ERRORS:
            fn = error_function(e)
            old = g.best_paths(link["a"], link["b"], e)[0].attributes
            new = attributes_from_wire(link["attrs"][e])
            assert close(fn.path_value(new), fn.path_value(old)), (link["a"], link["b"], e)
            if extra == 0 or e == "accuracy":  # one simple path, or the same candidates
                assert all(close(new[k], old[k]) for k in old), (link["a"], link["b"], e)


def test_a_topology_is_a_copy_and_summarizes_as_its_graph_did() -> None:
    g, boundary = random_graph(3, 10, 3)
    top = Topology.of(g)
    before = summarize(g, boundary)
    frame = g.frames()[0]
    g.add_measurement(frame, "late/frame", 2, [1, 0, 0], [0, 0, 0, 1], latency_s=0.5)
    for key in top.attrs:  # new samples must not move the copied nominal values
        if not top.attrs[key]["static"]:
            g.add_measurement(*key[:2], 5, [9, 9, 9], [0, 0, 0, 1], source=key[2])
    assert summarize(top, boundary) == before
    assert "late/frame" in summarize(g, boundary)["frames"]


def test_bridges_of_a_multigraph_and_of_a_long_chain() -> None:
    g = Graph()
    for parent, child, source in [("w", "a", "s"), ("a", "b", "s"), ("a", "b", "t"),
                                  ("b", "c", "s"), ("c", "d", "s"), ("d", "b", "s")]:
        g.add_static(parent, child, [1, 0, 0], [0, 0, 0, 1], source=source)
    # parallel edges a-b and the cycle b-c-d are not bridges; w-a is
    assert paths.bridges(g.adjacency()) == {("w", "a", "s")}
    chain = {f"f{i}": [] for i in range(5000)}  # deeper than Python's recursion limit
    for i in range(4999):
        chain[f"f{i}"].append((f"f{i + 1}", i, True))
        chain[f"f{i + 1}"].append((f"f{i}", i, False))
    assert paths.bridges(chain) == set(range(4999))


def test_a_plan_finds_the_route_from_a_frame_behind_hundreds_of_others() -> None:
    """Each agent summarises a link from every one of its 150 frames to the shared one; a
    plan considers at most 66 links of an agent, and the source's own link came after 66
    dead ends (frames only their agent knows): the plan now skips those first."""
    from agent.protocol.query import parse_summary
    from agent.sdk.planner import Segment, plan_routes

    graphs = {}
    for name in ("h0", "h1"):
        g = Graph()
        g.add_static("scale/world", f"{name}/world", [1, 0, 0], [0, 0, 0, 1], pos_std_m=0.01)
        for k in range(150):
            g.add_static(f"{name}/world", f"{name}/f{k}", [0, k, 0], [0, 0, 0, 1])
        g.add_static(f"{name}/world", f"{name}/s0", [0, 0, 1], [0, 0, 0, 1], pos_std_m=0.01)
        graphs[name] = g
    summaries = {name: parse_summary(summarize(g, ["scale/world"]) | {"agent": name, "rev": 1})
                 for name, g in graphs.items()}
    for e in SUMMARY_ERRORS:
        route = plan_routes(summaries, "h0/s0", "h1/s0", error_function(e))[0]
        assert route.segments == [Segment("h0", "h0/s0", "scale/world"),
                                  Segment("h1", "scale/world", "h1/s0")], e

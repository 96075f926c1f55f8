"""The view's page in viser: the text panels and controls (root frame, edge details, the
query box) and the 3D scene (frames as axes, edges coloured by owner agent, static edges
thin and pale, labels, covariance ellipsoids, trails, the last query's path).

Everything is sent only when it changed; frames are one instanced node (viser's batched
axes), edges one line-segment node per owner and kind, so the browser's load grows with the
number of nodes that change, not with the number of frames.
"""

from __future__ import annotations

import itertools
import zlib
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import viser

from agent.view.space import EdgeView, Placed, ellipsoid

#: owner colours (RGB), picked by a stable hash of the agent id
PALETTE = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
           (140, 86, 75), (227, 119, 194), (23, 190, 207), (188, 189, 34))
#: a label follows its frame once it moved this far (m)
LABEL_MOVE_M = 0.005
#: labels moved per call of ``frames(labels=True)``, farthest-moved first: every update is
#: one websocket message (about a millisecond of the view's time), so with many moving
#: frames labels trail their axes rather than slow the page
LABEL_MOVES = 10
#: ellipsoids drawn at most (the frames with the largest covariance are not chosen: the
#: first ones placed are, a stable choice)
MAX_ELLIPSOIDS = 200


def owner_colour(owner: str) -> tuple[int, int, int]:
    return PALETTE[zlib.crc32(owner.encode()) % len(PALETTE)]


def wxyz(q_xyzw: np.ndarray) -> np.ndarray:
    """uma's x y z w quaternions as viser's w x y z."""
    return np.roll(np.asarray(q_xyzw, float), 1, axis=-1)


class Page:
    """The page of one viser server (module docstring).  ``on_query(source, target,
    error)`` answers the query box with Markdown and the path's frames (set once the view
    is connected)."""

    def __init__(self, server: viser.ViserServer, root: str) -> None:
        self.server = server
        self.on_query: Callable[[str, str, str], tuple[str, list[str]]] = (
            lambda *_: ("not connected to the realm yet", []))
        self._sent: dict[str, Any] = {}
        gui = server.gui
        gui.set_panel_label("uma view")
        gui.configure_theme(control_width="large")  # the match table has six columns
        with gui.add_folder("Realm"):
            self.realm = gui.add_markdown("looking at the realm...")
        with gui.add_folder("Matches"):
            self.matches = gui.add_markdown("")
        with gui.add_folder("Events"):
            self.events = gui.add_markdown("")
        with gui.add_folder("Services"):
            self.services = gui.add_markdown("")
        with gui.add_folder("SRG"):
            self.root = gui.add_text("root frame", initial_value=root)
            self.edge = gui.add_dropdown("edge", ["(none)"], initial_value="(none)")
            self.edge_info = gui.add_markdown("select an edge")
            self.placed_info = gui.add_markdown("")
        with gui.add_folder("Query"):
            self.q_source = gui.add_text("source", initial_value=root)
            self.q_target = gui.add_text("target", initial_value="")
            self.q_error = gui.add_text("error", initial_value="hops")
            button = gui.add_button("query")
            self.q_result = gui.add_markdown("")
        self.query_path: list[str] = []

        @button.on_click
        def _(_: Any) -> None:
            text, path = self.on_query(self.q_source.value.strip(), self.q_target.value.strip(),
                                  self.q_error.value.strip() or "hops")
            self.q_result.content = text
            self.query_path = path

        self._labels: dict[str, tuple[Any, np.ndarray]] = {}
        self._label_ids = itertools.count()
        self._ellipsoids: dict[str, Any] = {}
        self._frames: Any = None
        self._edge_nodes: dict[str, Any] = {}
        self._edge_names: list[str] = []

    # ------------------------------------------------------------------ text

    def text(self, handle: Any, content: str) -> None:
        """Set a Markdown panel, only if its text changed."""
        if self._sent.get(id(handle)) != content:
            self._sent[id(handle)] = content
            handle.content = content

    def edge_choices(self, names: list[str]) -> None:
        if names != self._edge_names:
            self._edge_names = names
            self.edge.options = ["(none)", *names]

    # ------------------------------------------------------------------ scene

    def aim(self, positions: np.ndarray) -> None:
        """Point the camera at the placed frames, from far enough to see them all (once:
        afterwards the user moves it)."""
        centre = positions.mean(axis=0)
        span = max(float(np.ptp(positions, axis=0).max()), 0.3)
        self.server.initial_camera.look_at = tuple(centre)
        self.server.initial_camera.position = tuple(centre + span * np.array([1.0, -1.0, 0.7]))

    def frames(self, placed: Placed, labels: bool) -> None:
        """Every placed frame as axes; labels follow when ``labels`` (they cost one message
        each, so they move at a lower rate than the axes)."""
        P = placed.positions.astype(np.float32)
        Q = wxyz(placed.quaternions).astype(np.float32)
        if self._frames is None or len(self._frames.batched_positions) != len(P):
            self._frames = self.server.scene.add_batched_axes(
                "/srg/frames", Q, P, axes_length=0.12, axes_radius=0.006)
        else:
            self._frames.batched_positions = P
            self._frames.batched_wxyzs = Q
        if labels:
            self._update_labels(placed)

    def _update_labels(self, placed: Placed) -> None:
        for frame in set(self._labels) - set(placed.frames):
            self._labels.pop(frame)[0].remove()
        moved = []
        for frame, p in zip(placed.frames, placed.positions, strict=True):
            known = self._labels.get(frame)
            if known is None:
                handle = self.server.scene.add_label(f"/srg/labels/{next(self._label_ids)}", frame,
                                                     position=p, font_screen_scale=0.7)
                self._labels[frame] = (handle, p.copy())
                continue
            distance = float(np.linalg.norm(known[1] - p))
            if distance > LABEL_MOVE_M:
                moved.append((distance, frame, p))
        for _, frame, p in sorted(moved, key=lambda m: -m[0])[:LABEL_MOVES]:
            handle = self._labels[frame][0]
            handle.position = p
            self._labels[frame] = (handle, p.copy())

    def edges(self, placed: Placed, edges: Mapping[str, EdgeView]) -> None:
        """Each edge whose frames are both placed, one node per owner and kind."""
        at = placed.index()
        groups: dict[str, list[tuple[int, int]]] = {}
        for e in edges.values():
            if e.parent in at and e.child in at:
                name = f"/srg/edges/{e.owner}/{'static' if e.static else 'measured'}"
                groups.setdefault(name, []).append((at[e.parent], at[e.child]))
        for name in {n for n in self._edge_nodes if n.startswith("/srg/edges/")} - set(groups):
            self._edge_nodes.pop(name).remove()
        for name, ends in groups.items():
            segs = placed.positions[np.array(ends)]  # (N, 2, 3): parent, child
            owner, kind = name.split("/")[-2:]
            colour = np.array(owner_colour(owner), float)
            if kind == "static":
                colour = 0.5 * colour + 0.5 * 255.0
            self._lines(name, segs, colour, 2.0 if kind == "static" else 5.0)

    def trails(self, segments: np.ndarray) -> None:
        self._lines("/srg/trails", segments, np.array([120.0, 120.0, 120.0]), 1.5)

    def path(self, placed: Placed) -> None:
        """The last query's path, highlighted over its frames that are placed."""
        at = placed.index()
        pts = [placed.positions[at[f]] for f in self.query_path if f in at]
        segs = np.stack([pts[:-1], pts[1:]], axis=1) if len(pts) > 1 else np.zeros((0, 2, 3))
        self._lines("/srg/query_path", segs, np.array([255.0, 200.0, 0.0]), 9.0)

    def ellipsoids(self, placed: Placed,
                   covariances: Mapping[str, tuple[np.ndarray, str]]) -> None:
        """The position covariance of each frame's placing edge, where known
        (``covariances``: frame -> (3x3 covariance in its parent's axes, parent))."""
        at = placed.index()
        chosen = [f for f in placed.frames
                  if f in covariances and covariances[f][1] in at][:MAX_ELLIPSOIDS]
        for frame in set(self._ellipsoids) - set(chosen):
            self._ellipsoids.pop(frame).remove()
        for frame in chosen:
            i = at[frame]
            cov, parent = covariances[frame]
            radii, q = ellipsoid(cov, placed.quaternions[at[parent]])
            handle = self._ellipsoids.get(frame)
            if handle is None:
                handle = self.server.scene.add_icosphere(
                    f"/srg/covariance/{frame}", radius=1.0, color=(90, 90, 220),
                    subdivisions=2, opacity=0.35)
                self._ellipsoids[frame] = handle
            handle.scale = tuple(np.maximum(radii, 1e-4))
            handle.wxyz = wxyz(q)
            handle.position = placed.positions[i]

    def _lines(self, name: str, segs: np.ndarray, colour: np.ndarray, px: float) -> None:
        """A line-segment node, replaced when its count changed, else moved."""
        node = self._edge_nodes.get(name)
        if len(segs) == 0:
            if node is not None:
                self._edge_nodes.pop(name).remove()
            return
        if node is None or len(node.points) != len(segs):
            colours = np.broadcast_to(colour, (*segs.shape[:2], 3))
            self._edge_nodes[name] = self.server.scene.add_line_segments(
                name, segs.astype(np.float32), colours.astype(np.uint8), thickness=px,
                thickness_units="screen")
        else:
            node.points = segs.astype(np.float32)

"""The compiled twins' check against their source: a twin built from other source than the
``.c`` file beside it is not used (its pure-Python code runs, with one warning saying how to
rebuild), and every twin built in this tree is current."""

from __future__ import annotations

import importlib.util
import logging
from pathlib import Path

import pytest

from schemas.native import REBUILD, compiled_twin, source_hash

TWINS = ("agent.srg._kernel", "agent.protocol._wire", "schemas._pose",
         "services.accel_rig._step", "services.outside_in._blobs", "services.outside_in._fit",
         "services.fiducials._kernels", "services.laser_camera._kernels")
#: an environment switch nobody sets: these tests ask for the twin itself
SWITCH = "UMA_TEST_TWINS_UNSET"


def _fake_twin(root: Path, package: str, built_from: str | None, source: str | None) -> str:
    """A package ``package`` under ``root`` with a module ``_twin`` standing for a compiled
    twin built from ``built_from`` (its ``SOURCE_HASH``; None: no hash compiled in) and a
    ``_twin.c`` holding ``source`` (None: no source shipped); its dotted name."""
    home = root / package
    home.mkdir()
    (home / "__init__.py").write_text("")
    if source is not None:
        (home / "_twin.c").write_text(source)
    digest = None
    if built_from is not None:
        (root / "built.c").write_text(built_from)
        digest = source_hash(root / "built.c")
    (home / "_twin.py").write_text(f"SOURCE_HASH = {digest!r}\n")
    return f"{package}._twin"


def _warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


@pytest.mark.parametrize("built_from, source", [("int old;\n", "int new;\n"),
                                                (None, "int new;\n"),
                                                ("int new;\n", None)],
                         ids=["older-source", "no-hash", "no-source"])
def test_a_stale_twin_falls_back_with_one_warning(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture,
        request: pytest.FixtureRequest, built_from: str | None, source: str | None) -> None:
    package = f"stale_{request.node.callspec.id.replace('-', '_')}"
    name = _fake_twin(tmp_path, package, built_from, source)
    monkeypatch.syspath_prepend(str(tmp_path))
    with caplog.at_level(logging.WARNING):
        assert compiled_twin(name, SWITCH) is None
        assert compiled_twin(name, SWITCH) is None
    (message,) = _warnings(caplog)
    assert name in message and REBUILD in message


def test_a_current_twin_is_used_and_the_switch_turns_it_off(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    name = _fake_twin(tmp_path, "current_twin", "int same;\n", "int same;\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with caplog.at_level(logging.WARNING):
        twin = compiled_twin(name, SWITCH)
        monkeypatch.setenv(SWITCH, "1")
        assert compiled_twin(name, SWITCH) is None
    assert twin is not None and twin.__name__ == name
    assert _warnings(caplog) == []


@pytest.mark.parametrize("name", TWINS)
def test_every_twin_built_here_is_current(name: str, caplog: pytest.LogCaptureFixture) -> None:
    if importlib.util.find_spec(name) is None:
        pytest.skip(f"{name} is not built (no C compiler at install)")
    with caplog.at_level(logging.WARNING):
        twin = compiled_twin(name, SWITCH)
    assert twin is not None, f"{name} is stale: {_warnings(caplog)}"

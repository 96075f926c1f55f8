"""The public API: what ``agent.__all__`` promises resolves, and importing the pure parts
pulls in no Zenoh."""

from __future__ import annotations

import subprocess
import sys

import agent


def test_every_public_name_resolves() -> None:
    for name in agent.__all__:
        assert getattr(agent, name).__name__ == name


def test_an_unknown_name_is_a_clear_attribute_error() -> None:
    try:
        agent.Agent  # noqa: B018  (the daemon is not public API)
    except AttributeError as exc:
        assert "'agent' has no attribute 'Agent'" in str(exc)
    else:
        raise AssertionError("agent.Agent resolved")


def test_the_srg_alone_imports_no_zenoh() -> None:
    code = ("import sys, agent, agent.srg\n"
            "from agent.srg import Graph\n"
            "assert 'zenoh' not in sys.modules, 'zenoh imported'\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr


def test_the_agent_never_imports_a_service() -> None:
    """Dependencies go one way (schemas -> agent -> services): the agent finds services,
    evaluations and the commands they add only through plug-in entry points."""
    import re
    from pathlib import Path

    root = Path(agent.__file__).parent
    offenders = [f"{path.relative_to(root.parent)}:{n}"
                 for path in root.rglob("*.py")
                 for n, line in enumerate(path.read_text().splitlines(), 1)
                 if re.match(r"\s*(from|import)\s+services\b", line)
                 or re.search(r"[\"']services\.[a-z_.]+:", line)]
    assert offenders == []


def test_commands_added_by_plugins_are_in_uma_help() -> None:
    from agent.cli.main import build_parser

    text = build_parser().format_help()
    assert "demo" in text
    out = subprocess.run([sys.executable, "-m", "agent.cli", "service", "recalibrate",
                          "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "--agent ID" in out.stdout


def _public_names(module_name: str) -> set[str] | None:
    """The public names of a public module: its ``__all__``, or None (any name without a
    leading ``_``)."""
    import importlib

    return set(getattr(importlib.import_module(module_name), "__all__", ())) or None


def _import_offences(path, own: str | None) -> list[str]:
    """Each import of ``path`` that reaches past the public API, as 'file:line: import';
    ``own`` is the package the file belongs to (it may use its own modules)."""
    import ast

    def allowed(module: str, names: list[str]) -> bool:
        if module == "agent._lazy" and path.name == "__init__.py":
            return True  # how every package of agent exports its names lazily
        if own is not None and (module == own or module.startswith(own + ".")):
            return True
        if module == "agent":
            return all(n in agent.__all__ or f"agent.{n}" in agent.PUBLIC_MODULES
                       for n in names)
        if module not in agent.PUBLIC_MODULES:
            return False
        public = _public_names(module)
        return all(not n.startswith("_") and (public is None or n in public) for n in names)

    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and (
                node.module == "agent" or node.module.startswith("agent.")):
            names = [a.name for a in node.names]
            if not allowed(node.module, names):
                found.append(f"{path}:{node.lineno}: from {node.module} import "
                             f"{', '.join(names)}")
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("agent.") and not allowed(a.name, []):
                    found.append(f"{path}:{node.lineno}: import {a.name}")
    return found


def test_services_view_and_record_use_only_the_public_api() -> None:
    """Services, ``uma view``, ``uma record`` and the examples import ``agent``'s
    ``__all__`` and the modules ``agent.PUBLIC_MODULES`` names (only their public names),
    never the internals; view and record may use their own modules."""
    from pathlib import Path

    root = Path(agent.__file__).parent.parent
    offences = []
    for folder, own in (("services", None), ("agent/view", "agent.view"),
                        ("agent/record", "agent.record"), ("examples", None)):
        for path in sorted((root / folder).rglob("*.py")):
            offences += _import_offences(path.relative_to(root), own)
    assert offences == [], "imports of agent internals:\n" + "\n".join(offences)


def test_the_import_check_names_an_internal_import(tmp_path, monkeypatch) -> None:
    """The check above fails on an internal import, naming the file, the line and what it
    imports (the check itself can fail)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "m.py").write_text("from agent.sdk.client import Client\n"
                                   "from agent import Client, geometry\n"
                                   "from agent.runtime import RateLimitedLog\n"
                                   "from agent.geometry import _SMALL_ANGLE\n"
                                   "import agent.daemon.agent\n")
    from pathlib import Path

    assert _import_offences(Path("m.py"), None) == [
        "m.py:1: from agent.sdk.client import Client",
        "m.py:4: from agent.geometry import _SMALL_ANGLE",
        "m.py:5: import agent.daemon.agent"]


def test_every_public_module_imports_without_zenoh_and_its_names_resolve() -> None:
    """The public modules are light to import (a plug-in's module is imported by ``uma
    --help``) and every name they list resolves."""
    code = ("import sys, importlib, agent\n"
            "for m in agent.PUBLIC_MODULES:\n"
            "    importlib.import_module(m)\n"
            "assert 'zenoh' not in sys.modules, 'zenoh imported'\n"
            "for m in agent.PUBLIC_MODULES:\n"
            "    mod = importlib.import_module(m)\n"
            "    for n in getattr(mod, '__all__', ()):\n"
            "        assert getattr(mod, n) is not None, (m, n)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr


def _imported(path) -> list[tuple[int, str]]:
    """(line, module) of every absolute import of a file (``from M import x`` gives M)."""
    import ast

    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
        elif isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
    return found


def test_protocol_and_srg_depend_only_on_schemas_and_the_pure_modules() -> None:
    """``agent/protocol`` and ``agent/srg`` import nothing of uma but ``schemas``, their own
    package and the pure modules beside them, and not each other (docs/ARCHITECTURE.md)."""
    from pathlib import Path

    root = Path(agent.__file__).parent
    pure = {"agent", "agent.geometry", "agent.attributes", "agent.result", "agent.errors",
            "agent._lazy"}
    offences = []
    for package in ("protocol", "srg"):
        for path in sorted((root / package).rglob("*.py")):
            offences += [f"{path.name}:{line}: {n}" for line, n in _imported(path)
                         if n.startswith("agent") and n not in pure
                         and not n.startswith(f"agent.{package}")]
    assert offences == []


def test_the_daemon_and_the_sdk_never_import_each_other() -> None:
    """Neither ``agent/daemon`` nor ``agent/sdk`` imports the other, not even inside a
    function (docs/ARCHITECTURE.md): the agent gets the SDK's client handed in."""
    from pathlib import Path

    root = Path(agent.__file__).parent
    offences = []
    for package, other in (("daemon", "sdk"), ("sdk", "daemon")):
        for path in sorted((root / package).rglob("*.py")):
            offences += [f"{package}/{path.name}:{line}: {n}" for line, n in _imported(path)
                         if n.startswith(f"agent.{other}")
                         or (n == "agent" and package == "daemon")]
    assert offences == []


def test_every_error_a_user_sees_is_an_uma_error_and_keeps_its_builtin_base() -> None:
    """One ``except UmaError`` catches what the SDK raises at its user; code that catches
    the builtin base (``ValueError``, ``LookupError``, ``TimeoutError``) still does."""
    import pytest

    from agent import Graph, UmaError
    from agent import geometry as geo
    from agent.errors import InvalidInputError, NotFoundError, UmaTimeoutError
    from agent.sdk.planner import RouteError, SegmentError
    from agent.sdk.query import check_time
    from agent.srg import errors
    from schemas.codec import DecodeError
    from schemas.expr import ExprError

    for cls, base in ((InvalidInputError, ValueError), (NotFoundError, LookupError),
                      (DecodeError, ValueError), (ExprError, ValueError),
                      (UmaTimeoutError, TimeoutError), (errors.SrgLookupError, LookupError),
                      (errors.BadErrorFunctionError, ValueError), (RouteError, LookupError),
                      (SegmentError, LookupError)):
        assert issubclass(cls, UmaError) and issubclass(cls, base), cls
    g = Graph()
    g.add_static("a/w", "a/b", [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    with pytest.raises(UmaError, match="unknown frame 'a/x'"):
        g.pose("a/w", "a/x")
    with pytest.raises(UmaError, match="error function"):
        g.pose("a/w", "a/b", error="no such thing +")
    with pytest.raises(UmaError, match="not a unit quaternion"):
        geo.check_quaternion([0.0, 0.0, 0.0, 2.0])
    with pytest.raises(UmaError, match="integer ns"):
        check_time(1.5)
    from agent import Service
    pose = Service("s", realm="lab", agent="hostA").ability(
        "pose", type="pose6d", edge=("a/w", "a/b"))
    with pytest.raises(UmaError, match="ability 'pose': position"):
        pose.publish(1, [0.0, float("nan"), 0.0], [0.0, 0.0, 0.0, 1.0])


def test_services_raise_no_plain_builtin_errors() -> None:
    """A service's argument and input checks raise ``InvalidInputError`` (an ``UmaError``
    and a ``ValueError``), as the SDK does, never a bare ``ValueError``."""
    import ast
    from pathlib import Path

    import services

    offences = []
    for path in sorted(Path(services.__file__).parent.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call)
                    and isinstance(node.exc.func, ast.Name) and node.exc.func.id == "ValueError"):
                offences.append(f"{path.name}:{node.lineno}")
    assert offences == []
    from agent import UmaError
    from services.accel_rig.sensor import NoiseModel
    from services.vrpn.protocol import ProtocolError

    assert issubclass(ProtocolError, UmaError) and issubclass(ProtocolError, ValueError)
    import pytest

    with pytest.raises(UmaError, match="conversions"):
        NoiseModel(1e-6, 1e-3, True, None, 0, 0.0)


def test_plugin_declarations_import_no_zenoh_and_name_what_runs() -> None:
    """Every service and evaluation plug-in is declared in a module light to import (``uma
    service run NAME --help`` loads it), and its ``run`` names a function that exists."""
    code = ("import sys\n"
            "from agent.runtime import plugins\n"
            "found = [plugins.load(plugins.SERVICE_GROUP, n)\n"
            "         for n in plugins.names(plugins.SERVICE_GROUP)]\n"
            "assert 'zenoh' not in sys.modules, 'zenoh imported'\n"
            "found += [plugins.load(plugins.EVAL_GROUP, n)\n"
            "          for n in plugins.names(plugins.EVAL_GROUP)]\n"
            "assert len(found) >= 13, len(found)\n"
            "for p in found:\n"
            "    assert isinstance(p.run, str) and callable(plugins.runner(p.run)), p.name\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr


def test_real_hardware_code_never_imports_the_simulator() -> None:
    """The trackers that run on a real site (the laser tracker and its calibration, the dead
    reckoner, the fusion) know the installation (``services.installation``), never the
    simulator (``services.sim``), which is built on the installation model."""
    from pathlib import Path

    root = Path(agent.__file__).parent.parent / "services"
    real = [*(root / "installation").glob("*.py"), root / "kinematics.py", root / "frames.py",
            *(root / "laser_camera" / f"{m}.py" for m in ("tracker", "calibration", "pose",
                                                           "homography", "detection")),
            *(root / "accel_rig" / f"{m}.py" for m in ("integrator", "rig", "sensor",
                                                        "calibration", "pose_rates")),
            *(root / "fusion" / f"{m}.py" for m in ("dots", "service", "ekf", "state",
                                                     "tracker", "measurements", "process"))]
    offences = []
    for path in real:
        offences += [f"{path.relative_to(root.parent)}:{line}: {n}"
                     for line, n in _imported(path)
                     if n == "services.sim" or n.startswith("services.sim.")]
    assert len(real) > 20 and offences == []


def test_every_public_name_is_in_the_readme() -> None:
    """The README's table of the public API names everything ``agent.__all__`` and the
    public modules' ``__all__`` export (a name added without a word there fails here)."""
    import importlib
    from pathlib import Path

    readme = (Path(agent.__file__).parents[1] / "README.md").read_text()
    missing = [f"{m}.{n}" for m in ("agent", *agent.PUBLIC_MODULES)
               for n in getattr(importlib.import_module(m), "__all__", ())
               if f"`{n}`" not in readme]
    assert missing == []

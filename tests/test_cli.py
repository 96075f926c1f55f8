"""The ``uma`` command line as a user meets it: help, version, exit codes 0/1/2, messages.

Each subcommand's help and argparse's refusals are asked of :func:`agent.cli.main.main` in
this process (the parser and its messages, about 0.25 s of CPU less a case than a new
interpreter); the executable itself (its exit codes, no traceback) is run as a process by
the other tests here."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from agent.cli.main import main
from schemas import export
from schemas.models import MODELS


def uma(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "agent.cli", *args], capture_output=True,
                          text=True, timeout=timeout, check=False)


def uma_here(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """``uma ARGS`` in this process: its exit code (argparse's SystemExit's too), stdout
    and stderr."""
    try:
        code = main(list(args))
    except SystemExit as stop:
        code = stop.code
    out = capsys.readouterr()
    return code, out.out, out.err


COMMANDS = ["agent", "router", "service", "services", "query", "demo", "eval", "schemas",
            "record", "play", "info", "view", "calibrate", "markers"]


def test_top_level_help_lists_every_command() -> None:
    r = uma("--help")
    assert r.returncode == 0, r.stderr
    assert "ubiquitous tracking" in r.stdout
    for command in COMMANDS:
        assert f"\n    {command} " in r.stdout or f"\n    {command}\n" in r.stdout, command


@pytest.mark.parametrize(("args", "purpose"), [
    (["agent"], "per-host agent"),
    (["router"], "Zenoh router"),
    (["service"], "tracker service"),
    (["services"], "each agent, service, need, ability"),
    (["query"], "pose of frame TARGET in frame SOURCE"),
    (["demo"], "simulated IVY world"),
    (["view"], "shows a realm live"),
    (["schemas"], "JSON Schemas"),
    (["schemas", "export"], "output directory"),
    (["eval"], "accuracy against simulated ground truth"),
    (["service", "run"], "Known services"),
    (["record"], "losslessly into FILE.mcap"),
    (["play"], "recorded timing scaled by --rate"),
    (["info"], "read up to the damage"),
    (["calibrate"], "'uma.calibrate' entry-point group"),
    (["calibrate", "camera"], "printed ChArUco board"),
    (["markers", "print"], "Print at 100 %"),
])
def test_every_command_explains_itself(capsys, args: list[str], purpose: str) -> None:
    code, out, err = uma_here(capsys, *args, "--help")
    assert code == 0, err
    assert out.startswith(f"usage: uma {' '.join(args)}")
    assert purpose in " ".join(out.split())


def test_version() -> None:
    r = uma("--version")
    assert r.returncode == 0
    assert r.stdout.startswith("uma ")
    assert r.stdout.split()[1][0].isdigit() or "unknown" in r.stdout


@pytest.mark.parametrize(("args", "fragment"), [
    ([], "required: COMMAND"),
    (["nosuch"], "invalid choice: 'nosuch'"),
    (["query"], "required: SOURCE, TARGET"),
    (["query", "a/b", "c/d", "--timeout", "soon"], "invalid float value: 'soon'"),
    (["demo", "--seconds", "x"], "invalid float value: 'x'"),
    (["eval", "fusion", "--seconds", "nan"], "--seconds must be a positive number, got nan"),
    (["eval", "predictor", "--seconds", "-1"], "--seconds must be a positive number, got -1"),
    (["schemas"], "required: ACTION"),
    (["schemas", "export"], "required: DIR"),
    (["agent", "--bogus"], "unrecognized arguments: --bogus"),
])
def test_bad_arguments_exit_2(capsys, args: list[str], fragment: str) -> None:
    code, out, err = uma_here(capsys, *args)
    assert code == 2, (out, err)
    assert fragment in err
    assert "Traceback" not in err


def test_an_evals_help_and_bad_options_do_not_import_the_evaluation() -> None:
    """``uma eval NAME --help`` and a bad option are answered from the plug-in's light
    declaration: the module that runs the evaluation (scipy.stats, the simulators: seconds
    to import) is imported only when the evaluation runs."""
    code = """
import contextlib, io, sys
from agent.cli.main import main
from agent.runtime import plugins
names = plugins.names(plugins.EVAL_GROUP)
assert len(names) >= 7, names
for name in names:
    for args, status in ((["--help"], 0), (["--no-such-option"], 2)):
        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            try:
                main(["eval", name, *args])
            except SystemExit as e:
                assert e.code == status, (name, args, e.code, out.getvalue())
        assert out.getvalue().startswith(f"usage: uma eval {name}"), out.getvalue()
    runs = plugins.load(plugins.EVAL_GROUP, name).run.partition(":")[0]
    assert runs not in sys.modules, f"uma eval {name} --help imported {runs}"
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120, check=False)
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize(("args", "fragment"), [
    (["eval", "nosuch"], "no eval named 'nosuch' (known: "),
    (["service", "run", "nosuch"], "no service named 'nosuch' (known: "),
])
def test_unknown_plugins_exit_1_with_a_message(args: list[str], fragment: str) -> None:
    r = uma(*args)
    assert r.returncode == 1, (r.stdout, r.stderr)
    assert fragment in r.stderr
    assert "Traceback" not in r.stderr + r.stdout


@pytest.mark.parametrize("content", [None, "{ listen: ["])
def test_a_router_config_that_cannot_be_used_is_named(tmp_path: Path, content) -> None:
    cfg = tmp_path / "router.json5"
    if content is not None:
        cfg.write_text(content)
    r = uma("router", "--config", str(cfg))
    assert r.returncode == 1, (r.stdout, r.stderr)
    assert r.stderr.startswith(f"uma router: error: cannot use Zenoh configuration '{cfg}'")
    assert "Traceback" not in r.stderr


def test_schemas_export_writes_the_committed_schemas(tmp_path: Path) -> None:
    out = tmp_path / "new" / "dir"
    r = uma("schemas", "export", str(out))
    assert r.returncode == 0, r.stderr
    names = sorted(f"{n}.schema.json" for n in MODELS)
    assert sorted(Path(line).name for line in r.stdout.split()) == names
    for name in MODELS:
        assert (out / f"{name}.schema.json").read_text() == export.render(name)


def test_schemas_export_into_a_file_fails_cleanly(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    r = uma("schemas", "export", str(blocker))
    assert r.returncode == 1
    assert r.stderr.startswith("uma schemas: error:") and "File exists" in r.stderr
    assert "Traceback" not in r.stderr

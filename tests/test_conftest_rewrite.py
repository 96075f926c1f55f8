"""The controller's writing of the test modules' assertion-rewritten bytecode
(``conftest._write_rewritten_test_modules``): the files pytest's workers read, and pytest's
normal behaviour wherever the optimisation cannot apply (a module that does not parse, a
pytest whose private rewrite functions differ)."""

from __future__ import annotations

from pathlib import Path

import pytest
from _pytest.assertion import rewrite
from conftest import _write_rewritten_test_modules

GOOD = "def test_sum():\n    total = 1 + 1\n    assert total == 3\n"


def _modules(tmp_path: Path, **sources: str) -> Path:
    for name, text in sources.items():
        (tmp_path / f"{name}.py").write_text(text)
    return tmp_path


def _pyc(source: Path) -> Path:
    return rewrite.get_cache_dir(source) / (source.stem + rewrite.PYC_TAIL)


def test_writes_bytecode_pytest_reads_with_rewritten_asserts(
        tmp_path: Path, pytestconfig: pytest.Config) -> None:
    tests = _modules(tmp_path, test_good=GOOD)
    _write_rewritten_test_modules(pytestconfig, tests)
    code = rewrite._read_pyc(tests / "test_good.py", _pyc(tests / "test_good.py"))
    assert code is not None
    namespace: dict = {}
    exec(code, namespace)
    with pytest.raises(AssertionError, match="assert 2 == 3"):
        namespace["test_sum"]()


def test_module_that_does_not_parse_is_left_to_its_worker(
        tmp_path: Path, pytestconfig: pytest.Config) -> None:
    tests = _modules(tmp_path, test_broken="def test_x(:\n    pass\n", test_good=GOOD)
    _write_rewritten_test_modules(pytestconfig, tests)
    assert not _pyc(tests / "test_broken.py").exists()
    assert _pyc(tests / "test_good.py").exists()


def test_pytest_without_a_private_function_skips_the_optimisation(
        tmp_path: Path, pytestconfig: pytest.Config, monkeypatch: pytest.MonkeyPatch) -> None:
    tests = _modules(tmp_path, test_good=GOOD)
    monkeypatch.delattr(rewrite, "_write_pyc")
    _write_rewritten_test_modules(pytestconfig, tests)
    assert not _pyc(tests / "test_good.py").exists()


def test_pytest_whose_private_function_takes_other_arguments_skips_the_optimisation(
        tmp_path: Path, pytestconfig: pytest.Config, monkeypatch: pytest.MonkeyPatch) -> None:
    tests = _modules(tmp_path, test_good=GOOD)
    monkeypatch.setattr(rewrite, "_rewrite_test", lambda fn: (b"", compile("", "", "exec")))
    _write_rewritten_test_modules(pytestconfig, tests)
    assert not _pyc(tests / "test_good.py").exists()


def test_pytest_whose_rewrite_returns_another_shape_skips_the_optimisation(
        tmp_path: Path, pytestconfig: pytest.Config, monkeypatch: pytest.MonkeyPatch) -> None:
    tests = _modules(tmp_path, test_good=GOOD)
    monkeypatch.setattr(rewrite, "_rewrite_test",
                        lambda fn, config: (b"", compile("", "", "exec"), None))
    _write_rewritten_test_modules(pytestconfig, tests)
    assert not _pyc(tests / "test_good.py").exists()


def test_an_error_inside_the_rewrite_is_not_hidden(
        tmp_path: Path, pytestconfig: pytest.Config, monkeypatch: pytest.MonkeyPatch) -> None:
    tests = _modules(tmp_path, test_good=GOOD)

    def failing(fn: Path, config: pytest.Config) -> tuple:
        raise RuntimeError("rewrite failed")

    monkeypatch.setattr(rewrite, "_rewrite_test", failing)
    with pytest.raises(RuntimeError, match="rewrite failed"):
        _write_rewritten_test_modules(pytestconfig, tests)

"""Optional compiled twins: a hot loop's C module, built by ``pip install`` where a compiler
is there (setup.py), next to the pure-Python code it mirrors, which runs where it was not
built or where an environment switch asks for it (tests compare the two)."""

from __future__ import annotations

import importlib
import os
from types import ModuleType


def compiled_twin(module: str, switch: str) -> ModuleType | None:
    """The compiled module ``module``, or None: not built, or the environment variable
    ``switch`` set (to anything but "" or "0") to run the pure-Python code."""
    if os.environ.get(switch, "") not in ("", "0"):
        return None
    try:
        return importlib.import_module(module)
    except ImportError:
        return None

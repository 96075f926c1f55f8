"""Optional compiled twins: a hot loop's C module, built by ``pip install`` where a compiler
is there (setup.py), next to the pure-Python code it mirrors, which runs where it was not
built, where an environment switch asks for it (tests compare the two), or where the build
is stale.

A twin is only as good as the source it was built from: a copy left by an earlier build
(an editable install not rebuilt after a change to its ``.c`` file) would run the old C
beside the new Python, with other results or other signatures.  So setup.py compiles the
SHA-256 of each twin's C source and of the init they share (``_twin.h``) into it
(``SOURCE_HASH``), both ship beside the modules (package data), and a twin is used only
where the two agree.  This lives in
``schemas`` because every layer that has a twin (schemas, agent, services) may use it.
"""

from __future__ import annotations

import hashlib
import importlib
import logging
import os
from functools import cache
from pathlib import Path
from types import ModuleType

log = logging.getLogger(__name__)

#: what rebuilds every twin from the source beside it (an editable install, from its root)
REBUILD = "pip install -e . --no-deps"


def compiled_twin(module: str, switch: str) -> ModuleType | None:
    """The compiled module ``module``, or None: not built, the environment variable
    ``switch`` set (to anything but "" or "0") to run the pure-Python code, or built from
    other source than the ``.c`` file beside it (logged once a process as a warning)."""
    if os.environ.get(switch, "") not in ("", "0"):
        return None
    return _current(module)


@cache
def _current(module: str) -> ModuleType | None:
    """``module`` if it imports and was built from the source beside it, else None."""
    try:
        twin = importlib.import_module(module)
    except ImportError:
        return None
    source = source_of(twin)
    built = getattr(twin, "SOURCE_HASH", None)
    if source.is_file() and built == source_hash(source):
        return twin
    why = (f"{source} is missing" if not source.is_file() else
           f"it was built from other source than {source}")
    log.warning("compiled twin %s is not used (%s): its pure-Python code runs instead; "
                "rebuild it with `%s`", module, why, REBUILD)
    return None


def source_of(twin: ModuleType) -> Path:
    """The C source a twin is built from: ``_name.c`` beside the module's file."""
    return Path(twin.__file__ or "").parent / f"{twin.__name__.rpartition('.')[2]}.c"


def source_hash(path: Path) -> str:
    """The hash setup.py compiles into a twin: SHA-256, in hex, of its source's bytes and
    then those of the module init every twin includes (:data:`TWIN_HEADER`), so that a
    change to either makes an older build stale."""
    return hashlib.sha256(path.read_bytes() + TWIN_HEADER.read_bytes()).hexdigest()


#: the module init all twins include (shipped beside this module)
TWIN_HEADER = Path(__file__).parent / "_twin.h"

"""The README's python examples, found by a marker and run as a user would (a fresh
interpreter, the example's text as it stands)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

README = Path(__file__).resolve().parents[2] / "README.md"


def readme_block(marker: str) -> str:
    """The one python example of the README that contains ``marker``."""
    found = [b for b in re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
             if marker in b]
    assert len(found) == 1, f"README has no single python example containing {marker!r}"
    return found[0]


def run_python(code: str, timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=timeout)

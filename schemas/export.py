"""``uma schemas export DIR``: write the JSON Schema of every model in ``schemas.models``.

The exported files are committed beside this module, so other languages and tools can
validate uma's descriptors and results; ``tests/test_models.py`` fails when they drift from
the models (re-run ``uma schemas export schemas`` after changing a model).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from schemas.models import MODELS


def render(name: str) -> str:
    """The JSON Schema text of model ``name``: sorted keys, indent 2, trailing newline."""
    schema = MODELS[name].model_json_schema()
    return json.dumps(schema, indent=2, sort_keys=True) + "\n"


def export(directory: str | Path) -> list[Path]:
    """Write ``<name>.schema.json`` for each model into ``directory`` (created if missing)."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name in sorted(MODELS):
        path = out / f"{name}.schema.json"
        path.write_text(render(name), encoding="utf-8")
        written.append(path)
    return written


def main(args: argparse.Namespace) -> int:
    """The ``uma schemas export DIR`` handler: prints each file written."""
    for path in export(args.dir):
        print(path)
    return 0

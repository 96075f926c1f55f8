"""Lazy package attributes: a package names what it exports and where it lives, and the
module holding a name is imported when the name is first used, so importing a package
never pulls in Zenoh, viser or mcap before they are needed."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any


def lazy_attributes(package: str, homes: Mapping[str, str]) -> Callable[[str], Any]:
    """A module ``__getattr__`` for ``package``: ``homes`` maps each exported name to the
    module that defines it (or, for a sub-module, to the sub-module itself); any other name
    is an ``AttributeError``."""
    def get(name: str) -> Any:
        if name in homes:
            module = importlib.import_module(homes[name])
            return module if homes[name] == f"{package}.{name}" else getattr(module, name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")
    return get

"""Package namespaces that load their modules on first use (PEP 562).

A package's `__init__` lists its public names as imports under `if TYPE_CHECKING:` (what type
checkers, readers and the stage fingerprint's import scan see) and calls `lazy_exports`, which
reads that block once and imports a name's module when the name is first asked for. Why: a
worker process that unpickles `gst.data.extract.masks.compute_camera_masks` runs
`gst/data/__init__.py` first, and eager re-exports made every such worker import torch and the
synthetic world (about 3 s of CPU each) for code that needs neither.
"""

from __future__ import annotations

import ast
import importlib
import sys
from collections.abc import Callable
from pathlib import Path

__all__ = ["lazy_exports"]


def _type_checking_imports(path: Path) -> dict[str, str]:
    """{name: module} of the `from M import name` statements inside `if TYPE_CHECKING:`."""
    exports: dict[str, str] = {}
    for node in ast.parse(path.read_text(), str(path)).body:
        if isinstance(node, ast.If) and ast.unparse(node.test) == "TYPE_CHECKING":
            for stmt in node.body:
                if isinstance(stmt, ast.ImportFrom) and stmt.module and not stmt.level:
                    exports |= {a.asname or a.name: stmt.module for a in stmt.names}
    return exports


def lazy_exports(package: str, init_file: str) -> tuple[Callable, Callable]:
    """`(__getattr__, __dir__)` for package `package` whose `__init__` is `init_file`."""
    exports = _type_checking_imports(Path(init_file))
    if not exports:
        raise ImportError(f"{init_file}: no `from M import name` under `if TYPE_CHECKING:`")

    def __getattr__(name: str):
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        setattr(sys.modules[package], name, value)  # later lookups skip this function
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(exports))

    return __getattr__, __dir__

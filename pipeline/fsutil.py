"""Atomic file operations: nothing half-written is ever left under its final name."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path


def atomic_write_text(path: Path, text: str) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def replace_path(src: Path, dest: Path, trash_dir: Path) -> None:
    """Move `src` (file or folder) to `dest`, replacing what was there. The old `dest` is
    renamed aside first, so `dest` is at every moment either the old or the new version."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    old = None
    if dest.exists() or dest.is_symlink():
        trash_dir.mkdir(parents=True, exist_ok=True)
        old = Path(tempfile.mkdtemp(prefix=dest.name + ".", dir=trash_dir)) / dest.name
        os.replace(dest, old)
    os.replace(src, dest)
    if old is not None:
        remove_path(old.parent)


def remove_path(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)

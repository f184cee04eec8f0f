"""Atomic writes, the one implementation every package uses: nothing half-written is ever left
under its final name.

Files: `with atomic_path(target) as tmp:` gives a fresh path beside the target with the same
suffix (so writers that key on the extension, like OpenCV's, keep working); when the block
ends normally the file is fsynced and renamed over the target, and on any error it is removed.
Folders: `with atomic_dir(target) as tmp:` does the same for a whole directory tree; the old
folder is renamed aside first, so the target is at every moment either the old or the new one.
The callback form `atomic_write(path, write)` and the text/JSON/torch/NumPy helpers build on
these.
"""

from __future__ import annotations

import json
import math
import numbers
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

__all__ = [
    "PendingFile",
    "atomic_dir",
    "atomic_path",
    "atomic_save_npz",
    "atomic_torch_save",
    "atomic_write",
    "finite_json",
    "atomic_write_json",
    "atomic_write_text",
    "fsync_dir",
    "remove_path",
    "replace_path",
]


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def fsync_dir(path: Path) -> None:
    """Make a rename in folder `path` durable (where the file system can)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # some filesystems do not open folders; the rename is still atomic
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(path: str | Path, unique: bool = True) -> Iterator[Path]:
    """Yield a temporary file path beside `path` (same suffix); rename it over `path` when the
    block succeeds, remove it when the block raises.

    `unique=False` names the temporary file after the target alone (`.<stem>.tmp<suffix>`), for
    writers that own their target: a rerun after a crash then overwrites the leftover instead of
    leaving it beside the result."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if unique:
        fd, name = tempfile.mkstemp(
            prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent
        )
        os.close(fd)
        tmp = Path(name)
    else:
        tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
        remove_path(tmp)
        tmp.touch()
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the usual permissions
        yield tmp
        if tmp.is_file():
            _fsync_file(tmp)
        os.replace(tmp, path)
        fsync_dir(path.parent)
    finally:
        remove_path(tmp)


@contextmanager
def atomic_dir(path: str | Path, trash: str | Path | None = None) -> Iterator[Path]:
    """Yield a temporary folder beside `path`; on success it replaces `path` (see
    `replace_path`; `trash` is where the old folder is parked, default beside `path`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp creates 0700; give the usual permissions
        yield tmp
        replace_path(tmp, path, Path(trash) if trash is not None else path.parent)
    finally:
        remove_path(tmp)


def atomic_write(path: str | Path, write: Callable[[Path], Any]) -> None:
    """Call `write(tmp_path)`, then rename the temporary file over `path`."""
    with atomic_path(path) as tmp:
        write(tmp)


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def finite_json(value: Any) -> Any:
    """`value` (dicts, lists, tuples, numbers, numpy's too) with every NaN or infinite number as
    None, for strict JSON (`allow_nan=False`): json.dumps wrote `NaN`, which jq, JavaScript and
    most JSON parsers refuse."""
    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite_json(v) for v in value]
    if (
        isinstance(value, numbers.Real)
        and not isinstance(value, numbers.Integral)
        and not math.isfinite(value)
    ):
        return None
    return value


def atomic_write_json(path: str | Path, data: Any, indent: int | None = 2) -> None:
    atomic_write_text(path, json.dumps(data, indent=indent) + "\n")


def atomic_save_npz(path: str | Path, compressed: bool = False, **arrays) -> None:
    """NumPy's `.npz` of `arrays` written atomically (`np.savez`, or `np.savez_compressed`)."""
    import numpy as np  # only the array writers need it

    save = np.savez_compressed if compressed else np.savez

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:  # a file object: NumPy adds no ".npz" to the name
            save(f, **arrays)

    atomic_write(path, write)


def atomic_torch_save(obj: Any, path: str | Path) -> None:
    import torch  # only the checkpoint writers need it

    atomic_write(path, lambda tmp: torch.save(obj, tmp))


def replace_path(src: Path, dest: Path, trash_dir: Path) -> None:
    """Move `src` (file or folder) to `dest`, replacing what was there. The old `dest` is
    renamed aside into `trash_dir` first, so `dest` is at every moment either the old or the new
    version; the old one is deleted afterwards."""
    src, dest = Path(src), Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    old = None
    if dest.exists() or dest.is_symlink():
        Path(trash_dir).mkdir(parents=True, exist_ok=True)
        old = Path(tempfile.mkdtemp(prefix=f".{dest.name}.old.", dir=trash_dir)) / dest.name
        os.replace(dest, old)
    os.replace(src, dest)
    fsync_dir(dest.parent)
    if old is not None:
        remove_path(old.parent)


def remove_path(path: str | Path) -> None:
    """Delete a file or a folder tree; absent paths are fine."""
    path = Path(path)
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


class PendingFile:
    """A temporary file that becomes `target` on `commit()` or disappears on `abort()`: the
    `atomic_path` contract for writers that stay open across calls (video and HDF5 writers)."""

    def __init__(self, target: str | Path):
        self.target = Path(target)
        self._context = atomic_path(self.target, unique=False)
        self.path = self._context.__enter__()
        self._open = True

    def commit(self) -> None:
        if self._open:
            self._open = False
            self._context.__exit__(None, None, None)

    def abort(self) -> None:
        if self._open:
            self._open = False
            try:
                raise RuntimeError("aborted")
            except RuntimeError as exc:
                self._context.__exit__(type(exc), exc, exc.__traceback__)

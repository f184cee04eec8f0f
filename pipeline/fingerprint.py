"""Content hashes of files and folders, cached by (path, size, mtime) so a bare `touch`
(or an unchanged file) costs a stat, and a stage fingerprint built from them."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

from gst.atomic import atomic_write_text

_CHUNK = 1 << 20


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


class HashCache:
    """sha256 of files, remembered by (size, mtime_ns). A touched file whose content did not
    change is re-hashed once and gives the same digest, so it never triggers a rerun."""

    def __init__(self, path: Path | None):
        self.path = path
        self._entries: dict[str, list] = {}
        self._dirty = False
        if path is not None and path.is_file():
            try:
                self._entries = json.loads(path.read_text())
            except (json.JSONDecodeError, OSError):
                self._entries = {}  # a corrupt cache only costs re-hashing

    def file_digest(self, path: Path) -> str:
        st = path.stat()
        key = str(path.resolve())
        hit = self._entries.get(key)
        if hit and hit[0] == st.st_size and hit[1] == st.st_mtime_ns:
            return hit[2]
        digest = _sha256_file(path)
        self._entries[key] = [st.st_size, st.st_mtime_ns, digest]
        self._dirty = True
        return digest

    def digest(self, path: Path) -> str | None:
        """Digest of a file, or of a folder (relative names and file digests), None if absent."""
        path = Path(path)
        if path.is_file():
            return self.file_digest(path)
        if path.is_dir():
            h = hashlib.sha256()
            for root, dirs, files in os.walk(path):
                dirs.sort()
                for name in sorted(files):
                    f = Path(root) / name
                    h.update(f.relative_to(path).as_posix().encode())
                    h.update(self.file_digest(f).encode())
            return "dir:" + h.hexdigest()
        return None

    def save(self) -> None:
        if self.path is not None and self._dirty:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_text(self.path, json.dumps(self._entries))
            self._dirty = False


def stage_fingerprint(code: str, params: dict[str, Any], inputs: dict[str, str | None]) -> str:
    """One hash over the code version, the params and the input digests."""
    blob = json.dumps(
        {"code": code, "params": params, "inputs": inputs}, sort_keys=True, default=str
    )
    return hashlib.sha256(blob.encode()).hexdigest()

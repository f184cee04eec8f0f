"""The landmark model's readings of crop images, kept between runs and between stages.

The fuse stage reads every crowded crop again with the other people painted over
(gst.fuse.relook); `train`'s rig teacher fuses the training crops again without the held-out
ones (gst.lift.teacher), which reads the same crowded crops the same way, twice; and a fuse
stage run again with other fit settings reads them once more. What the landmark model reads
depends only on the pixels it is given (the crop after the painting) and on what runs it, so a
reading is kept under the SHA-256 of those pixels, in a file whose name is a digest of the rest
(`namespace`): the source of the modules that read (`READER_MODULES`, the left/right table of
gst.body.markers among them), the SHA-256 of the model files as they are on disk, the versions
of the libraries that run them (LiteRT, NumPy, OpenCV's own), whether the second pass runs
(`refine`), and the file format. A file that cannot be read is not used (it is
written again). Processes that share the folder merge what they save (a `.lock` file beside
it). The readings are those of a one-thread interpreter, which is what the fuse stage and the
teacher run: the same pixels give the same numbers (tests/test_fuse_relook.py).

File (`readings-<digest>.npz`, written atomically): `keys` (N,) the images' SHA-256 as 64
hexadecimal characters, `readings` (N, 33, 3) float32 u, v in crop pixels and confidence
(visibility x the crop's presence; the crop store keeps visibility alone).
"""

from __future__ import annotations

import fcntl
import hashlib
import importlib
import importlib.metadata
import logging
import threading
from pathlib import Path

import numpy as np

from gst.atomic import atomic_save_npz
from gst.registry import sha256_of

__all__ = ["READER_MODULES", "ReadingCache"]

log = logging.getLogger("gst.detect")

FORMAT = 1
READER_MODULES = (
    "gst.detect.blazepose",
    "gst.detect.crops",
    "gst.detect.weights",
    "gst.body.markers",  # the left/right table the second pass mirrors with
)
READER_PACKAGES = ("ai-edge-litert", "numpy")


def namespace(refine: bool) -> str:
    """The digest of everything but the pixels that decides a reading."""
    import cv2

    from gst.detect.weights import MODELS, model_paths

    what: dict[str, object] = {"format": FORMAT, "refine": bool(refine), "opencv": cv2.__version__}
    for name in READER_MODULES:
        what[name] = sha256_of(Path(importlib.import_module(name).__file__))
    model_paths()  # the files there are the pinned ones (checked once per process)
    for role, model in MODELS.items():
        what[f"model.{role}"] = model.sha256
    for package in READER_PACKAGES:
        try:
            what[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            what[package] = "not installed"
    blob = repr(sorted(what.items())).encode()
    return hashlib.sha256(blob).hexdigest()


class ReadingCache:
    """Readings by image content in `folder` (module doc); safe to share between threads."""

    def __init__(self, folder: Path | str, refine: bool):
        self.path = Path(folder) / f"readings-{namespace(refine)[:32]}.npz"
        self._lock = threading.Lock()
        self._known: dict[str, np.ndarray] = {}
        self._new: dict[str, np.ndarray] = {}
        self.hits = 0
        self._known = self._read()

    def _read(self) -> dict[str, np.ndarray]:
        """The file's readings; a file that cannot be read for any reason (it is only a cache:
        a damaged zip can raise NotImplementedError, say) is removed and its readings made
        again."""
        if not self.path.is_file():
            return {}
        try:
            with np.load(self.path) as z:
                keys, readings = z["keys"], z["readings"]
            if readings.shape != (len(keys), 33, 3):
                raise ValueError(f"readings have shape {readings.shape}")
            return {str(k): r for k, r in zip(keys, readings, strict=True)}
        except Exception as e:  # noqa: BLE001 - any damage means: not used, made again
            log.warning("%s: not read (%s); removed, the readings are made again", self.path, e)
            self.path.unlink(missing_ok=True)
            return {}

    @staticmethod
    def key(image: np.ndarray) -> str:
        """The SHA-256 of an image's shape, type and pixels."""
        image = np.ascontiguousarray(image)
        h = hashlib.sha256(f"{image.shape}{image.dtype}".encode())
        h.update(image.tobytes())
        return h.hexdigest()

    def get(self, key: str) -> np.ndarray | None:
        with self._lock:
            got = self._known.get(key)
            if got is None:
                got = self._new.get(key)
            if got is not None:
                self.hits += 1
            return None if got is None else got.copy()

    def put(self, key: str, reading: np.ndarray) -> None:
        with self._lock:
            self._new[key] = np.asarray(reading, np.float32).reshape(33, 3).copy()

    def save(self) -> None:
        """Write the file with the new readings added (nothing to add: nothing written). Under
        a lock on the folder, the file is read again first: readings another process saved
        since this one loaded it are kept (the last writer's alone were)."""
        with self._lock:
            if not self._new:
                return
            new, self._new = self._new, {}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path.with_suffix(".lock"), "a") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                merged = {**self._read(), **self._known, **new}
                keys = np.array(list(merged), dtype="U64")
                readings = np.stack(list(merged.values())).astype(np.float32)
                atomic_save_npz(self.path, keys=keys, readings=readings)
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)
        with self._lock:
            self._known = merged

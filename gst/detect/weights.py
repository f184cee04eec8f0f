"""BlazePose person models (detector + landmarks with segmentation) from the package registry.

MediaPipe 0.10.14's wheel on PyPI ships the two TFLite models of BlazePose (Apache-2.0):
`pose_detection.tflite` (an SSD person detector) and `pose_landmark_full.tflite` (33 landmarks
and a person segmentation mask for one region of interest). `fetch_blazepose_models` downloads
that one wheel with pip (no dependencies; it is never installed), checks its SHA-256 and the
SHA-256 of both models, and writes the models atomically under `<cache>/blazepose/`.
Nothing from the wheel is executed.
"""

from __future__ import annotations

import functools
import hashlib
import tempfile
from dataclasses import dataclass
from pathlib import Path

from gst.atomic import atomic_write
from gst.registry import (
    PinnedArchive,
    check_hash,
    default_cache_dir,
    pip_download,
    read_member,
    sha256_of,
)

# The platform wheel is pinned by tag, so every host downloads the same file.
MEDIAPIPE_WHEEL = PinnedArchive(
    "mediapipe==0.10.14",
    "mediapipe-0.10.14-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
    "a807328339e7356fda0bb14df12fedbf1d33bdf81649c5f8666b0026b1cc30b4",
    platform="manylinux2014_x86_64",
    python_version="3.11",
)


@dataclass(frozen=True)
class ModelFile:
    member: str  # path inside the wheel
    sha256: str

    @property
    def name(self) -> str:
        return Path(self.member).name


MODELS = {
    "detector": ModelFile(
        "mediapipe/modules/pose_detection/pose_detection.tflite",
        "9ba9dd3d42efaaba86b4ff0122b06f29c4122e756b329d89dca1e297fd8f866c",
    ),
    "landmarks": ModelFile(
        "mediapipe/modules/pose_landmark/pose_landmark_full.tflite",
        "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f",
    ),
}

FETCH_COMMAND = "python -m gst.detect fetch"


class BlazePoseModelsMissing(FileNotFoundError):
    """The BlazePose model files are not in the cache."""


def default_models_dir() -> Path:
    return default_cache_dir() / "blazepose"


class BlazePoseModelsCorrupt(ValueError):
    """A cached BlazePose model file is not the pinned one (damaged, truncated, replaced)."""


@functools.lru_cache(maxsize=16)
def _sha256_version(path: Path, size: int, mtime_ns: int) -> str:
    return sha256_of(path)  # a few ms for the two models; once per file version and process


def _matches_pin(path: Path, sha256: str) -> bool:
    """The file's content is the pinned one (hashed once per file version and process)."""
    st = path.stat()
    return _sha256_version(path, st.st_size, st.st_mtime_ns) == sha256


def model_paths(models_dir: str | Path | None = None) -> dict[str, Path]:
    """Paths of the fetched models, each checked against its pinned SHA-256 (a damaged model
    gives plausible wrong landmarks, and the caches would keep them); raises
    BlazePoseModelsMissing or BlazePoseModelsCorrupt with the fix."""
    root = Path(models_dir) if models_dir is not None else default_models_dir()
    paths = {role: root / m.name for role, m in MODELS.items()}
    # the fix names the folder that failed (the bare command fills the default cache)
    command = FETCH_COMMAND
    if root.resolve() != default_models_dir().resolve():
        command += f" --models-dir {root}"
    missing = [str(p) for p in paths.values() if not p.is_file()]
    if missing:
        raise BlazePoseModelsMissing(
            f"BlazePose model files missing: {', '.join(missing)}. "
            f"Fetch them once with `{command}` "
            f"(downloads {MEDIAPIPE_WHEEL.requirement}'s wheel, about 35 MB, from PyPI; "
            "nothing is installed), "
            f"or on an offline machine `{command} --from DIR` "
            f"with {MEDIAPIPE_WHEEL.filename} in DIR."
        )
    bad = [str(paths[r]) for r, m in MODELS.items() if not _matches_pin(paths[r], m.sha256)]
    if bad:
        raise BlazePoseModelsCorrupt(
            f"BlazePose model file(s) {', '.join(bad)} are not the pinned models (damaged or "
            f"replaced); fetch them again with `{command} --force`"
        )
    return paths


def fetch_blazepose_models(
    models_dir: str | Path | None = None,
    *,
    archive_dir: str | Path | None = None,
    force: bool = False,
) -> dict[str, Path]:
    """Make sure both model files exist under `models_dir` (default `default_models_dir()`)."""
    root = Path(models_dir) if models_dir is not None else default_models_dir()
    paths = {role: root / m.name for role, m in MODELS.items()}
    intact = all(p.is_file() and _matches_pin(p, MODELS[r].sha256) for r, p in paths.items())
    if intact and not force:
        return paths  # a damaged or truncated file is fetched again
    with tempfile.TemporaryDirectory(prefix="gst-blazepose-") as tmp:
        if archive_dir is not None:
            wheel = Path(archive_dir) / MEDIAPIPE_WHEEL.filename
            if not wheel.is_file():
                raise FileNotFoundError(
                    f"{wheel} not found: --from needs {MEDIAPIPE_WHEEL.filename} in {archive_dir}"
                )
        else:
            wheel = pip_download(MEDIAPIPE_WHEEL, Path(tmp))
        check_hash(wheel, MEDIAPIPE_WHEEL)
        blobs = {role: read_member(wheel, m.member) for role, m in MODELS.items()}
    for role, m in MODELS.items():
        # The wheel's hash pins its content already; this also guards against a wrong member path.
        got = hashlib.sha256(blobs[role]).hexdigest()
        if got != m.sha256:
            raise ValueError(
                f"{MEDIAPIPE_WHEEL.filename}:{m.member}: SHA-256 {got} is not the pinned {m.sha256}"
            )
        atomic_write(paths[role], lambda tmp, data=blobs[role]: Path(tmp).write_bytes(data))
    return paths

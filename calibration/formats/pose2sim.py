"""Pose2Sim calibration TOML: the aniposelib layout in metres, with 4 distortion terms
(k1, k2, p1, p2) and `fisheye = false` per camera; tables are usually keyed by camera name.
Pose2Sim's world is z up (e.g. from a board on the floor or a marker-based system)."""

from __future__ import annotations

from pathlib import Path

from calibration.camera import Rig
from calibration.formats._toml_cameras import (
    looks_like_pose2sim,
    read_cameras,
    rms_or_zero,
    write_cameras,
)


def read(path: str | Path) -> Rig:
    return read_cameras(Path(path), 1.0, "pose2sim")


def write(rig: Rig, path: str | Path) -> None:
    write_cameras(
        rig,
        path,
        1.0,
        dist_len=4,
        keys="name",
        extra={"fisheye": False},
        metadata={"adjusted": False, "error": rms_or_zero(rig)},
    )


def sniff(path: Path, text: str | None) -> bool:
    return path.suffix.lower() == ".toml" and looks_like_pose2sim(path)

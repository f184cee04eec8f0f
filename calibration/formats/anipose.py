"""aniposelib / FreeMoCap calibration TOML (`CameraGroup.dump`).

Translations are in the units of the board's square size as the user entered it; the file does
not say which, so pass `units` ('mm' by default, what FreeMoCap and the anipose examples use;
'cm' or 'm' otherwise). Distortion: 5 OpenCV terms. The world is wherever the calibration put
it (aniposelib: the first camera; FreeMoCap: optionally a board on the floor, z up); we keep it
and set `Rig.up` to +z.
"""

from __future__ import annotations

from pathlib import Path

from calibration.camera import Rig
from calibration.formats._common import metres_per_unit
from calibration.formats._toml_cameras import (
    looks_like_pose2sim,
    read_cameras,
    rms_or_zero,
    write_cameras,
)


def read(path: str | Path, units: str = "mm") -> Rig:
    return read_cameras(Path(path), metres_per_unit(units, "anipose"), "anipose")


def write(rig: Rig, path: str | Path, units: str = "mm") -> None:
    write_cameras(
        rig,
        path,
        metres_per_unit(units, "anipose"),
        dist_len=5,
        keys="index",
        metadata={"adjusted": False, "error": rms_or_zero(rig)},
    )


def sniff(path: Path, text: str | None) -> bool:
    return path.suffix.lower() == ".toml" and not looks_like_pose2sim(path)

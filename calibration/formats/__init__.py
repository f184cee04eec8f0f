"""Read and write camera rigs in every common calibration format.

    rig = read_rig("calibration_171204_pose1.json")          # format detected
    rig = read_rig("cameras.h5", "h36m", subject=9)
    write_rig(rig, "calibration/rig.json")                     # our canonical format
    write_rig(rig, "Calib.toml", "pose2sim")

Every reader returns a validated Rig in metres, world to camera, OpenCV axes and pixel
convention; every writer validates the rig first and writes atomically (temporary file, then
rename), so a failed write leaves no partial file. Units and axes of each format are in
docs/formats/calibration_formats.md.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np
from scipy.spatial.transform import Rotation

from calibration.camera import Rig
from calibration.formats import (
    anipose,
    colmap,
    h36m,
    h36m_json,
    panoptic,
    pose2sim,
    qualisys,
    rig_json,
)
from calibration.formats._common import RigFormatError, validate_rig

log = logging.getLogger("calibration")


@dataclass(frozen=True)
class FormatInfo:
    name: str
    description: str
    module: ModuleType
    can_write: bool
    read_options: tuple[str, ...] = ()
    write_options: tuple[str, ...] = ()
    # the world's up axis by the format's convention (what its reader gives `Rig.up`); None:
    # the file stores the rig's own up, or the reader is told it (colmap's `up` option)
    world_up: tuple[float, float, float] | None = None


FORMATS: dict[str, FormatInfo] = {
    f.name: f
    for f in (
        FormatInfo(
            "rig", "gst-capture rig.json (metres, world to camera, versioned)", rig_json, True
        ),
        FormatInfo(
            "panoptic",
            "CMU Panoptic calibration_<seq>.json (cm, world y down)",
            panoptic,
            True,
            ("camera_types",),
            world_up=(0.0, -1.0, 0.0),
        ),
        FormatInfo(
            "h36m",
            "Human3.6M cameras.h5 (mm, H36M lens model)",
            h36m,
            True,
            ("subject", "image_size"),
            ("subject", "approximate_distortion"),
            world_up=(0.0, 0.0, 1.0),
        ),
        FormatInfo(
            "h36m-json",
            "Human3.6M camera JSON variant (mm)",
            h36m_json,
            True,
            ("subject", "tangential", "image_size"),
            ("subject", "tangential"),
            world_up=(0.0, 0.0, 1.0),
        ),
        FormatInfo(
            "anipose",
            "aniposelib / FreeMoCap TOML (board units, default mm)",
            anipose,
            True,
            ("units",),
            ("units",),
            world_up=(0.0, 0.0, 1.0),
        ),
        FormatInfo(
            "pose2sim",
            "Pose2Sim TOML (m, 4 distortion terms)",
            pose2sim,
            True,
            world_up=(0.0, 0.0, 1.0),
        ),  # fmt: skip
        FormatInfo(
            "qualisys",
            "Qualisys .qca.txt XML (mm; read only)",
            qualisys,
            False,
            ("include_inactive", "video_only", "distortion_scale"),
        ),
        FormatInfo(
            "colmap",
            "COLMAP sparse model folder via pycolmap (unitless)",
            colmap,
            True,
            ("metres_per_unit", "up"),
            ("metres_per_unit",),
        ),
    )
}

# Order matters: specific signatures before generic ones.
_SNIFF_ORDER = ("rig", "h36m-json", "panoptic", "qualisys", "h36m", "colmap", "pose2sim", "anipose")


def detect_format(path: str | Path) -> str:
    """The format of a rig file or folder, from its suffix and content."""
    path = Path(path)
    if not path.exists():
        raise RigFormatError(f"{path}: no such file or folder")
    text = None
    if path.is_file() and path.suffix.lower() not in (".h5", ".hdf5"):
        try:
            text = path.read_text(encoding="utf-8", errors="replace")[:200_000]
        except OSError as exc:
            raise RigFormatError(f"{path}: cannot read ({exc})") from exc
    for name in _SNIFF_ORDER:
        if FORMATS[name].module.sniff(path, text):
            return name
    raise RigFormatError(f"{path}: cannot tell its rig format; pass fmt= one of {sorted(FORMATS)}")


def _info(fmt: str) -> FormatInfo:
    if fmt not in FORMATS:
        raise RigFormatError(f"unknown rig format '{fmt}', expected one of {sorted(FORMATS)}")
    return FORMATS[fmt]


def _check_options(fmt: str, opts: dict, allowed: tuple[str, ...], verb: str) -> None:
    unknown = sorted(set(opts) - set(allowed))
    if unknown:
        raise RigFormatError(
            f"format '{fmt}' takes no {verb} options {unknown} (it takes {list(allowed)})"
        )


def read_rig(path: str | Path, fmt: str | None = None, **opts) -> Rig:
    """Read a rig; `fmt` None detects it. Options per format are listed in FORMATS."""
    path = Path(path)
    fmt = fmt or detect_format(path)
    info = _info(fmt)
    _check_options(fmt, opts, info.read_options, "read")
    if not path.exists():
        raise RigFormatError(f"{path}: no such file or folder")
    return info.module.read(path, **opts)


def write_rig(rig: Rig, path: str | Path, fmt: str = "rig", **opts) -> None:
    """Validate and write a rig atomically. Options per format are listed in FORMATS."""
    info = _info(fmt)
    if not info.can_write:
        raise RigFormatError(f"format '{fmt}' is read only")
    _check_options(fmt, opts, info.write_options, "write")
    validate_rig(rig)
    if info.world_up is not None:
        rig = in_world_up(rig, info.world_up)
    info.module.write(rig, Path(path), **opts)


def in_world_up(rig: Rig, up: tuple[float, float, float]) -> Rig:
    """The rig in a world turned (the smallest rotation about the origin) so that its up axis
    is `up`: a format whose files carry no up direction is read back with its convention's, so
    a rig of another up is written in that convention's axes (the same cameras; world points
    turn with it). Unchanged where the ups already agree."""
    a = np.asarray(rig.up, np.float64)
    b = np.asarray(up, np.float64)
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    if np.allclose(a, b, atol=1e-12):
        return rig
    axis = np.cross(a, b)
    if np.linalg.norm(axis) < 1e-9:  # opposite: half a turn about any axis across them
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    angle = np.arctan2(np.linalg.norm(np.cross(a, b)), float(a @ b))
    rotation = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
    log.warning(
        "rig up %s written in axes whose up is %s: the world is turned by %.1f degrees",
        tuple(float(round(v, 3)) for v in a), tuple(up), np.degrees(angle),
    )  # fmt: skip
    return rig.transformed(rotation, np.zeros(3), up=up)


__all__ = [
    "FORMATS", "FormatInfo", "RigFormatError", "detect_format", "in_world_up", "read_rig",
    "write_rig",
]  # fmt: skip

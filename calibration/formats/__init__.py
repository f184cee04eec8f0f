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

from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

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


@dataclass(frozen=True)
class FormatInfo:
    name: str
    description: str
    module: ModuleType
    can_write: bool
    read_options: tuple[str, ...] = ()
    write_options: tuple[str, ...] = ()


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
        ),
        FormatInfo(
            "h36m",
            "Human3.6M cameras.h5 (mm, H36M lens model)",
            h36m,
            True,
            ("subject", "image_size"),
            ("subject", "approximate_distortion"),
        ),
        FormatInfo(
            "h36m-json",
            "Human3.6M camera JSON variant (mm)",
            h36m_json,
            True,
            ("subject", "tangential", "image_size"),
            ("subject", "tangential"),
        ),
        FormatInfo(
            "anipose",
            "aniposelib / FreeMoCap TOML (board units, default mm)",
            anipose,
            True,
            ("units",),
            ("units",),
        ),
        FormatInfo("pose2sim", "Pose2Sim TOML (m, 4 distortion terms)", pose2sim, True),
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
    info.module.write(rig, Path(path), **opts)


__all__ = ["FORMATS", "FormatInfo", "RigFormatError", "detect_format", "read_rig", "write_rig"]

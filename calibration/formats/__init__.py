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
            ("subject", "tangential", "approximate_distortion"),
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
    guessed = fmt is None
    fmt = fmt or detect_format(path)
    info = _info(fmt)
    _check_options(fmt, opts, info.read_options, "read")
    if not path.exists():
        raise RigFormatError(f"{path}: no such file or folder")
    try:
        rig = info.module.read(path, **opts)
    except RigFormatError as exc:
        if guessed:
            raise
        # a declared format that the file is not ("not valid TOML" for a Qualisys file)
        try:
            other = detect_format(path)
        except Exception:  # a sniffer that chokes on this file must not hide the real error
            other = None
        if other is None or other == fmt:
            raise
        raise RigFormatError(
            f"{exc} (read as '{fmt}', as asked; the file looks like '{other}': give that "
            "format, or omit it to detect it)"
        ) from exc
    if guessed and fmt in ("anipose", "pose2sim"):
        # the two TOML layouts differ by a key or a distortion length, and in units (mm against
        # m): a metres file taken for anipose put a camera 4.2 m away 4.2 mm away, silently
        log.warning(
            "%s: read as '%s' (a TOML file, told apart by its keys%s); give the format "
            "(and anipose's units) to be sure",
            path,
            fmt,
            f", translations in {opts.get('units', 'mm')}" if fmt == "anipose" else "",
        )
    spread = _camera_spread(rig)
    if spread is not None and spread < 0.05:
        log.warning(
            "%s: the %d cameras stand within %.3f m of each other: are the translations in "
            "another unit than the reader assumed (anipose: units='mm' by default)?",
            path,
            len(rig),
            spread,
        )
    return rig


def _camera_spread(rig: Rig) -> float | None:
    """The largest distance between two camera centres (m), None for fewer than two."""
    if len(rig) < 2:
        return None
    centres = np.array([c.center for c in rig])
    return float(np.max(np.linalg.norm(centres[:, None] - centres[None], axis=-1)))


def write_rig(
    rig: Rig, path: str | Path, fmt: str = "rig", *, warn_up: bool = True, **opts
) -> None:
    """Validate and write a rig atomically. Options per format are listed in FORMATS.
    `warn_up`: log `up_warning` where the format cannot hold the rig's up (off for writers
    whose files document their world, as the synthetic scenes')."""
    info = _info(fmt)
    if not info.can_write:
        raise RigFormatError(f"format '{fmt}' is read only")
    _check_options(fmt, opts, info.write_options, "write")
    validate_rig(rig)
    warning = up_warning(rig, fmt) if warn_up else None
    if warning is not None:
        log.warning("%s: %s", path, warning)
    info.module.write(rig, Path(path), **opts)


def up_warning(rig: Rig, fmt: str) -> str | None:
    """The warning for writing `rig` as `fmt` where the format's files carry no up axis and the
    rig's up is not the one its readers assume (None where they agree, or the file stores it).
    The world is written unchanged, so 3D data in it (truth, fused bodies) stay valid; a reader
    of the file must be told the up (ours: `Rig.up` after `read_rig`, set it by hand)."""
    up = _info(fmt).world_up
    if up is None or np.allclose(np.asarray(rig.up, float), up, atol=1e-9):
        return None
    return (
        f"the rig's up {tuple(float(round(v, 3)) for v in rig.up)} is written in a '{fmt}' "
        f"file, which holds no up: readers will assume {up}; the world is written unchanged"
    )


__all__ = [
    "FORMATS", "FormatInfo", "RigFormatError", "detect_format", "read_rig", "up_warning",
    "write_rig",
]  # fmt: skip

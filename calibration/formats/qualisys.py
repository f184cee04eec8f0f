"""Qualisys Track Manager calibration export (`.qca.txt`, XML). Read only.

Per `<camera>` (attribute `serial` is the name): `<transform x y z r11 .. r33>` gives the camera
position in world millimetres and a rotation whose rows are the camera axes in world coordinates
(X_q = M (P - position)); Qualisys cameras look down their -z axis with +y up, so the OpenCV
camera is diag(1, -1, -1) X_q. `<intrinsic>` gives focalLengthU/V and centerPointU/V in sensor
subpixels (64 per pixel), radialDistortion1..3 and tangentalDistortion1..2; `<fov_video>` gives
the video window (left, top, right, bottom, inclusive), whose offset is removed from the
principal point. The Qualisys world is z up, millimetres (converted to metres).

Distortion: we read the coefficients as OpenCV's k1, k2, p1, p2, k3 on normalised coordinates,
as given (values like k1 = -0.05, k2 = 0.14 are typical lens values in that convention). The
Qualisys documentation available to us does not define the model. Pose2Sim's converter
divides them by 64 like the pixel quantities; pass `distortion_scale=1/64` to reproduce it.
Skew other than 0 and rotated views (`viewrotation` other than 0) are refused.
"""

from __future__ import annotations

import logging
import math
import xml.etree.ElementTree as ET
from fractions import Fraction
from pathlib import Path

import numpy as np

from calibration.camera import Rig
from calibration.formats._common import RigFormatError, make_camera, make_rig

SUBPIXELS_PER_PIXEL = 64.0
MM_PER_M = 1000.0
QUALISYS_TO_OPENCV_AXES = np.diag([1.0, -1.0, -1.0])
VIDEO_PLUS_LINES = 1440.0  # Miqus Video Plus's native video lines (1920 x 1440)

log = logging.getLogger("calibration")


# XML names are case-sensitive, but a hand-edited file may spell them otherwise: matched only as
# Qualisys spells them, `Active="0"` kept an inactive camera, `Serial=` renamed the camera and a
# `<Camera>` element was dropped without a word. Names are matched regardless of case (the exact
# spelling first).
def _attr(el: ET.Element, name: str, default: str | None = None) -> str | None:
    if name in el.attrib:
        return el.attrib[name]
    return next((v for k, v in el.attrib.items() if k.lower() == name.lower()), default)


def _find(el: ET.Element, tag: str) -> ET.Element | None:
    return next((c for c in el if c.tag.lower() == tag.lower()), None)


def _float(el: ET.Element, attr: str, path: Path, where: str) -> float:
    value = _attr(el, attr)
    if value is None:
        raise RigFormatError(f"{path}: {where} <{el.tag}> lacks attribute '{attr}'")
    try:
        number = float(value)
    except ValueError as exc:
        raise RigFormatError(
            f"{path}: {where} <{el.tag}> {attr}={value!r} is not a number"
        ) from exc
    if not math.isfinite(number):  # "nan" and "inf" parse; no calibration value is either
        raise RigFormatError(f"{path}: {where} <{el.tag}> {attr}={value!r} is not finite")
    return number


def _child(cam: ET.Element, tag: str, path: Path, where: str) -> ET.Element:
    el = _find(cam, tag)
    if el is None:
        raise RigFormatError(f"{path}: {where} has no <{tag}> element")
    return el


def _video_scale(cam: ET.Element, path: Path, where: str) -> float:
    """The recorded video's size against the resolution the camera was calibrated at. Qualisys
    cameras that record below it say so (`video_resolution="540p"`) while their intrinsics and
    field of view stay at the native resolution: 1440p where the shorter side of
    `<fov_video_max>` holds 1440 lines (Miqus Video Plus), else 1080p (Miqus Video, whose
    windows may hold 1088 lines), which Pose2Sim's reader assumes for every camera and so
    scales Video Plus files by 4/3 (pose2sim issues 200, 212)."""
    resolution = _attr(cam, "video_resolution")
    if resolution in (None, "", "N/A"):
        return 1.0
    text = resolution.strip().lower()
    if not (text.endswith("p") and text[:-1].isdigit() and int(text[:-1]) > 0):
        raise RigFormatError(
            f"{path}: {where} has video_resolution={resolution!r}; expected e.g. '1080p' or '540p'"
        )
    native = 1080.0
    window = _find(cam, "fov_video_max")
    if window is not None:
        sides = [
            _float(window, hi, path, where) - _float(window, lo, path, where) + 1
            for lo, hi in (("left", "right"), ("top", "bottom"))
        ]
        native = VIDEO_PLUS_LINES if min(sides) >= VIDEO_PLUS_LINES else 1080.0
    scale = int(text[:-1]) / native
    if scale > 1 + 1e-9:
        raise RigFormatError(
            f"{path}: {where} has video_resolution={resolution!r}, more lines than its "
            f"calibrated video window ({native:g}); expected at most {native:g}p"
        )
    return scale


def read(
    path: str | Path,
    include_inactive: bool = False,
    video_only: bool = True,
    distortion_scale: float = 1.0,
) -> Rig:
    """Active video cameras (model containing 'Video', or 'none' as in exported files); the
    cameras passed over are logged and listed in the rig's `meta["skipped"]`."""
    path = Path(path)
    include_inactive = _flag(include_inactive, "include_inactive", path)
    video_only = _flag(video_only, "video_only", path)
    distortion_scale = _scale_option(distortion_scale, path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise RigFormatError(f"{path}: not valid XML ({exc})") from exc
    if root.tag != "calibration":
        raise RigFormatError(f"{path}: root element is <{root.tag}>, expected <calibration>")
    cameras, skipped = [], []
    listed = [c for group in root if group.tag.lower() == "cameras" for c in group]
    for i, cam in enumerate(c for c in listed if c.tag.lower() == "camera"):
        name = _attr(cam, "serial") or f"camera{i + 1}"
        where = f"camera '{name}'"
        if not include_inactive and _attr(cam, "active", "1") != "1":
            skipped.append(f"{name} (inactive)")
            continue
        model = _attr(cam, "model", "none")
        if video_only and not ("video" in model.lower() or model == "none"):
            skipped.append(f"{name} (model {model!r})")
            continue
        if _attr(cam, "viewrotation", "0") not in ("0", "0.0"):
            raise RigFormatError(
                f"{path}: {where} has viewrotation={_attr(cam, 'viewrotation')}; "
                "rotated views are not supported"
            )
        scale = _video_scale(cam, path, where)
        fov = _child(cam, "fov_video", path, where)
        left, top = _float(fov, "left", path, where), _float(fov, "top", path, where)
        width = int(round((_float(fov, "right", path, where) - left + 1) * scale))
        height = int(round((_float(fov, "bottom", path, where) - top + 1) * scale))
        intr = _child(cam, "intrinsic", path, where)
        if _attr(intr, "skew") not in (None, "") and _float(intr, "skew", path, where) != 0:
            raise RigFormatError(
                f"{path}: {where} has skew={_attr(intr, 'skew')}; its units are not "
                "documented, so it is not supported"
            )
        fu = _float(intr, "focalLengthU", path, where) / SUBPIXELS_PER_PIXEL * scale
        fv = _float(intr, "focalLengthV", path, where) / SUBPIXELS_PER_PIXEL * scale
        # pixel centres sit at whole coordinates, so a video scaled by `scale` maps native u to
        # (u + 0.5) * scale - 0.5 (a 2x area downscale takes pixels 600 and 601 to 300)
        cu = (_float(intr, "centerPointU", path, where) / SUBPIXELS_PER_PIXEL - left + 0.5) * scale
        cv = (_float(intr, "centerPointV", path, where) / SUBPIXELS_PER_PIXEL - top + 0.5) * scale
        cu, cv = cu - 0.5, cv - 0.5
        dist = distortion_scale * np.array(
            [
                _float(intr, "radialDistortion1", path, where),
                _float(intr, "radialDistortion2", path, where),
                _float(intr, "tangentalDistortion1", path, where),
                _float(intr, "tangentalDistortion2", path, where),
                _float(intr, "radialDistortion3", path, where),
            ]
        )
        tr = _child(cam, "transform", path, where)
        position = np.array([_float(tr, a, path, where) for a in "xyz"]) / MM_PER_M
        M = np.array([[_float(tr, f"r{r}{c}", path, where) for c in (1, 2, 3)] for r in (1, 2, 3)])
        ortho_err = float(np.abs(M @ M.T - np.eye(3)).max())
        if ortho_err > 1e-5:
            raise RigFormatError(
                f"{path}: {where} rotation r11..r33 is not orthonormal "
                f"(max |M M^T - I| = {ortho_err:.2e})"
            )
        U, _, Vt = np.linalg.svd(M)  # remove the last digits' rounding
        R = QUALISYS_TO_OPENCV_AXES @ (U @ Vt)
        meta = {"source": "qualisys", "model": model, "avg_residual": _attr(cam, "avg-residual")}
        cameras.append(
            make_camera(
                path,
                name,
                K=[[fu, 0, cu], [0, fv, cv], [0, 0, 1]],
                dist=dist,
                R=R,
                t=-R @ position,
                width=width,
                height=height,
                meta=meta,
            )
        )
    if not cameras and skipped:  # "no cameras found" did not say which were passed over, or why
        raise RigFormatError(
            f"{path}: no camera to read: skipped {', '.join(skipped)}; {KEEP_HINT}"
        )
    for why in skipped:  # a camera passed over must not look like a camera missing from the file
        log.warning("%s: camera %s passed over (%s)", path, why, KEEP_HINT)
    meta = {"source": "qualisys", **({"skipped": skipped} if skipped else {})}
    return make_rig(path, cameras, up=(0.0, 0.0, 1.0), meta=meta)


KEEP_HINT = (
    "video_only=True keeps models with 'video' in their name (or 'none'; video_only=False keeps "
    "every model), include_inactive=True the inactive ones"
)


def _flag(value, name: str, path: Path) -> bool:
    """A true/false read option, as it is (YAML's `false` is a bool; the text 'false' is not)."""
    if not isinstance(value, bool | np.bool_):
        raise RigFormatError(
            f"{path}: the Qualisys read option {name} must be true or false, got {value!r}"
        )
    return bool(value)


def _scale_option(value, path: Path) -> float:
    """`distortion_scale`: a number > 0, or its text as a fraction ('1/64', as YAML keeps it)."""
    try:
        if isinstance(value, bool):
            raise ValueError
        scale = float(Fraction(value.strip())) if isinstance(value, str) else float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        scale = math.nan
    if not (math.isfinite(scale) and scale > 0):
        raise RigFormatError(
            f"{path}: the Qualisys read option distortion_scale must be a number > 0 (e.g. 1 or "
            f"1/64), got {value!r}"
        )
    return scale


def sniff(path: Path, text: str | None) -> bool:
    name = path.name.lower()
    if name.endswith(".qca.txt") or name.endswith(".qca"):
        return True
    return text is not None and "<calibration" in text and "<intrinsic" in text

"""The common JSON variant of the Human3.6M cameras.

Layout: {"intrinsics": {<camera id>: {"calibration_matrix": 3x3, "distortion": [k1, k2, p1, p2,
k3]}}, "extrinsics": {"S<n>": {<camera id>: {"R": 3x3, "t": 3x1}}}}. R, t map world to camera,
t in millimetres; the world is H36M's (z up).

Distortion: the variant lists five numbers in OpenCV's order and its users feed them to OpenCV,
so by default (`tangential="opencv"`) they are read as OpenCV coefficients. Public copies were
transcribed from H36M's own k and p, whose tangential model differs (see `h36m.py`); with
`tangential="h36m"` the numbers are read as H36M's (k1, k2, p1, p2, k3) and converted exactly.
The two readings differ only through p, which is of order 1e-3 for H36M, i.e. at most a few
pixels at the image corners.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

from calibration.camera import Rig
from calibration.formats._common import (
    RigFormatError,
    as_float_array,
    atomic_write_text,
    five_term_dist,
    load_json,
    make_camera,
    make_rig,
    require,
    require_array,
    require_distortion,
    require_typed,
)
from calibration.formats.h36m import (
    MM_PER_M,
    h36m_to_opencv,
    image_size_of,
    opencv_to_h36m,
    subject_number,
)

TANGENTIAL = ("opencv", "h36m")


def _subject_name(subject) -> str:
    return f"S{subject_number(subject)}"


def read(
    path: str | Path,
    subject=None,
    tangential: str = "opencv",
    image_size: tuple[int, int] | None = None,
) -> Rig:
    """One subject's cameras (`subject='S1'` or 1; optional when the file holds one)."""
    path = Path(path)
    if tangential not in TANGENTIAL:
        raise RigFormatError(f"tangential must be one of {TANGENTIAL}, got {tangential!r}")
    data = load_json(path)
    intr = require_typed(data, "intrinsics", dict, path)
    extr = require_typed(data, "extrinsics", dict, path)
    if subject is None:
        if len(extr) != 1:
            raise RigFormatError(
                f"{path}: holds subjects {sorted(extr)}; choose one with subject=..."
            )
        subj = next(iter(extr))
    else:
        subj = _subject_name(subject)
        if subj not in extr:
            raise RigFormatError(
                f"{path}: no extrinsics for subject '{subj}' (subjects: {sorted(extr)})"
            )
    cameras = []
    for name, e in require_typed(extr, subj, dict, path, "extrinsics").items():
        where = f"camera '{name}'"
        i = require_typed(intr, name, dict, path, "intrinsics")
        K = as_float_array(
            require(i, "calibration_matrix", path, f"{where} intrinsics"),
            (3, 3),
            path,
            f"{where} K",
        )
        raw = require_distortion(i, "distortion", path, f"{where} intrinsics")
        if tangential == "h36m":
            if raw.size != 5:
                raise RigFormatError(f"{path}: {where} distortion has {raw.size} terms, expected 5")
            dist = h36m_to_opencv(raw[[0, 1, 4]], raw[[2, 3]])
        else:
            dist = raw
        if ("width" in i) != ("height" in i):  # one alone was ignored for the standard size
            raise RigFormatError(
                f"{path}: {where} intrinsics give {'width' if 'width' in i else 'height'} "
                "without the other; give both or neither"
            )
        stored = (i["width"], i["height"]) if "width" in i else None
        size = image_size_of(path, where, name, stored, image_size)
        cameras.append(
            make_camera(
                path,
                name,
                K=K,
                dist=dist,
                R=require_array(e, "R", (3, 3), path, where),
                t=require_array(e, "t", (3,), path, where) / MM_PER_M,
                width=size[0],
                height=size[1],
                meta={"source": "h36m-json", "subject": subj},
            )
        )
    return make_rig(
        path, cameras, up=(0.0, 0.0, 1.0), meta={"source": "h36m-json", "subject": subj}
    )


def write(
    rig: Rig,
    path: str | Path,
    subject="S1",
    tangential: str = "opencv",
    approximate_distortion: bool = False,
) -> None:
    """One subject's cameras. Distortion is written as 5 OpenCV terms (`tangential='opencv'`) or
    as H36M's k, p in the same slots (`'h36m'`); cameras that cannot be written exactly that way
    are refused, or with `tangential='h36m'` and `approximate_distortion=True` fitted as the
    cameras.h5 writer fits them (the refusal suggests it). Image sizes go into extra
    `width`/`height` keys of each intrinsics entry."""
    if tangential not in TANGENTIAL:
        raise RigFormatError(f"tangential must be one of {TANGENTIAL}, got {tangential!r}")
    subj = _subject_name(subject)
    intr, extr = {}, {}
    for c in rig:
        if c.skew:  # as the TOML, cameras.h5 and COLMAP writers refuse it
            raise RigFormatError(
                f"camera '{c.name}': K[0, 1] = {c.skew} (skew); this file's users project with "
                "cv2.projectPoints, which ignores it, so the file would place points elsewhere"
            )
        if tangential == "h36m":
            k, p, err = opencv_to_h36m(c, approximate_distortion)
            if err > 0:
                warnings.warn(
                    f"camera '{c.name}': H36M distortion fitted, worst error {err:.3g} px",
                    stacklevel=2,
                )
            dist = [k[0], k[1], p[0], p[1], k[2]]
        else:
            dist = five_term_dist(c, "H36M JSON").tolist()
        intr[c.name] = {
            "calibration_matrix": c.K.tolist(),
            "distortion": [float(v) for v in dist],
            "width": c.width,
            "height": c.height,
        }
        extr[c.name] = {"R": c.R.tolist(), "t": (c.t * MM_PER_M).reshape(3, 1).tolist()}
    atomic_write_text(
        path, json.dumps({"intrinsics": intr, "extrinsics": {subj: extr}}, indent=1) + "\n"
    )


def sniff(path: Path, text: str | None) -> bool:
    return text is not None and '"calibration_matrix"' in text and '"extrinsics"' in text

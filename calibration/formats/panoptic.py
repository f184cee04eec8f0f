"""CMU Panoptic Studio `calibration_<seq>.json`.

Layout: {"calibDataSource": str, "cameras": [{"name": "PP_NN", "type": "hd" | "vga" | "kinect",
"resolution": [w, h], "panel": int, "node": int, "K": 3x3, "distCoef": [k1, k2, p1, p2, k3],
"R": 3x3, "t": 3x1}]}. R, t map world to camera (OpenCV axes), t is in centimetres, and the
world's Y axis points down (so our `Rig.up` is (0, -1, 0)). The world frame is kept; only the
units change (cm -> m).
"""

from __future__ import annotations

import json
from pathlib import Path

from calibration.camera import Rig
from calibration.formats._common import (
    RigFormatError,
    atomic_write_text,
    five_term_dist,
    json_safe,
    load_json,
    make_camera,
    make_rig,
    pixel_count,
    require_array,
    require_distortion,
    require_text,
    require_typed,
)

CM_PER_M = 100.0  # multiply/divide by 100 (exact for more values than scaling by 0.01)


def read(path: str | Path, camera_types: tuple[str, ...] | None = None) -> Rig:
    """All cameras, or only those whose `type` is in `camera_types` (e.g. ("hd",), or "hd")."""
    if isinstance(camera_types, str):  # `camera_types: hd` in YAML: matched as a substring
        camera_types = (camera_types,)
    path = Path(path)
    if camera_types is not None and (
        not isinstance(camera_types, (list, tuple, set, frozenset))
        or not all(isinstance(t, str) for t in camera_types)
    ):  # `camera_types: 5` was a bare "argument of type 'int' is not iterable"
        raise RigFormatError(
            f"{path}: the Panoptic read option camera_types is {camera_types!r}, expected a "
            "camera type or a list of them (e.g. hd, or [hd, vga])"
        )
    data = load_json(path)
    cams_data = require_typed(data, "cameras", list, path)
    cameras = []
    for i, cd in enumerate(cams_data):
        if not isinstance(cd, dict):
            raise RigFormatError(f"{path}: cameras[{i}] must be an object")
        name = require_text(cd, "name", path, f"cameras[{i}]")
        where = f"camera '{name}'"
        ctype = cd.get("type", "")
        if camera_types is not None and ctype not in camera_types:
            continue
        w, h = require_array(cd, "resolution", (2,), path, where)
        dist = require_distortion(cd, "distCoef", path, where)
        meta = {"source": "panoptic", "type": ctype}
        for key in ("panel", "node"):
            if key in cd:
                meta[key] = cd[key]
        cameras.append(
            make_camera(
                path,
                name,
                K=require_array(cd, "K", (3, 3), path, where),
                dist=dist,
                R=require_array(cd, "R", (3, 3), path, where),
                t=require_array(cd, "t", (3,), path, where) / CM_PER_M,
                width=pixel_count(w, path, f"{where} resolution[0]"),
                height=pixel_count(h, path, f"{where} resolution[1]"),
                meta=meta,
            )
        )
    if not cameras:
        raise RigFormatError(
            f"{path}: no cameras of types {camera_types} "
            f"(types present: {sorted({str(c.get('type')) for c in cams_data})})"
        )
    rig_meta = {"source": "panoptic"}
    if "calibDataSource" in data:
        rig_meta["calibDataSource"] = data["calibDataSource"]
    return make_rig(path, cameras, up=(0.0, -1.0, 0.0), meta=rig_meta)


def write(rig: Rig, path: str | Path) -> None:
    """Panoptic JSON (t in cm). Camera type/panel/node come from each camera's meta when it was
    read from Panoptic; otherwise type 'hd', panel 0 and node = index."""
    cams = []
    for i, c in enumerate(rig):
        cams.append(
            {
                "name": c.name,
                "type": json_safe(c.meta.get("type", "hd")),
                "resolution": [c.width, c.height],
                "panel": json_safe(c.meta.get("panel", 0)),
                "node": json_safe(c.meta.get("node", i)),
                "K": c.K.tolist(),
                "distCoef": five_term_dist(c, "Panoptic").tolist(),
                "R": c.R.tolist(),
                "t": (c.t * CM_PER_M).reshape(3, 1).tolist(),
            }
        )
    data = {"calibDataSource": str(rig.meta.get("calibDataSource", "gst-capture")), "cameras": cams}
    atomic_write_text(path, json.dumps(data, indent=1) + "\n")


def sniff(path: Path, text: str | None) -> bool:
    return text is not None and '"distCoef"' in text and '"cameras"' in text

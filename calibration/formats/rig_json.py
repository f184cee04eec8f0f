"""Our canonical rig file, `rig.json` (documented in docs/formats/rig_json.md).

Metres, world to camera (X_cam = R X_world + t), OpenCV camera axes and pixel convention,
OpenCV distortion order. Floats are written with Python's shortest round-trip repr, so a
write/read round trip is bit-exact.
"""

from __future__ import annotations

import json
from pathlib import Path

from calibration.camera import Rig
from calibration.formats._common import (
    RigFormatError,
    as_float_array,
    atomic_write_text,
    json_safe,
    load_json,
    make_camera,
    make_rig,
    optional_object,
    pixel_count,
    require,
    require_array,
)

SCHEMA = "gst-capture/rig"
VERSION = 1
CAMERA_KEYS = {"name", "width", "height", "K", "dist", "R", "t", "meta"}


def to_dict(rig: Rig) -> dict:
    return {
        "schema": SCHEMA,
        "version": VERSION,
        "units": "m",
        "convention": "world_to_camera; OpenCV axes (x right, y down, z forward); "
        "pixel (0, 0) is the centre of the top-left pixel",
        "up": [float(v) for v in rig.up],
        "meta": json_safe(rig.meta),
        "cameras": [
            {
                "name": c.name,
                "width": c.width,
                "height": c.height,
                "K": c.K.tolist(),
                "dist": c.dist.tolist(),
                "R": c.R.tolist(),
                "t": c.t.tolist(),
                "meta": json_safe(c.meta),
            }
            for c in rig
        ],
    }


def from_dict(data: dict, path: Path) -> Rig:
    if not isinstance(data, dict):
        raise RigFormatError(f"{path}: expected a JSON object at the top level")
    schema = require(data, "schema", path)
    if schema != SCHEMA:
        raise RigFormatError(f"{path}: schema is '{schema}', expected '{SCHEMA}'")
    version = require(data, "version", path)
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise RigFormatError(f"{path}: version must be a positive integer, got {version!r}")
    if version > VERSION:
        raise RigFormatError(
            f"{path}: rig file version {version} is newer than this reader "
            f"(version {VERSION}); update gst-capture"
        )
    units = data.get("units", "m")
    if units != "m":
        raise RigFormatError(f"{path}: units must be 'm', got '{units}'")
    cams_data = require(data, "cameras", path)
    if not isinstance(cams_data, list):
        raise RigFormatError(f"{path}: 'cameras' must be a list")
    cameras = []
    for i, cd in enumerate(cams_data):
        where = f"cameras[{i}]"
        if not isinstance(cd, dict):
            raise RigFormatError(f"{path}: {where} must be an object")
        unknown = set(cd) - CAMERA_KEYS
        if unknown:
            raise RigFormatError(
                f"{path}: {where} has unknown keys {sorted(unknown)}; "
                f"expected {sorted(CAMERA_KEYS)}"
            )
        name = require(cd, "name", path, where)
        if not isinstance(name, str) or not name:
            raise RigFormatError(f"{path}: {where} name must be a non-empty text, got {name!r}")
        where = f"camera '{name}'"
        cameras.append(
            make_camera(
                path,
                name,
                repair_rotation=False,
                # held to the layout `to_dict` writes (the other formats' readers reshape what
                # has the right size: a flat K, an R of 1 x 9, a nested dist were taken)
                K=require_array(cd, "K", (3, 3), path, where, exact=True),
                dist=require_array(cd, "dist", (None,), path, where, exact=True),
                R=require_array(cd, "R", (3, 3), path, where, exact=True),
                t=require_array(cd, "t", (3,), path, where, exact=True),
                width=pixel_count(require(cd, "width", path, where), path, f"{where} width"),
                height=pixel_count(require(cd, "height", path, where), path, f"{where} height"),
                meta=optional_object(cd, "meta", path, where),
            )
        )
    up = as_float_array(data.get("up", [0.0, 0.0, 1.0]), (3,), path, "up")
    return make_rig(path, cameras, up=tuple(up.tolist()), meta=optional_object(data, "meta", path))


def read(path: str | Path) -> Rig:
    path = Path(path)
    data = load_json(path)
    return from_dict(data, path)


def write(rig: Rig, path: str | Path) -> None:
    atomic_write_text(path, json.dumps(to_dict(rig), indent=2, allow_nan=False) + "\n")


def sniff(path: Path, text: str | None) -> bool:
    return text is not None and f'"{SCHEMA}"' in text

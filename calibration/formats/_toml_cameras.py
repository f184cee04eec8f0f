"""The `[cam_N]` TOML layout shared by aniposelib, FreeMoCap and Pose2Sim.

Each camera table holds `name`, `size` [w, h], `matrix` 3x3, `distortions` (OpenCV order),
`rotation` (Rodrigues vector, world to camera) and `translation` (world to camera); a
`[metadata]` table follows. The formats differ in units and distortion length only. Tables
that hold none of a camera's keys (`[metadata]`, and the `[capture_volume]`, `[charuco]` or
`[checkerboard]` of Caliscope-style files, which Pose2Sim's readers skip too) are not cameras.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import tomllib

from calibration.camera import Rig
from calibration.formats._common import (
    RigFormatError,
    atomic_write_text,
    make_camera,
    make_rig,
    pixel_count,
    read_text,
    require_array,
    require_distortion,
    require_text,
    toml_dumps,
)

_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")
CAMERA_KEYS = ("matrix", "rotation", "translation")
# every key a camera table may hold: a table with any of them is a camera and must hold the
# geometry (a typo'd or truncated camera was dropped without a word)
CAMERA_TABLE_KEYS = ("name", "size", "matrix", "distortions", "rotation", "translation")
# tables of other tools that are not cameras (module doc)
OTHER_TABLES = ("metadata", "capture_volume", "charuco", "checkerboard")


def _bare(name: str) -> bool:
    """Whether a camera name can be its own TOML table key."""
    return bool(_BARE_KEY.match(name)) and name != "metadata"


def camera_tables(data: dict) -> dict[str, dict]:
    """The tables of `data` that describe cameras (any of CAMERA_TABLE_KEYS, outside
    OTHER_TABLES; module doc), and empty ones: a camera listed with no data (a file cut right
    after `[cam_3]`) was dropped without a word, where Pose2Sim and aniposelib fail on it."""
    return {
        key: table
        for key, table in data.items()
        if isinstance(table, dict)
        and key not in OTHER_TABLES
        and (not table or any(k in table for k in CAMERA_TABLE_KEYS))
    }


def load_tables(path: Path) -> dict:
    try:
        return tomllib.loads(read_text(path))
    except tomllib.TOMLDecodeError as exc:
        raise RigFormatError(f"{path}: not valid TOML ({exc})") from exc


def read_cameras(path: Path, metres_per_unit: float, source: str) -> Rig:
    data = load_tables(path)
    cameras = []
    for key, table in camera_tables(data).items():
        where = f"[{key}]"
        if not table:
            raise RigFormatError(
                f"{path}: {where} has no keys; a camera needs {list(CAMERA_TABLE_KEYS)} (a "
                "truncated file, or a table left empty?)"
            )
        lacking = [k for k in CAMERA_KEYS if k not in table]
        if lacking:  # a camera's table without its geometry: typo'd keys or a truncated file
            raise RigFormatError(
                f"{path}: {where} looks like a camera (it has "
                f"{sorted(set(table) & set(CAMERA_TABLE_KEYS))}) but lacks {lacking}; expected "
                f"every one of {list(CAMERA_TABLE_KEYS)} (a typo'd key, or a truncated file?)"
            )
        fisheye = table.get("fisheye", False)
        if not isinstance(fisheye, bool):  # the text "false" read as a fisheye
            raise RigFormatError(f"{path}: {where} fisheye is {fisheye!r}, expected true or false")
        if fisheye:
            raise RigFormatError(
                f"{path}: {where} is a fisheye camera, which this project does not model"
            )
        w, h = require_array(table, "size", (2,), path, where)
        rvec = require_array(table, "rotation", (3,), path, where)
        t = require_array(table, "translation", (3,), path, where)
        for name, value in (("rotation", rvec), ("translation", t)):
            if not np.all(np.isfinite(value)):  # was reported as the R or t made from it
                raise RigFormatError(f"{path}: {where} {name} is not finite: {value.tolist()}")
        cameras.append(
            make_camera(
                path,
                require_text(table, "name", path, where) if "name" in table else key,
                K=require_array(table, "matrix", (3, 3), path, where),
                dist=require_distortion(table, "distortions", path, where),
                R=cv2.Rodrigues(rvec)[0],
                t=t * metres_per_unit,
                width=pixel_count(w, path, f"{where} size[0]"),
                height=pixel_count(h, path, f"{where} size[1]"),
                meta={"source": source, "section": key},
            )
        )
    meta = {"source": source}
    if isinstance(data.get("metadata"), dict):
        meta["metadata"] = data["metadata"]
    return make_rig(path, cameras, up=(0.0, 0.0, 1.0), meta=meta)


def write_cameras(
    rig: Rig,
    path: str | Path,
    metres_per_unit: float,
    dist_len: int,
    keys: str,
    extra: dict | None = None,
    metadata: dict | None = None,
) -> None:
    """`keys`: 'index' gives [cam_0], [cam_1], ...; 'name' uses the camera name when it is a
    bare TOML key (else cam_NN). Distortion is written with `dist_len` terms, or all of them
    when later terms are non-zero (OpenCV reads any valid length)."""
    tables = {}
    for i, c in enumerate(rig):
        if c.skew:  # as COLMAP's and H36M's writers refuse it
            raise RigFormatError(
                f"camera '{c.name}': K[0, 1] = {c.skew} (skew); Pose2Sim and aniposelib "
                "project with cv2.projectPoints, which ignores it (0.45 px off at the corner "
                "for 2 px), so the file would place points elsewhere"
            )
        d = c.dist
        n = dist_len if not np.any(d[dist_len:]) else d.size
        dist = np.zeros(n)
        dist[: min(n, d.size)] = d[:n]
        if keys == "name" and _bare(c.name):
            key = c.name
        elif keys == "index":
            # zero-padded from 11 cameras on: aniposelib orders its cameras by the table names
            # as text, so cam_10 came before cam_2 and 2D points given in rig order went to
            # the wrong cameras
            key = f"cam_{i:0{len(str(len(rig) - 1))}d}"
        else:  # a free cam_NN: ["a b", "cam_01"] gave both [cam_01] and was refused
            taken = {x.name for x in rig if _bare(x.name)} | set(tables)
            key = next(f"cam_{k:02d}" for k in range(i + 1, i + 2 + len(rig) + len(taken))
                       if f"cam_{k:02d}" not in taken)  # fmt: skip
        if key in tables:
            raise RigFormatError(f"two cameras map to the TOML table [{key}]")
        table = {
            "name": c.name,
            "size": [c.width, c.height],
            "matrix": c.K.tolist(),
            "distortions": dist.tolist(),
            "rotation": c.rvec.tolist(),
            "translation": (c.t / metres_per_unit).tolist(),
        }
        table.update(extra or {})
        tables[key] = table
    tables["metadata"] = metadata or {"adjusted": False, "error": 0.0}
    atomic_write_text(path, toml_dumps(tables))


def looks_like_pose2sim(path: Path) -> bool:
    """Pose2Sim writes `fisheye = ...` and 4 distortion terms; aniposelib neither."""
    data = load_tables(path)
    cams = camera_tables(data).values()
    return any(
        "fisheye" in t or (isinstance(t.get("distortions"), list) and len(t["distortions"]) == 4)
        for t in cams
    )


def rms_or_zero(rig: Rig) -> float:
    """The rig's calibration RMS (px) from its meta, for the `[metadata] error` field."""
    value = rig.meta.get("rms_px", 0.0)
    return float(value) if isinstance(value, (int, float)) else 0.0

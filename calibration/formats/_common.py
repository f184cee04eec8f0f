"""Shared helpers for rig file formats: errors, validation, atomic writes, unit scales, TOML."""

from __future__ import annotations

import datetime
import json
import math
import os
from pathlib import Path

import numpy as np

from calibration.camera import Camera, CameraError, Rig, is_pixel_count
from gst.atomic import atomic_write, atomic_write_text  # noqa: F401  (the formats' writers)

UNIT_SCALE = {"m": 1.0, "cm": 0.01, "mm": 0.001}  # metres per unit


class RigFormatError(ValueError):
    """A rig file is malformed or a rig cannot be written in a format; names file and key."""


def metres_per_unit(units: str, fmt: str) -> float:
    if units not in UNIT_SCALE:
        raise RigFormatError(
            f"{fmt}: units '{units}' unknown, expected one of {sorted(UNIT_SCALE)}"
        )
    return UNIT_SCALE[units]


def validate_rig(rig: Rig) -> Rig:
    """Re-run every camera's validation (a Camera built without `create` may be broken).

    Raises CameraError naming the camera; returns the rig unchanged when valid."""
    if not isinstance(rig, Rig):
        raise CameraError(f"expected a Rig, got {type(rig).__name__}")
    if len(rig) == 0:
        raise CameraError("rig has no cameras")
    for cam in rig:
        Camera.create(cam.name, cam.K, cam.dist, cam.R, cam.t, cam.width, cam.height, cam.meta)
    Rig(rig.cameras, rig.up, rig.units, rig.meta)  # rig-level checks (names, up, units)
    return rig


ROUNDED_R_TOL = 1e-3  # rotations printed with few digits are re-orthonormalised up to this error


def make_camera(path: Path, name, *, repair_rotation: bool = True, **fields) -> Camera:
    """Camera.create with the file named in any error.

    Other tools' files often print rotations with 6-8 digits, which breaks orthonormality at
    the 1e-6 level our Camera demands; such a rotation (error below 1e-3) is replaced by the
    nearest rotation matrix and the original error is recorded in the camera's meta. Larger
    errors are refused. `repair_rotation` False (our own rig.json, which stores full precision
    and promises bit-exact reads): the rotation is taken as written, checked to 1e-6."""
    R = fields.get("R")
    if R is not None and repair_rotation:
        R = np.asarray(R, dtype=np.float64)
        if R.shape == (3, 3) and np.all(np.isfinite(R)):
            err = float(np.abs(R @ R.T - np.eye(3)).max())
            if 1e-9 < err <= ROUNDED_R_TOL and np.linalg.det(R) > 0:
                U, _, Vt = np.linalg.svd(R)
                fields["R"] = U @ Vt
                fields["meta"] = {**(fields.get("meta") or {}), "R_orthonormalised_from_error": err}
    try:
        return Camera.create(name, **fields)
    except CameraError as exc:
        raise RigFormatError(f"{path}: {exc}") from exc
    except (TypeError, ValueError) as exc:  # a field that is not a number (int('abc'), a dict)
        raise RigFormatError(f"{path}: camera '{name}': {exc}") from exc


def make_rig(path: Path, cameras: list[Camera], **kwargs) -> Rig:
    if not cameras:
        raise RigFormatError(f"{path}: no cameras found")
    try:
        return Rig(tuple(cameras), **kwargs)
    except CameraError as exc:
        raise RigFormatError(f"{path}: {exc}") from exc


def require(data: dict, key: str, path: Path, where: str = ""):
    if not isinstance(data, dict) or key not in data:
        raise RigFormatError(f"{path}: missing key '{key}'{' in ' + where if where else ''}")
    return data[key]


_JSON_KIND = {
    type(None): "null",
    bool: "true/false",
    int: "a number",
    float: "a number",
    str: "text",
    list: "a list",
    dict: "an object",
}


def require_typed(data: dict, key: str, kind: type, path: Path, where: str = ""):
    """`data[key]`, which must be a `kind` (list or dict: a JSON array or object); else a
    RigFormatError naming the file, the key and what it holds (`cameras: null` was a bare
    "'NoneType' object is not iterable")."""
    value = require(data, key, path, where)
    if not isinstance(value, kind):
        expected = {list: "a list", dict: "an object"}.get(kind, kind.__name__)
        found = _JSON_KIND.get(type(value), type(value).__name__)
        raise RigFormatError(
            f"{path}: '{key}'{' in ' + where if where else ''} must be {expected}, got {found}"
        )
    return value


def read_text(path: Path) -> str:
    """The text of a rig file, which JSON and TOML define as UTF-8; a file in another encoding
    (a name saved as Latin-1 by an editor) is a RigFormatError naming the file and the byte (it
    was a bare UnicodeDecodeError naming neither file nor camera)."""
    data = path.read_bytes()
    try:
        # utf-8-sig: Windows editors save UTF-8 with a byte order mark, which json and tomllib
        # refuse ("Unexpected UTF-8 BOM", "Invalid statement")
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        bad = exc.object  # the bytes after a byte order mark, which exc.start counts in
        line = bad[: exc.start].count(b"\n") + 1
        raise RigFormatError(
            f"{path}: not UTF-8 text (byte 0x{bad[exc.start]:02X} on line {line}); save the "
            "file as UTF-8"
        ) from exc


def load_json(path: Path):
    """The parsed JSON document at `path`; a syntax error, or a key given twice in one object
    (JSON leaves it undefined; Python kept the last: "width": 1920, "width": 640 read 640),
    becomes a RigFormatError."""

    def unique(pairs: list) -> dict:
        keys = [k for k, _ in pairs]
        twice = sorted({k for k in keys if keys.count(k) > 1})
        if twice:
            raise RigFormatError(f"{path}: keys given twice in one object: {twice}")
        return dict(pairs)

    try:
        return json.loads(read_text(path), object_pairs_hook=unique)
    except json.JSONDecodeError as exc:
        raise RigFormatError(f"{path}: not valid JSON ({exc})") from exc


def as_float_array(
    value, shape: tuple[int | None, ...], path: Path, what: str, exact: bool = False
) -> np.ndarray:
    """`value` as a float64 array of `shape`: reshaped when it has the right size, or, `exact`,
    only as written (nested lists of that shape; None in `shape`: any length on that axis)."""
    if _holds_bool(value):  # true read as 1.0 (a focal length of one pixel)
        raise RigFormatError(f"{path}: {what} holds true/false where numbers are expected")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise RigFormatError(f"{path}: {what} is not numeric ({exc})") from exc
    if exact:
        if arr.ndim != len(shape) or any(
            n not in (None, m) for n, m in zip(shape, arr.shape, strict=True)
        ):
            raise RigFormatError(f"{path}: {what} has shape {arr.shape}, expected {shape}")
        return arr
    if arr.size != int(np.prod(shape)):
        raise RigFormatError(f"{path}: {what} has shape {arr.shape}, expected {shape}")
    return arr.reshape(shape)


def require_array(
    data: dict,
    key: str,
    shape: tuple[int | None, ...],
    path: Path,
    where: str,
    exact: bool = False,
) -> np.ndarray:
    """`data[key]` as a float64 array of `shape` (`as_float_array`); a missing or malformed
    value is a RigFormatError naming the file, `where` and the key (the readers' usual pairing of
    `require` and `as_float_array`)."""
    value = require(data, key, path, where)
    return as_float_array(value, shape, path, f"{where} {key}", exact)


def require_distortion(data: dict, key: str, path: Path, where: str) -> np.ndarray:
    """`data[key]` as a flat float64 array. The key is required: a file that leaves it out is
    refused rather than read as a lens without distortion (the formats' own readers fail on it
    too); a lens without distortion is written as an empty list."""
    value = require(data, key, path, where)
    if value is None or _holds_bool(value):  # null read as one NaN term
        found = "null" if value is None else "true/false"
        raise RigFormatError(f"{path}: {where} {key} is {found}, expected a list of numbers")
    try:
        return np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError) as exc:
        raise RigFormatError(f"{path}: {where} {key} is not a list of numbers ({exc})") from exc


def _holds_bool(value) -> bool:
    if isinstance(value, (bool, np.bool_)):
        return True
    if isinstance(value, (list, tuple)):
        return any(_holds_bool(v) for v in value)
    return isinstance(value, np.ndarray) and value.dtype == bool


def optional_object(data: dict, key: str, path: Path, where: str = "") -> dict:
    """`data[key]` when it is an object (JSON) or table (TOML), {} when absent or null; else a
    RigFormatError naming the key (a list was taken as meta, and writers failed on it later
    with a bare AttributeError)."""
    value = data.get(key)
    if value is None:
        return {}
    if not isinstance(value, dict):
        found = _JSON_KIND.get(type(value), type(value).__name__)
        raise RigFormatError(
            f"{path}: '{key}'{' in ' + where if where else ''} must be an object, got {found}"
        )
    return value


def require_text(data: dict, key: str, path: Path, where: str = "") -> str:
    """`data[key]` as non-empty text (a null or a table as a camera name became 'None')."""
    value = require(data, key, path, where)
    if not isinstance(value, str) or not value:
        found = _JSON_KIND.get(type(value), type(value).__name__)
        raise RigFormatError(
            f"{path}: '{key}'{' in ' + where if where else ''} must be non-empty text, "
            f"got {found if value != '' else 'empty text'}"
        )
    return value


def pixel_count(value, path: Path, what: str) -> int:
    """An image side in pixels: a whole number (1920 or 1920.0), never a bool or 1000.9."""
    if not is_pixel_count(value):
        shown = value.item() if isinstance(value, np.generic) else value
        raise RigFormatError(f"{path}: {what} is {shown!r}, expected a whole number of pixels")
    return int(value)


def five_term_dist(camera: Camera, fmt: str) -> np.ndarray:
    """The camera's distortion as k1, k2, p1, p2, k3, for formats whose lens model stops there
    (Panoptic, H36M JSON): a camera with non-zero rational or thin-prism terms is refused, since
    readers of those formats would ignore the terms and project elsewhere."""
    d = trim_dist(camera.dist)
    if d.size > 5:
        raise RigFormatError(
            f"camera '{camera.name}': distortion {camera.dist.tolist()} needs more than "
            f"the 5 OpenCV terms (k1, k2, p1, p2, k3) the {fmt} format holds"
        )
    return d


def trim_dist(dist: np.ndarray, min_len: int = 5) -> np.ndarray:
    """Shortest valid OpenCV distortion vector (length 4, 5, 8, 12 or 14, at least `min_len`)
    holding all non-zero terms of `dist`."""
    d = np.asarray(dist, dtype=np.float64).ravel()
    nz = np.flatnonzero(d)
    need = max(min_len, int(nz[-1]) + 1 if len(nz) else 0)
    for n in (4, 5, 8, 12, 14):
        if n >= need:
            out = np.zeros(n)
            out[: min(n, len(d))] = d[:n]
            return out
    raise RigFormatError(f"distortion has {len(d)} terms, more than OpenCV's 14")


# -- a small TOML writer (tomllib reads; the standard library cannot write TOML) ---------------
def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if not math.isfinite(f):
            raise RigFormatError(f"cannot write non-finite number {f} to TOML")
        return repr(f)
    if isinstance(v, str):
        return '"' + "".join(_toml_char(ch) for ch in v) + '"'
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise RigFormatError(f"cannot write {type(v).__name__} to TOML")


def _toml_char(ch: str) -> str:
    """One character of a TOML basic string: quote and backslash escaped, every control
    character (which TOML forbids raw) as \\uXXXX."""
    if ch in ('"', "\\"):
        return "\\" + ch
    if ord(ch) < 0x20 or ord(ch) == 0x7F:
        return f"\\u{ord(ch):04X}"
    return ch


def toml_dumps(tables: dict[str, dict]) -> str:
    """TOML text for {table name: {key: scalar or (nested) list}}."""
    lines = []
    for table, items in tables.items():
        lines.append(f"[{table}]")
        lines += [f"{k} = {toml_value(v)}" for k, v in items.items()]
        lines.append("")
    return "\n".join(lines)


def json_safe(value):
    """Meta values made JSON-serialisable (numpy scalars and arrays to Python; dict keys to text,
    tuples to lists, as JSON has them) and strict JSON: a NaN or infinite number is null (a
    camera without residuals has `rms_px` NaN, which Python wrote as a bare NaN that jq,
    JavaScript and serde refuse). Dates and times (TOML has them, e.g. a [metadata] table's
    `calibrated = 2024-05-02T10:31:00`) become their ISO 8601 text."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        return json_safe(value.item())
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, (datetime.date, datetime.time)):  # a datetime is a date
        return value.isoformat()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    # json.dumps failed on it later with a TypeError naming neither file nor key
    raise RigFormatError(
        f"meta value {value!r} of type {type(value).__name__} cannot be written as JSON"
    )

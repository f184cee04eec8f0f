"""Standard 3D Gaussian Splatting PLY files (binary little endian), as common viewers read them.

One vertex per Gaussian with float32 properties, in this order:
    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3
- f_dc: degree-0 spherical-harmonic colour, rgb = 0.5 + SH_C0 * f_dc (SH_C0 = 0.28209479...).
- opacity: logit of the [0, 1] opacity; scale: natural log of the linear scale (metres);
  rot: quaternion w x y z (viewers normalise it; a zero one, which the rasteriser reads as no
  rotation, is written as 1 0 0 0); normals are written as zeros.
- No f_rest_* (degree 0 only): viewers that read the properties by name (SuperSplat, gsplat,
  antimatter15/splat) open the files as they are; the INRIA SIBR viewer reads a fixed record
  per Gaussian and needs `--sh_degree 0` (or its degree-0 build) for them.
Opacities are clipped to [1e-6, 1 - 1e-6] and scales to >= 1e-12 before the logit / log, so
the file holds finite numbers for fully transparent, fully opaque or degenerate Gaussians.

The reader accepts any property order, float or double properties, extra properties
(f_rest_*, normals) and ignores them; it needs x y z, f_dc_0..2, opacity, scale_0..2, rot_0..3.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from gst.atomic import atomic_write
from gst.render.conventions import QUAT_EPS

SH_C0 = 0.28209479177387814
OPACITY_CLIP = 1e-6
SCALE_MIN = 1e-12

_WRITE_PROPS = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    + [f"scale_{i}" for i in range(3)]
    + [f"rot_{i}" for i in range(4)]
)
_REQUIRED = (
    ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    + [f"scale_{i}" for i in range(3)]
    + [f"rot_{i}" for i in range(4)]
)
_PLY_TYPES = {
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
    "uchar": "u1", "uint8": "u1", "char": "i1", "int8": "i1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
}  # fmt: skip


class PlyFormatError(ValueError):
    """A PLY file is not a binary little-endian Gaussian splat file; the message says why."""


@dataclass
class GaussianCloud:
    """Gaussians in the rasteriser's conventions (float32 tensors, N Gaussians)."""

    means: Tensor  # (N, 3) metres
    quats: Tensor  # (N, 4) wxyz, as stored (not normalised)
    scales: Tensor  # (N, 3) linear
    opacities: Tensor  # (N,) in (0, 1)
    colors: Tensor  # (N, 3) rgb


def _as_numpy(name: str, value, shape_tail: tuple[int, ...], n: int | None) -> np.ndarray:
    arr = value.detach().cpu().numpy() if isinstance(value, Tensor) else np.asarray(value)
    arr = arr.astype(np.float64)
    expected_n = arr.shape[0] if n is None else n
    if arr.ndim != 1 + len(shape_tail) or arr.shape != (expected_n, *shape_tail):
        want = ", ".join(["N", *map(str, shape_tail)])
        raise ValueError(f"write_gaussians_ply: {name} has shape {arr.shape}, expected ({want})")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"write_gaussians_ply: {name} contains NaN or Inf")
    return arr


def write_gaussians_ply(path, means, quats, scales, opacities, colors) -> Path:
    """Write N Gaussians (torch or numpy, any float dtype) to `path` atomically.

    Args are in the rasteriser's conventions: means (N, 3), quats (N, 4) wxyz, scales (N, 3)
    linear, opacities (N,) in [0, 1], colors (N, 3) rgb. Returns the path written.
    """
    path = Path(path)
    m = _as_numpy("means", means, (3,), None)
    n = m.shape[0]
    q = _as_numpy("quats", quats, (4,), n)
    s = _as_numpy("scales", scales, (3,), n)
    o = _as_numpy("opacities", opacities, (), n)
    c = _as_numpy("colors", colors, (3,), n)

    o = np.clip(o, OPACITY_CLIP, 1.0 - OPACITY_CLIP)
    # the rasteriser reads a (near) zero quaternion as no rotation; viewers divide by its norm
    # (NaN): the file says what the rasteriser rendered
    q = np.where((np.linalg.norm(q, axis=1) < QUAT_EPS)[:, None], [1.0, 0.0, 0.0, 0.0], q)
    with np.errstate(over="ignore"):  # beyond float32: refused just below, by name
        columns = np.concatenate(
            [
                m,
                np.zeros((n, 3)),
                (c - 0.5) / SH_C0,
                np.log(o / (1.0 - o))[:, None],
                # the rasteriser renders |s| (R diag(s) loses the sign): write that, not 1e-12
                np.log(np.maximum(np.abs(s), SCALE_MIN)),
                q,
            ],
            axis=1,
        ).astype("<f4")
    if not np.all(np.isfinite(columns)):  # finite in float64, beyond float32's range
        bad = sorted({_WRITE_PROPS[j] for j in np.nonzero(~np.isfinite(columns))[1]})
        raise ValueError(f"write_gaussians_ply: {bad} exceed float32's range (about 3.4e38)")
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {n}\n"
        + "".join(f"property float {p}\n" for p in _WRITE_PROPS)
        + "end_header\n"
    ).encode("ascii")

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(header)
            f.write(np.ascontiguousarray(columns).tobytes())

    atomic_write(path, write)
    return path


def _parse_header(f, path: Path) -> tuple[int, np.dtype, int]:
    """Return (vertex count, vertex record dtype, byte offset of the vertex data)."""
    first = f.readline()
    if first.strip() != b"ply":
        raise PlyFormatError(f"{path}: not a PLY file (first line {first[:20]!r})")
    count = None
    fields: list[tuple[str, str]] = []
    element = None
    formatted = False
    while True:
        line = f.readline()
        if not line:
            raise PlyFormatError(f"{path}: header has no end_header")
        words = line.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            formatted = True
            if words[1:2] != ["binary_little_endian"]:
                raise PlyFormatError(
                    f"{path}: format {' '.join(words[1:])!r}, expected binary_little_endian"
                )
        elif words[0] == "element":
            element = words[1]  # elements after vertex are stored after its data: ignored
            if element == "vertex":
                if len(words) < 3 or not words[2].isdigit():
                    raise PlyFormatError(f"{path}: vertex count {' '.join(words[2:])!r}")
                count = int(words[2])
            elif count is None:
                raise PlyFormatError(f"{path}: element {element!r} precedes the vertex element")
        elif words[0] == "property" and element == "vertex":
            if words[1] == "list":
                raise PlyFormatError(f"{path}: list property {words[-1]!r} in vertex element")
            if words[1] not in _PLY_TYPES:
                raise PlyFormatError(f"{path}: unknown property type {words[1]!r}")
            if words[2] in dict(fields):  # numpy's "field occurs more than once"
                raise PlyFormatError(f"{path}: vertex property {words[2]!r} given twice")
            fields.append((words[2], _PLY_TYPES[words[1]]))
    if not formatted:  # read as little endian without a word
        raise PlyFormatError(f"{path}: header has no format line")
    if count is None:
        raise PlyFormatError(f"{path}: no vertex element")
    missing = [p for p in _REQUIRED if p not in dict(fields)]
    if missing:
        raise PlyFormatError(f"{path}: vertex element lacks properties {missing}")
    return count, np.dtype(fields), f.tell()


def read_gaussians_ply(path) -> GaussianCloud:
    """Read a 3DGS PLY (ours or another tool's) into rasteriser conventions (float32)."""
    path = Path(path)
    with open(path, "rb") as f:
        count, dtype, offset = _parse_header(f, path)
        data = f.read(count * dtype.itemsize)
    if len(data) != count * dtype.itemsize:
        raise PlyFormatError(
            f"{path}: truncated: {len(data)} bytes of vertex data, expected "
            f"{count * dtype.itemsize} for {count} vertices"
        )
    rec = np.frombuffer(data, dtype=dtype, count=count)
    # NaN (anywhere) or an infinite position, colour or rotation was read into the cloud without
    # a word; an infinite log-scale or opacity logit still means a scale or opacity of 0 or 1
    bad = [
        p
        for p in _REQUIRED
        if np.isnan(rec[p]).any()
        or (not p.startswith(("scale", "opacity")) and np.isinf(rec[p]).any())
    ]
    if bad:
        raise PlyFormatError(f"{path}: vertex properties {bad} hold NaN or Inf")

    def cols(names):
        return np.stack([rec[name].astype(np.float64) for name in names], axis=1)

    logit = rec["opacity"].astype(np.float64)
    cloud = {
        "means": cols(["x", "y", "z"]),
        "quats": cols([f"rot_{i}" for i in range(4)]),
        "scales": np.exp(cols([f"scale_{i}" for i in range(3)])),
        "opacities": 1.0 / (1.0 + np.exp(-logit)),
        "colors": 0.5 + SH_C0 * cols(["f_dc_0", "f_dc_1", "f_dc_2"]),
    }
    return GaussianCloud(**{k: torch.from_numpy(v.astype(np.float32)) for k, v in cloud.items()})

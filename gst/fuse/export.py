"""Marker files for biomechanics tools: TRC (OpenSim) and C3D, one file per person.

Markers are the fitted body's 24 joints, named as the SMPL joints (`pelvis`, `left_hip`, ...,
gst.body.skeleton.SMPL_JOINT_NAMES), in metres in the TRC and millimetres in the C3D.

TRC: OpenSim expects Y up, so the rig's Z-up world is rotated by -90 degrees about X:
(x, y, z)_trc = (x, z, -y)_world (a proper rotation; the floor z = 0 becomes y = 0). Header as
OpenSim writes it (PathFileType 4, DataRate ... OrigNumFrames, `Frame#  Time  names`, then
`X1 Y1 Z1 ...`), tab-separated; Frame# is the 1-based video frame, Time = frame / fps.

C3D: written with the `c3d` package (pure Python, 0.6.0) as float points (POINT:SCALE < 0, so
values are stored exactly as float32), POINT:UNITS "mm", the rig's world axes (Z up), frames
numbered from the person's first video frame + 1. Every fitted joint is a valid point (readers
zero the coordinates of points with a negative residual, so -1 would lose the fit's value):
residual 0 marks a joint observed by >= 2 cameras, residual 1 a joint filled by the fit.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from gst.atomic import atomic_write
from gst.body.skeleton import SMPL_JOINT_NAMES

__all__ = ["Z_UP_TO_Y_UP", "write_trc", "read_trc", "write_c3d", "read_c3d"]

Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def write_trc(
    path: str | Path,
    frames: np.ndarray,
    points: np.ndarray,
    fps: float,
    names: tuple[str, ...] = SMPL_JOINT_NAMES,
) -> None:
    """`points` (T, M, 3) metres in the rig world (Z up), written Y up (see module doc)."""
    path = Path(path)
    T, M = points.shape[:2]
    if len(names) != M or len(frames) != T:
        raise ValueError(
            f"write_trc: {T} frames x {M} markers need {M} names and {T} frame numbers"
        )
    yup = points @ Z_UP_TO_Y_UP.T
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame"
        "\tOrigNumFrames",
        f"{fps:.2f}\t{fps:.2f}\t{T}\t{M}\tm\t{fps:.2f}\t{int(frames[0]) + 1 if T else 1}\t{T}",
        "Frame#\tTime\t" + "\t".join(f"{n}\t\t" for n in names).rstrip("\t"),
        "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, M + 1)),
        "",
    ]
    for f, row in zip(frames, yup, strict=True):
        vals = "\t".join("" if not np.isfinite(v) else f"{v:.6f}" for v in row.ravel())
        lines.append(f"{int(f) + 1}\t{f / fps:.6f}\t{vals}")

    def write(tmp: str) -> None:
        Path(tmp).write_text("\n".join(lines) + "\n")

    atomic_write(path, write)


def read_trc(path: str | Path) -> tuple[dict[str, str], list[str], np.ndarray, np.ndarray]:
    """(header values, marker names, frame numbers (T,), points (T, M, 3) as written, Y up)."""
    lines = Path(path).read_text().splitlines()
    keys, values = lines[1].split("\t"), lines[2].split("\t")
    header = dict(zip(keys, values, strict=True))
    names = [n for n in lines[3].split("\t")[2:] if n]
    rows = [ln.split("\t") for ln in lines[6:] if ln.strip()]
    frames = np.array([int(r[0]) for r in rows])
    pts = np.array([[float(v) if v else np.nan for v in r[2:]] for r in rows]).reshape(
        len(rows), len(names), 3
    )
    return header, names, frames, pts


# the c3d library's notice that a file has no analog channels: ours hold markers only, by design
_NO_ANALOG = "No analog data found"


def write_c3d(
    path: str | Path,
    frames: np.ndarray,
    points: np.ndarray,
    fps: float,
    valid: np.ndarray | None = None,
    names: tuple[str, ...] = SMPL_JOINT_NAMES,
) -> None:
    """`points` (T, M, 3) metres, rig world; stored in mm as float32 (see module doc)."""
    import c3d

    T, M = points.shape[:2]
    valid = np.ones((T, M), bool) if valid is None else np.asarray(valid, bool)
    writer = c3d.Writer(point_rate=float(fps), analog_rate=0.0, point_scale=-1.0)
    writer.set_point_labels([n[:30] for n in names])
    writer.set_start_frame(int(frames[0]) + 1 if T else 1)
    pts = np.zeros((T, M, 5), np.float32)
    pts[..., :3] = np.nan_to_num(points * 1000.0).astype(np.float32)
    pts[..., 3] = np.where(valid, 0.0, 1.0)
    pts[..., 3] = np.where(np.isfinite(points).all(-1), pts[..., 3], -1.0)
    writer.add_frames([(pts[i], np.zeros((0, 0), np.float32)) for i in range(T)])

    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh, warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=_NO_ANALOG)
            writer.write(fh)

    atomic_write(Path(path), write)


def read_c3d(path: str | Path) -> tuple[list[str], float, np.ndarray, np.ndarray]:
    """(marker names, rate, frame numbers (T,), points (T, M, 4): x, y, z in mm, residual)."""
    import c3d

    with open(path, "rb") as fh, warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=_NO_ANALOG)
        reader = c3d.Reader(fh)
        names = [s.strip() for s in reader.point_labels]
        rate = float(reader.point_rate)
        frames, pts = [], []
        for i, p, _ in reader.read_frames():
            frames.append(i)
            pts.append(p[:, :4].copy())
    return names, rate, np.array(frames), np.array(pts, np.float32).reshape(len(frames), -1, 4)

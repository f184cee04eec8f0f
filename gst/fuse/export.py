"""Marker files for biomechanics tools: TRC (OpenSim) and C3D, one file per person.

Markers are the fitted body's 24 joints, named as the SMPL joints (`pelvis`, `left_hip`, ...,
gst.body.skeleton.SMPL_JOINT_NAMES), in metres in the TRC and millimetres in the C3D.

TRC: OpenSim expects Y up, so the rig's world is rotated to put its up (`Rig.up`) on +Y
(`y_up_rotation`). For the usual Z-up world that is -90 degrees about X: (x, y, z)_trc =
(x, z, -y)_world (a proper rotation; the floor z = 0 becomes y = 0); a world with another up
(a Panoptic rig's Y-down world, say) is first turned, by the smallest rotation, so that its up
is +Z. Header as
OpenSim writes it (PathFileType 4, DataRate ... OrigNumFrames, `Frame#  Time  names`, then
`X1 Y1 Z1 ...`), tab-separated, each data row ending in a tab as OpenSim's own writer ends
them (OpenSim drops a line's empty last field, so a row whose last marker is missing was one
field short and the whole file refused); Frame# is the 1-based video frame, Time =
(Frame# - 1) / fps, the 0-based video frame over the rate.

Both files hold one row per video frame from the person's first fitted frame to their last, at
the constant rate they declare: a frame inside a gap the fit does not fill (longer than
`fuse.fill_gaps_s`) is a row of missing markers (blank TRC cells, C3D residual -1), not left
out; a C3D has no frame column, so a dropped row would put every later frame early.

C3D: written with the `c3d` package (pure Python, 0.6.0) as float points (POINT:SCALE < 0, so
values are stored exactly as float32; its size 1 / k, the largest coordinate / 32000 mm rounded
up so that the nominal residual is a whole byte), POINT:UNITS "mm", the rig's world axes
(POINT:Y_SCREEN is the world axis nearest its up, so viewers draw it upright). Frames are
numbered from the person's first video frame + 1 where that fits the header's 16-bit first
frame (video frames up to 65533; the `c3d` reader miscounts a file whose header had to clamp
it) and their last fits its 16-bit last frame (up to 65535), else from 1; the parameter
GST:FIRST_FRAME (a float) always holds the first row's video frame (0-based). Every fitted
joint is a valid point. Residuals as the C3D format defines them: a positive residual marks a
measured point (here 1 for a joint observed by >= 2 cameras: a nominal value; its reprojection
error in pixels is in the fused Parquet), 0 a point not measured but modelled (a joint the fit
filled), -1 a missing value, whose coordinates are 0 (the `c3d` 0.6 writer left the last valid
frame's there, a body frozen through a gap, so they are cleared in the written file). The
residual word's camera byte holds the measuring cameras 1-7 (bit i: camera i + 1).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from gst.atomic import atomic_write
from gst.body.skeleton import SMPL_JOINT_NAMES

__all__ = [
    "Z_UP_TO_Y_UP",
    "every_frame",
    "y_up_rotation",
    "write_trc",
    "read_trc",
    "write_c3d",
    "read_c3d",
]

Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
Z_UP = (0.0, 0.0, 1.0)


def y_up_rotation(up=Z_UP) -> np.ndarray:
    """(3, 3) rotation taking world points to the TRC's Y-up axes: the smallest rotation that
    turns `up` onto +Z (scipy's `Rotation.align_vectors`, also for up near -Z), then
    `Z_UP_TO_Y_UP` (exactly that for a Z-up world)."""
    from scipy.spatial.transform import Rotation

    u = np.asarray(up, np.float64)
    if u.shape != (3,) or not np.isfinite(u).all() or np.linalg.norm(u) < 1e-9:
        raise ValueError(f"the world's up must be a finite non-zero 3-vector, got {up!r}")
    align = Rotation.align_vectors([[0.0, 0.0, 1.0]], [u / np.linalg.norm(u)])[0].as_matrix()
    return Z_UP_TO_Y_UP @ align


def _screen_axes(up) -> tuple[str, str]:
    """C3D POINT:X_SCREEN / Y_SCREEN: the world axis nearest `up` drawn vertical."""
    u = np.asarray(up, np.float64)
    k = int(np.argmax(np.abs(u)))
    vertical = ("+" if u[k] > 0 else "-") + "XYZ"[k]
    return ("+Y" if k == 0 else "+X"), vertical


def write_trc(
    path: str | Path,
    frames: np.ndarray,
    points: np.ndarray,
    fps: float,
    names: tuple[str, ...] = SMPL_JOINT_NAMES,
    up=Z_UP,
) -> None:
    """`points` (T, M, 3) metres in the rig world whose up is `up`, written Y up (module doc)."""
    path = Path(path)
    T, M = points.shape[:2]
    if len(names) != M or len(frames) != T:
        raise ValueError(
            f"write_trc: {T} frames x {M} markers need {M} names and {T} frame numbers"
        )
    if T == 0:  # OpenSim's reader skips blank lines before the first row: at the end of a
        # file with none it never stops (and write_c3d refuses such a person too)
        raise ValueError(f"write_trc: {path}: no frame to write (a TRC holds at least one)")
    frames, points, _ = every_frame(frames, points)
    T = len(frames)
    yup = points @ y_up_rotation(up).T
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame"
        "\tOrigNumFrames",
        f"{fps:.10g}\t{fps:.10g}\t{T}\t{M}\tm\t{fps:.10g}\t{int(frames[0]) + 1}\t{T}",
        "Frame#\tTime\t" + "\t".join(f"{n}\t\t" for n in names).rstrip("\t"),
        "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, M + 1)),
        "",
    ]
    for f, row in zip(frames, yup, strict=True):
        vals = "\t".join("" if not np.isfinite(v) else f"{v:.6f}" for v in row.ravel())
        lines.append(f"{int(f) + 1}\t{f / fps:.6f}\t{vals}\t")

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
    width = 3 * len(names)  # rows end in a tab (an empty last field): write_trc
    pts = np.array([[float(v) if v else np.nan for v in r[2 : 2 + width]] for r in rows])
    pts = pts.reshape(len(rows), len(names), 3)
    return header, names, frames, pts


def every_frame(
    frames: np.ndarray, points: np.ndarray, valid: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frames, points, valid) with one row per frame from the first to the last: rows for
    frames that `frames` skips hold NaN points and valid False. `frames` must increase."""
    frames = np.asarray(frames, np.int64)
    points = np.asarray(points, np.float64)
    valid = np.ones(points.shape[:2], bool) if valid is None else np.asarray(valid, bool)
    if len(frames) and not (np.diff(frames) > 0).all():
        raise ValueError(f"marker rows need increasing frames, got {frames.tolist()[:10]} ...")
    if len(frames) == 0 or frames[-1] - frames[0] + 1 == len(frames):
        return frames, points, valid
    every = np.arange(frames[0], frames[-1] + 1)
    at = frames - frames[0]
    dense = np.full((len(every), *points.shape[1:]), np.nan)
    dense[at] = points
    dense_valid = np.zeros((len(every), points.shape[1]), bool)
    dense_valid[at] = valid
    return every, dense, dense_valid


# the c3d library's notice that a file has no analog channels: ours hold markers only, by design
_NO_ANALOG = "No analog data found"
# the header's first frame is 16 bits: the `c3d` reader miscounts a file whose first frame had
# to be clamped to 65535, so later starts are numbered from 1 (GST:FIRST_FRAME keeps the truth)
_LAST_HEADER_START = 65534
_HEADER_FRAME_MAX = 65535  # the header's last frame (16 bits)
_GST_GROUP_ID = 10
C3D_LABEL_CHARS = 30  # POINT:LABELS entries: the length C3D tools assume (Vicon, Mokka)


def write_c3d(
    path: str | Path,
    frames: np.ndarray,
    points: np.ndarray,
    fps: float,
    valid: np.ndarray | None = None,
    names: tuple[str, ...] = SMPL_JOINT_NAMES,
    up=Z_UP,
    cameras: np.ndarray | None = None,
) -> None:
    """`points` (T, M, 3) metres, rig world (up `up`); stored in mm as float32 (module doc).
    `cameras`: (T, M) bit masks of the cameras that measured each point, for the residual
    word's camera byte (cameras 1-7 only: the byte has 7 bits)."""
    import c3d

    T0 = len(frames)
    if T0 == 0:  # the `c3d` writer's own error said "Expected frame input ... shape (1, 0)"
        raise ValueError(f"write_c3d: {path}: no frame to write (a C3D holds at least one)")
    mask = np.zeros((T0, points.shape[1]), np.int64) if cameras is None else np.asarray(cameras)
    if mask.shape != points.shape[:2]:
        raise ValueError(f"write_c3d: cameras has shape {mask.shape}, expected {points.shape[:2]}")
    # only cameras 1-7 fit the byte; taken before the float padding, which cannot hold a mask
    # with a bit past 2^53 exactly (camera 54 on lost cameras 1-7's bits)
    low = (mask.astype(np.int64) & 0x7F).astype(np.float64)
    _, mask_rows, _ = every_frame(frames, low[..., None], valid)
    frames, points, valid = every_frame(frames, points, valid)
    T, M = points.shape[:2]
    if len(names) != M:
        raise ValueError(f"write_c3d: {M} markers need {M} names, got {len(names)}")
    mm = np.abs(points[np.isfinite(points)]) * 1000.0
    # float storage (negative scale) whose size is what the format asks for, the largest
    # coordinate / 32000 mm (a tool converting the file to integers keeps 0.1 mm where -1 kept
    # 1 mm), rounded up to 1 / k so that the nominal residual 1 is a whole k in its byte
    k = int(np.clip(32000.0 / mm.max(), 1, 100)) if mm.size and mm.max() > 0 else 1
    scale = -1.0 / k
    writer = c3d.Writer(point_rate=float(fps), analog_rate=0.0, point_scale=scale)
    long = [n for n in names if len(n) > C3D_LABEL_CHARS]
    if long:  # cut, two labels could become one, and the TRC keeps them whole
        raise ValueError(
            f"write_c3d: marker names {long} are longer than a C3D label's "
            f"{C3D_LABEL_CHARS} characters"
        )
    writer.set_point_labels(list(names))
    writer.set_screen_axis(*_screen_axes(up))  # viewers draw the rig's world upright
    first = int(frames[0]) if T else 0
    # the header's last frame is 16 bits too: a start that fits with an end that does not
    # (first seen at 60000, 8000 frames) had a header of 5535 frames over 8000 rows
    fits = first + 1 <= _LAST_HEADER_START and first + T <= _HEADER_FRAME_MAX
    writer.set_start_frame(first + 1 if fits else 1)
    group = writer.add_group(_GST_GROUP_ID, "GST", "gst-capture")
    # a float (element size 4 is the format's float; an int32 under that label read as
    # 1.4e-43 in every reader but ours), exact to 2^24 frames (77 hours at 60 fps)
    group.set("FIRST_FRAME", "video frame of the first row (0-based)", 4, "<f", np.float32(first))
    pts = np.zeros((T, M, 5), np.float32)
    pts[..., :3] = np.nan_to_num(points * 1000.0).astype(np.float32)
    pts[..., 3] = np.where(valid, 1.0, 0.0)  # measured 1 (nominal), modelled 0: module doc
    missing = ~np.isfinite(points).all(-1)
    pts[..., 3] = np.where(missing, -1.0, pts[..., 3])
    # the camera byte of measured points (the format's high byte; ezc3d reads it as the
    # residual, so without it every measured point read as modelled there)
    bits = np.nan_to_num(mask_rows[..., 0]).astype(np.int64) & 0x7F
    pts[..., 4] = np.where(valid & ~missing, bits, 0)
    writer.add_frames([(pts[i], np.zeros((0, 0), np.float32)) for i in range(T)])

    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh, warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=_NO_ANALOG)
            writer.write(fh)
        _zero_missing_points(tmp, missing)

    atomic_write(Path(path), write)


def _zero_missing_points(path: str, missing: np.ndarray) -> None:
    """Clear the x, y, z of the (T, M) `missing` points in a float C3D without analog data just
    written: the `c3d` writer keeps one buffer for all frames and leaves a missing point's
    coordinates as the last frame that had it (the format wants them 0). Frames are contiguous
    from the header's data block, each M points of four float32 (x, y, z, residual word)."""
    import c3d

    if not missing.any():
        return
    with open(path, "rb") as fh, warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=_NO_ANALOG)
        header = c3d.Reader(fh).header
    start = 512 * (int(header.data_block) - 1)
    used = int(header.point_count)
    if used != missing.shape[1] or int(header.analog_count) != 0:
        raise RuntimeError(f"{path}: unexpected C3D layout ({used} points, analog data)")
    with open(path, "r+b") as fh:
        for t, m in zip(*np.nonzero(missing), strict=True):
            fh.seek(start + (int(t) * used + int(m)) * 16)
            fh.write(np.zeros(3, "<f4").tobytes())


def read_c3d(path: str | Path) -> tuple[list[str], float, np.ndarray, np.ndarray]:
    """(marker names, rate, frame numbers (T,): the 1-based video frames (GST:FIRST_FRAME + 1
    onwards where the file has it, else the file's own numbers), points (T, M, 4): x, y, z in
    mm, residual)."""
    import c3d

    with open(path, "rb") as fh, warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=_NO_ANALOG)
        reader = c3d.Reader(fh)
        names = [s.strip() for s in reader.point_labels]
        rate = float(reader.point_rate)
        first = reader.get("GST:FIRST_FRAME")
        frames, pts = [], []
        for i, p, _ in reader.read_frames():
            frames.append(i)
            pts.append(p[:, :4].copy())
    frames = np.array(frames, np.int64)
    if first is not None:
        frames = _first_frame(first) + 1 + np.arange(len(frames))
    return names, rate, frames, np.array(pts, np.float32).reshape(len(frames), -1, 4)


def _first_frame(param) -> int:
    """GST:FIRST_FRAME: a float; files written before 2026-12-01 held an int32 under the float
    label (read as a float, a denormal near 0 for any frame but 0)."""
    value = float(param.float_value)
    if np.isfinite(value) and value >= 0 and value == round(value) and (value == 0 or value >= 1):
        return int(value)
    return int(param.int32_value)

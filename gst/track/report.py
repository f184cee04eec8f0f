"""Looking at tracks: an overlay video (skeletons, boxes and ids on the frames) and a summary PNG
of joint angles over time."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa

from gst.atomic import atomic_path, atomic_write
from gst.body.markers import BLAZEPOSE_NAMES
from gst.detect.persons import BONES, TORSO
from gst.track.read import column_array, read_metadata, read_tracks
from gst.track.schema import SMPL_JOINT_NAMES
from gst.video import iter_frames, read_frames

# SMPL kinematic tree: parent of each joint (-1 for the root).
SMPL_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)

# BlazePose bones drawn for the landmark model's skeleton: limbs, torso outline, shoulders-nose.
LANDMARK_BONES = BONES + tuple(zip(TORSO, TORSO[1:] + TORSO[:1], strict=True)) + ((0, 11), (0, 12))
# Left and right drawn apart, so that a person read the wrong way round shows: the landmark
# model's right-side bones light blue, the others white; the network's right joints dark, the
# others white.
_RIGHT_LANDMARKS = frozenset(i for i, n in enumerate(BLAZEPOSE_NAMES) if n.startswith("right_"))
_RIGHT_JOINTS = frozenset(i for i, n in enumerate(SMPL_JOINT_NAMES) if n.startswith("right_"))
_LANDMARK_RIGHT_COLOUR = (255, 200, 120)  # BGR light blue

# Angle at the middle joint between the segments to the first and last joint
# (degrees, 180 = straight).
_J = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
ANGLES = {
    "left_knee": ("left_hip", "left_knee", "left_ankle"),
    "right_knee": ("right_hip", "right_knee", "right_ankle"),
    "left_elbow": ("left_shoulder", "left_elbow", "left_wrist"),
    "right_elbow": ("right_shoulder", "right_elbow", "right_wrist"),
    "left_hip": ("spine1", "left_hip", "left_knee"),
    "right_hip": ("spine1", "right_hip", "right_knee"),
}


def joint_angles(joints3d: np.ndarray) -> dict[str, np.ndarray]:
    """Inner angles (degrees) at knees, elbows and hips from (N, 24, 3) joints; 180 = straight."""
    out = {}
    for name, (a, b, c) in ANGLES.items():
        u = joints3d[:, _J[a]] - joints3d[:, _J[b]]
        v = joints3d[:, _J[c]] - joints3d[:, _J[b]]
        cos = np.sum(u * v, -1) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1) + 1e-12)
        out[name] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return out


def _colour(person_id: int) -> tuple[int, int, int]:
    hue = (person_id * 47) % 180  # well-spread hues for consecutive ids
    hsv = np.uint8([[[hue, 220, 255]]])
    return tuple(int(c) for c in cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0])


def _draw_landmarks(img: np.ndarray, lm: np.ndarray, conf: np.ndarray, thick: int) -> None:
    """The landmark model's skeleton: white bones (light blue on the right side), joints shaded
    by confidence (red = unsure)."""
    pts = np.round(lm * 16).astype(np.int32)
    for a, b in LANDMARK_BONES:
        if min(conf[a], conf[b]) >= 0.3:
            right = a in _RIGHT_LANDMARKS and b in _RIGHT_LANDMARKS
            colour = _LANDMARK_RIGHT_COLOUR if right else (255, 255, 255)
            cv2.line(img, tuple(pts[a]), tuple(pts[b]), colour, 1, cv2.LINE_AA, shift=4)
    for p, c in zip(pts, conf, strict=True):
        shade = int(round(255 * float(np.clip(c, 0, 1))))
        cv2.circle(img, tuple(p), thick * 16, (shade, shade, 255), -1, cv2.LINE_AA, shift=4)


def draw_people(frame_bgr: np.ndarray, rows: pa.Table) -> np.ndarray:
    """Draw each row's box and id, the network's skeleton (joints2d, the id's colour; its right
    joints dark, the others white) and, where the row has them, the landmark model's 33
    landmarks (white bones, light blue on the right side; joints from red = unsure to white =
    sure), on a copy of the frame."""
    img = frame_bgr.copy()
    if rows.num_rows == 0:
        return img
    j2 = column_array(rows, "joints2d")
    boxes = column_array(rows, "bbox")
    ids = rows.column("person_id").to_pylist()
    has_lm = "landmarks2d" in rows.column_names
    lms = column_array(rows, "landmarks2d") if has_lm else None
    confs = column_array(rows, "landmarks_conf") if has_lm else None
    thick = max(1, round(max(img.shape[:2]) / 500))
    for k, (pid, joints, box) in enumerate(zip(ids, j2, boxes, strict=True)):
        if lms is not None and np.isfinite(lms[k]).all():
            _draw_landmarks(img, lms[k], confs[k], thick)
        col = _colour(pid)
        x0, y0, x1, y1 = box
        cv2.rectangle(img, (int(x0), int(y0)), (int(x1) - 1, int(y1) - 1), col, thick)
        cv2.putText(
            img,
            str(pid),
            (int(x0), max(int(y0) - 4 * thick, 10)),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5 * thick,
            col,
            thick,
            cv2.LINE_AA,
        )
        if not np.isfinite(joints).all():
            continue
        pts = np.round(joints * 16).astype(np.int32)  # 4 fractional bits: sub-pixel lines
        for child, parent in enumerate(SMPL_PARENTS):
            if parent >= 0:
                cv2.line(
                    img, tuple(pts[parent]), tuple(pts[child]), col, thick, cv2.LINE_AA, shift=4
                )
        for j, p in enumerate(pts):
            dot = (40, 40, 40) if j in _RIGHT_JOINTS else (255, 255, 255)
            cv2.circle(img, tuple(p), 2 * thick * 16, dot, -1, cv2.LINE_AA, shift=4)
    return img


def draw_key(img: np.ndarray, with_landmarks: bool = True) -> np.ndarray:
    """A two-line key in the frame's bottom-left corner, in place: which skeleton is the
    network's body and which the landmark model's (the overlay carries no other legend)."""
    scale = max(0.4, max(img.shape[:2]) / 1600)
    thick = max(1, round(scale * 2))
    lines = [("id colour: network body (joints2d), right joints dark", (80, 200, 255))]
    if with_landmarks:
        lines.append(("white / blue: landmark model left / right (red = unsure)", (255, 255, 255)))
    step = int(28 * scale) + 4
    y = img.shape[0] - 10 - step * (len(lines) - 1)
    for text, colour in lines:
        for c, w in (((0, 0, 0), thick + 2), (colour, thick)):
            cv2.putText(img, text, (10, y), cv2.FONT_HERSHEY_SIMPLEX, scale, c, w, cv2.LINE_AA)
        y += step
    return img


OVERLAY_MAX_SIDE = 4096  # MPEG-4 part 2 takes at most 8191 px a side; 4K is plenty to look at
OVERLAY_MIN_SIDE = 16


def overlay_size(width: int, height: int) -> tuple[int, int]:
    """(width, height) of the overlay video of a `width` x `height` one: scaled down to
    `OVERLAY_MAX_SIDE` on its longer side (an 8400 px panorama failed the codec after the whole
    tracking, and the tracks were never published), sides even and at least `OVERLAY_MIN_SIDE`
    (a 1x1 video failed the same way)."""
    scale = min(1.0, OVERLAY_MAX_SIDE / max(width, height))
    return tuple(  # type: ignore[return-value]
        max(OVERLAY_MIN_SIDE, 2 * round(side * scale / 2)) for side in (width, height)
    )


def write_overlay(
    video_path: str | Path, tracks_path: str | Path, out_path: str | Path, fourcc: str = "mp4v"
) -> Path:
    """The processed frames of `video_path` with the tracks drawn on, as a video at the processed
    rate (fps / stride), at `overlay_size`. Written to a temporary name and renamed."""
    meta = read_metadata(tracks_path)
    table = read_tracks(tracks_path)
    v = meta["video"]
    stride = int(v["stride"])
    frames_col = table.column("frame").to_numpy()
    has_landmarks = "landmarks2d" in table.column_names
    out_path = Path(out_path)
    size = overlay_size(int(v["width"]), int(v["height"]))
    with atomic_path(out_path) as tmp:
        writer = cv2.VideoWriter(
            str(tmp), cv2.VideoWriter_fourcc(*fourcc), float(v["fps"]) / stride, size
        )
        if not writer.isOpened():
            raise RuntimeError(f"{out_path}: cannot write video with codec '{fourcc}'")
        try:
            end = v["end_frame"]
            for f in iter_frames(
                video_path,
                stride=stride,
                start_s=v["first_frame"] / v["fps"],
                end_s=None if end is None else end / v["fps"],
                fps=float(v["fps"]),  # the rate the frames were tracked at (the scene's, if given)
            ):
                rows = table.filter(pa.array(frames_col == f.index))
                drawn = draw_key(draw_people(f.image, rows), has_landmarks)
                if drawn.shape[1::-1] != size:
                    drawn = cv2.resize(drawn, size, interpolation=cv2.INTER_AREA)
                writer.write(drawn)
        finally:
            writer.release()
    return out_path


def contact_sheet(
    video_path: str | Path,
    tracks_path: str | Path,
    frames: list[int],
    height: int = 560,
    label: str | None = None,
    margin: float = 60.0,
) -> np.ndarray:
    """One column of overlay frames (`draw_people`), each cut to the region the tracks ever
    cover (plus `margin` px) and resized to `height`: for looking at a run, and for docs."""
    table = read_tracks(tracks_path)
    fr = table.column("frame").to_numpy()
    boxes = column_array(table, "bbox")
    has_landmarks = "landmarks2d" in table.column_names
    tiles = []
    for f, img in read_frames(video_path, frames):
        h, w = img.shape[:2]
        if len(boxes):
            x0, y0 = np.maximum(boxes[:, :2].min(0) - margin, 0).astype(int)
            x1, y1 = np.minimum(boxes[:, 2:].max(0) + margin, [w, h]).astype(int)
        else:
            x0, y0, x1, y1 = 0, 0, w, h
        im = draw_people(img, table.filter(pa.array(fr == f)))[y0:y1, x0:x1]
        im = cv2.resize(
            im, (round(im.shape[1] * height / im.shape[0]), height), interpolation=cv2.INTER_AREA
        )
        text = f"{label or Path(video_path).stem}, frame {f}"
        for colour, weight in (((0, 0, 0), 4), ((255, 255, 255), 1)):
            cv2.putText(
                im, text, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, colour, weight, cv2.LINE_AA
            )
        draw_key(im, has_landmarks)
        tiles.append(cv2.copyMakeBorder(im, 2, 2, 2, 2, cv2.BORDER_CONSTANT))
    width = max(t.shape[1] for t in tiles)
    return np.concatenate(
        [cv2.copyMakeBorder(t, 0, 0, 0, width - t.shape[1], cv2.BORDER_CONSTANT) for t in tiles]
    )


def plot_joint_angles(tracks_path: str | Path, out_png: str | Path, min_rows: int = 10) -> Path:
    """A PNG with knee, hip and elbow angles over time, one panel per joint pair, a line per person
    (people with fewer than `min_rows` rows are left out)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = read_tracks(tracks_path)
    meta = read_metadata(tracks_path)
    angles = joint_angles(column_array(table, "joints3d").astype(np.float64))
    t = table.column("time_s").to_numpy()
    pid = table.column("person_id").to_numpy()
    people = [p for p in np.unique(pid) if (pid == p).sum() >= min_rows]
    fig, axes = plt.subplots(
        3, 2, figsize=(12, 8), sharex=True, sharey=True, constrained_layout=True
    )
    for ax, name in zip(
        axes.ravel(),
        ["left_knee", "right_knee", "left_hip", "right_hip", "left_elbow", "right_elbow"],
        strict=True,
    ):
        for p in people:
            m = pid == p
            ax.plot(
                t[m],
                angles[name][m],
                ".-",
                ms=2,
                lw=1,
                label=f"person {p}",
                color=np.array(_colour(int(p))[::-1]) / 255,
            )
        ax.set_title(name.replace("_", " "))
        ax.set_ylabel("angle (deg, 180 = straight)")
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    if people:
        axes[0, 0].legend(fontsize=8)
    fig.suptitle(
        f"{meta['video']['name']}: joint angles ({meta['model']['name']} "
        f"{meta['model']['version']}, joints3d in the {meta['axes']['joints3d']} frame)"
    )
    out_png = Path(out_png)
    try:
        atomic_write(out_png, lambda tmp: fig.savefig(tmp, dpi=100))
    finally:
        plt.close(fig)
    return out_png

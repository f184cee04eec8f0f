"""Turn a group's tracked predictions into tidy Arrow rows (one per frame and person)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa
from scipy.spatial.transform import Rotation

from gst.data.camera_view import TrackingView
from gst.track.detection import N_LANDMARKS
from gst.track.predictor import NUM_JOINTS, PoseBatch


def rotvec(R: np.ndarray) -> np.ndarray:
    shape = R.shape[:-2]
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(*shape, 3)


@dataclass
class RowSet:
    """Rows ready to write, one per (frame, person), in any order (`rows_table` sorts them)."""

    frame: np.ndarray  # (n,) int64
    time_s: np.ndarray  # (n,) float64
    person_id: np.ndarray  # (n,) int64
    boxes: np.ndarray  # (n, 4)
    scores: np.ndarray  # (n,)
    landmarks: np.ndarray  # (n, 33, 3) float32, NaN where the detector gave none
    poses: PoseBatch  # n bodies
    source: np.ndarray  # (n,) index of the row's detection in its group's predictions, or -1

    def __len__(self) -> int:
        return len(self.frame)

    @classmethod
    def from_rows(cls, rows: list[dict], num_betas: int) -> RowSet:
        n = len(rows)

        def stack(key: str, shape: tuple, dtype=np.float64) -> np.ndarray:
            if not n:
                return np.zeros((0, *shape), dtype)
            return np.stack([np.asarray(r[key], dtype) for r in rows]).reshape(n, *shape)

        poses = PoseBatch(
            stack("rotmats", (NUM_JOINTS, 3, 3)),
            stack("betas", (num_betas,)),
            stack("transl_cam", (3,)),
            stack("joints_cam", (NUM_JOINTS, 3)),
            {},
        )
        return cls(
            np.array([r["frame"] for r in rows], np.int64),
            np.array([r["time_s"] for r in rows], np.float64),
            np.array([r["person_id"] for r in rows], np.int64),
            stack("box", (4,)),
            np.array([r["score"] for r in rows], np.float64),
            stack("landmarks", (N_LANDMARKS, 3), np.float32),
            poses,
            np.array([r["source"] for r in rows], np.int64),
        )


def rows_table(view: TrackingView, rows: RowSet, schema: pa.Schema) -> pa.Table:
    """The rows as an Arrow table, sorted by frame then person_id."""
    order = np.lexsort((rows.person_id, rows.frame))
    p = rows.poses.take(order)
    n = len(order)
    go_cam = rotvec(p.rotmats[:, 0])
    body_pose = rotvec(p.rotmats[:, 1:])
    joints_cam = p.joints_cam
    if view.calibrated:
        joints3d = view.to_world(joints_cam)
        go = rotvec(view.rotation_to_world(p.rotmats[:, 0]))
        # SMPL rotates about the root joint J0: choose transl_world so that the body model with
        # (global_orient world, transl_world) reproduces the world joints.
        rest_root = joints_cam[:, 0] - p.transl_cam
        transl_world = joints3d[:, 0] - rest_root
    else:
        joints3d, go, transl_world = joints_cam, go_cam, None
    joints2d = view.project(joints_cam)
    landmarks = rows.landmarks[order]
    # a landmark the detector could not place is (0, 0) at confidence 0, as in the crop store;
    # the row's landmarks are null only where it placed none (one NaN blanked all 33)
    placed = np.isfinite(landmarks).all(axis=2)
    has_lm = placed.any(axis=1)
    landmarks = np.where(placed[..., None], landmarks, 0.0)

    def fixed(a: np.ndarray, name: str, valid: np.ndarray | None = None) -> pa.Array:
        width = schema.field(name).type.list_size
        flat = np.ascontiguousarray(a, dtype=np.float32).reshape(n, width)
        arr = pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), width)
        if valid is None or valid.all():
            return arr
        return pa.FixedSizeListArray.from_arrays(
            pa.array(flat.reshape(-1)), width, mask=pa.array(~valid)
        )

    cols = {
        "frame": pa.array(rows.frame[order]),
        "time_s": pa.array(rows.time_s[order], pa.float64()),
        "person_id": pa.array(rows.person_id[order]),
        "bbox": fixed(rows.boxes[order], "bbox"),
        "score": pa.array(rows.scores[order].astype(np.float32)),
        "global_orient": fixed(go, "global_orient"),
        "global_orient_cam": fixed(go_cam, "global_orient_cam"),
        "body_pose": fixed(body_pose, "body_pose"),
        "betas": fixed(p.betas, "betas"),
        "transl_cam": fixed(p.transl_cam, "transl_cam"),
        "transl_world": (
            fixed(transl_world, "transl_world")
            if transl_world is not None
            else pa.nulls(n, schema.field("transl_world").type)
        ),
        "joints3d": fixed(joints3d, "joints3d"),
        "joints2d": fixed(joints2d, "joints2d"),
        "landmarks2d": fixed(np.nan_to_num(landmarks[..., :2]), "landmarks2d", has_lm),
        "landmarks_conf": fixed(np.nan_to_num(landmarks[..., 2]), "landmarks_conf", has_lm),
    }
    return pa.Table.from_arrays([cols[f.name].cast(f.type) for f in schema], schema=schema)

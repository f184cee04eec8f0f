"""Turn a group's tracked predictions into tidy Arrow rows (one per frame and person)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
from scipy.spatial.transform import Rotation

from gst.data.camera_view import TrackingView
from gst.track.frames import PendingFrame
from gst.track.predictor import PoseBatch


def rotvec(R: np.ndarray) -> np.ndarray:
    shape = R.shape[:-2]
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(*shape, 3)


def rows_table(
    view: TrackingView,
    group: list[PendingFrame],
    ids: list[list[int]],
    poses: PoseBatch,
    keep: np.ndarray,
    schema: pa.Schema,
) -> pa.Table:
    """The group's rows, sorted by frame then person_id; `keep` marks detections that got an id."""
    frame_of = (
        np.concatenate([[f.index] * len(f.scores) for f in group]).astype(np.int64)
        if group
        else np.zeros(0, np.int64)
    )
    time_of = np.concatenate([[f.time_s] * len(f.scores) for f in group]) if group else np.zeros(0)
    boxes = np.concatenate([f.boxes for f in group]) if group else np.zeros((0, 4))
    scores = np.concatenate([f.scores for f in group]) if group else np.zeros(0)
    pid = (
        np.concatenate([np.asarray(i, dtype=np.int64) for i in ids])
        if ids
        else np.zeros(0, np.int64)
    )
    sel = np.flatnonzero(keep)
    sel = sel[np.lexsort((pid[sel], frame_of[sel]))]
    p = poses.take(sel)
    n = len(sel)
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

    def fixed(a: np.ndarray, name: str) -> pa.FixedSizeListArray:
        width = schema.field(name).type.list_size
        flat = np.ascontiguousarray(a, dtype=np.float32).reshape(n, width)
        return pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), width)

    cols = {
        "frame": pa.array(frame_of[sel]),
        "time_s": pa.array(time_of[sel], pa.float64()),
        "person_id": pa.array(pid[sel]),
        "bbox": fixed(boxes[sel], "bbox"),
        "score": pa.array(scores[sel].astype(np.float32)),
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
    }
    return pa.Table.from_arrays([cols[f.name].cast(f.type) for f in schema], schema=schema)

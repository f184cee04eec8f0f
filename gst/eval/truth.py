"""Exact truth of a synthetic scene (docs/formats/synth_scene.md), mapped onto extracted crops.

`read_scene_truth` loads one row per (frame, person) from `truth/people.parquet`: body-model
parameters, world joints and the motion label. `attach_scene_truth` matches each extracted crop
to the person it shows (`gst.train.synthetic_crops.match_truth_views`) and gives the crop set the
truth keys every consumer needs: world and camera joints, 2D joints in crop pixels, visibility,
rotations (global orientation in the crop's camera) and betas, for evaluation and for the 2D/3D
fine-tuning baselines. Truth meshes are posed on demand (`SceneTruth.vertices`): the scene writes
parameters, and `body(betas, body_pose, global_orient, transl)` reproduces its world vertices.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from gst.train.synthetic_crops import match_truth_views
from gst.train.views import CropSet

__all__ = ["SceneTruth", "has_scene_truth", "read_scene_truth", "attach_scene_truth", "select_rows"]


@dataclass
class SceneTruth:
    """One row per (frame, person) of a synthetic scene. Arrays are float32 unless noted."""

    frame: np.ndarray  # (P,) int
    person_id: np.ndarray  # (P,) int
    motion: np.ndarray  # (P,) str, the motion clip playing at that frame
    betas: np.ndarray  # (P, nb)
    global_orient: np.ndarray  # (P, 3) axis-angle, body -> world
    body_pose: np.ndarray  # (P, 23, 3) axis-angle
    transl: np.ndarray  # (P, 3) metres
    joints_world: np.ndarray  # (P, 24, 3) metres
    joint_names: tuple[str, ...]
    body_model: str  # name of the body model the scene was posed with

    def __len__(self) -> int:
        return len(self.frame)

    @torch.no_grad()
    def vertices(self, body, rows: np.ndarray | None = None, batch: int = 32) -> torch.Tensor:
        """World vertices (P', V, 3) of `rows` (default all), posed with `body` (a gst BodyModel
        of the same topology as the scene's)."""
        rows = np.arange(len(self)) if rows is None else np.asarray(rows)
        parts = []
        for s in range(0, len(rows), batch):
            r = rows[s : s + batch]
            out = body(
                torch.from_numpy(self.betas[r]),
                torch.from_numpy(self.body_pose[r]),
                torch.from_numpy(self.global_orient[r]),
                torch.from_numpy(self.transl[r]),
            )
            parts.append(out.vertices.float())
        if not parts:
            return torch.zeros(0, body.num_vertices, 3)
        return torch.cat(parts)


def has_scene_truth(scene_dir: str | Path) -> bool:
    """Whether `scene_dir` (a synthetic scene folder) carries per-person truth."""
    truth = Path(scene_dir) / "truth"
    return (truth / "people.parquet").is_file() and (truth / "views.parquet").is_file()


def _fixed(table, name: str, width: int, path: Path) -> np.ndarray:
    if name not in table.column_names:
        raise ValueError(f"{path}: column '{name}' is missing (columns: {table.column_names})")
    flat = table.column(name).combine_chunks().flatten().to_numpy(zero_copy_only=False)
    if flat.size != table.num_rows * width:
        raise ValueError(
            f"{path}: column '{name}' has {flat.size // max(table.num_rows, 1)} values per row, "
            f"expected {width}"
        )
    return np.array(flat, dtype=np.float32).reshape(table.num_rows, width)


def read_scene_truth(scene_dir: str | Path) -> SceneTruth:
    """Load `truth/people.parquet` of a synthetic scene; raises FileNotFoundError when absent."""
    path = Path(scene_dir) / "truth" / "people.parquet"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no truth (only synthetic scenes carry it)")
    table = pq.read_table(path)
    meta = table.schema.metadata or {}
    joint_names = (
        tuple(json.loads(meta[b"joint_names"]))
        if b"joint_names" in meta
        else tuple(f"joint_{i}" for i in range(24))
    )
    body_model = json.loads(meta[b"body_model"]).get("name", "") if b"body_model" in meta else ""
    nb = table.schema.field("betas").type.list_size
    motion = (
        np.asarray(table.column("motion").to_pylist(), dtype=object)
        if "motion" in table.column_names
        else np.full(table.num_rows, "unknown", dtype=object)
    )
    return SceneTruth(
        frame=table.column("frame").to_numpy().astype(np.int64),
        person_id=table.column("person_id").to_numpy().astype(np.int64),
        motion=motion,
        betas=_fixed(table, "betas", nb, path),
        global_orient=_fixed(table, "global_orient", 3, path),
        body_pose=_fixed(table, "body_pose", 69, path).reshape(-1, 23, 3),
        transl=_fixed(table, "transl", 3, path),
        joints_world=_fixed(table, "joints3d", 72, path).reshape(-1, 24, 3),
        joint_names=joint_names,
        body_model=body_model,
    )


def attach_scene_truth(
    crops: CropSet, boxes: np.ndarray, scene_dir: str | Path, min_iou: float = 0.3
) -> SceneTruth:
    """Match every crop to the truth person it shows and add truth keys to `crops.truth`:
    has_truth (N,) bool, truth_row (N,) index into the returned SceneTruth (-1: unmatched),
    joints_world / joints_cam (N,24,3), joints2d (N,24,2) crop px, visible (N,24),
    rotmats_cam (N,24,3,3) (index 0: global orientation in the crop's camera), betas (N,nb).
    Unmatched crops carry zeros; always filter with has_truth."""
    scene_dir = Path(scene_dir)
    truth = read_scene_truth(scene_dir)
    views = pq.read_table(scene_dir / "truth" / "views.parquet")
    view_rows = match_truth_views(crops, boxes, scene_dir, min_iou)
    index = {
        (int(f), int(p)): k
        for k, (f, p) in enumerate(zip(truth.frame, truth.person_id, strict=True))
    }
    v_frame, v_pid = views.column("frame").to_numpy(), views.column("person_id").to_numpy()
    v_visible = _fixed(views, "visible", 24, scene_dir / "truth" / "views.parquet") > 0.5
    n = len(crops)
    row = np.full(n, -1, np.int64)
    visible = np.zeros((n, 24), np.float32)
    for i, r in enumerate(view_rows):
        if r >= 0:
            row[i] = index[(int(v_frame[r]), int(v_pid[r]))]
            visible[i] = v_visible[r]
    has = row >= 0
    safe = np.where(has, row, 0)
    jw = torch.from_numpy(truth.joints_world[safe]) * torch.from_numpy(has)[:, None, None]
    jc = jw @ crops.R.transpose(1, 2) + crops.t[:, None]
    z = jc[..., 2:].clamp_min(1e-6)
    uv = (jc / z) @ crops.K.transpose(1, 2)
    rot = axis_angle_to_rotation_matrix(
        torch.from_numpy(
            np.concatenate([truth.global_orient[safe][:, None], truth.body_pose[safe]], 1)
        ).reshape(-1, 3)
    ).reshape(n, 24, 3, 3)
    rot[:, 0] = crops.R @ rot[:, 0]  # body -> world, then world -> this crop's camera
    crops.truth.update(
        has_truth=torch.from_numpy(has),
        truth_row=torch.from_numpy(row),
        joints_world=jw,
        joints_cam=jc,
        joints2d=uv[..., :2],
        visible=torch.from_numpy(visible),
        rotmats_cam=rot,
        betas=torch.from_numpy(truth.betas[safe]),
    )
    return truth


def select_rows(crops: CropSet, rows: torch.Tensor | np.ndarray) -> CropSet:
    """A CropSet of the given rows only (truth included), e.g. a train split."""
    r = torch.as_tensor(np.asarray(rows), dtype=torch.long)
    return CropSet(
        images=crops.images[r],
        masks=crops.masks[r],
        K=crops.K[r],
        R=crops.R[r],
        t=crops.t[r],
        camera=crops.camera[r],
        frame=crops.frame[r],
        person=crops.person[r],
        camera_names=list(crops.camera_names),
        truth={k: v[r] for k, v in crops.truth.items()},
        occluders=None if crops.occluders is None else crops.occluders[r],
        anchors=None if crops.anchors is None else crops.anchors[r],
    )

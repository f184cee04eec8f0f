"""The synthetic scene's truth format, written and read here (docs/formats/synth_scene.md).

Writers build the tables `render_scene` saves: body parameters and 3D joints per person
(`truth/people.parquet`), 2D views per camera (`truth/views.parquet`) and the board's poses.
Readers (`read_scene_truth`, `read_truth_views`, `truth_mask_file`) are the one
place every consumer (evaluation, pretraining crops, track scoring) loads them from.

`visible[j]` is True when joint j projects into the image, the pixel there belongs to the same
person, and the surface seen there is at most `OCCLUSION_TOLERANCE` metres in front of the joint
(joints sit inside the body; anything nearer than that is an occluder).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from calibration import Camera
from synth.animate import PersonTrack
from synth.board import BoardPose, ChArUcoSpec, visible_corners
from synth.io import write_parquet
from synth.projection import project_in_view
from synth.skeleton import JOINT_NAMES, NUM_JOINTS

OCCLUSION_TOLERANCE = 0.25


def _fixed(
    values: np.ndarray, width: int, dtype: pa.DataType | None = None
) -> pa.FixedSizeListArray:
    flat = np.ascontiguousarray(values).reshape(-1)
    return pa.FixedSizeListArray.from_arrays(pa.array(flat, type=dtype or pa.float32()), width)


def people_table(tracks: list[PersonTrack], metadata: dict) -> pa.Table:
    """One row per frame and person: betas, global_orient, body_pose (23 x 3 axis-angle,
    flattened), transl, joints3d (24 x 3 world metres, flattened) and the motion name."""
    rows = []
    for tr in tracks:
        T = tr.n_frames
        rows.append(
            dict(
                frame=np.arange(T, dtype=np.int32),
                person_id=np.full(T, tr.person_id, np.int16),
                motion=list(tr.labels),
                betas=np.tile(tr.betas, (T, 1)),
                global_orient=tr.global_orient,
                body_pose=tr.body_pose.reshape(T, -1),
                transl=tr.transl,
                joints3d=tr.joints.reshape(T, -1),
            )
        )
    if not rows:
        raise ValueError("no people to write")
    nb = rows[0]["betas"].shape[1]
    cat = {
        k: np.concatenate([r[k] for r in rows]) if k != "motion" else sum((r[k] for r in rows), [])
        for k in rows[0]
    }
    order = np.lexsort((cat["person_id"], cat["frame"]))
    table = pa.table(
        {
            "frame": pa.array(cat["frame"][order]),
            "person_id": pa.array(cat["person_id"][order]),
            "motion": pa.array([cat["motion"][i] for i in order], type=pa.string()),
            "betas": _fixed(cat["betas"][order].astype(np.float32), nb),
            "global_orient": _fixed(cat["global_orient"][order].astype(np.float32), 3),
            "body_pose": _fixed(cat["body_pose"][order].astype(np.float32), 69),
            "transl": _fixed(cat["transl"][order].astype(np.float32), 3),
            "joints3d": _fixed(cat["joints3d"][order].astype(np.float32), 3 * NUM_JOINTS),
        }
    )
    return table.replace_schema_metadata({k: json.dumps(v) for k, v in metadata.items()})


# Columns of views.parquet, in file order.
VIEW_COLUMNS = (
    "frame", "person_id", "camera", "joints2d", "visible", "x0", "y0", "x1", "y1", "mask_area",
    "full_x0", "full_y0", "full_x1", "full_y1",
)  # fmt: skip


class ViewRows:
    """Accumulates per (frame, person, camera) 2D truth rows."""

    def __init__(self):
        self._cols: dict[str, list] = {k: [] for k in VIEW_COLUMNS}

    def add(
        self,
        camera: Camera,
        radius: float,
        frame: int,
        tracks: list[PersonTrack],
        mask: np.ndarray,
        depth: np.ndarray,
    ) -> None:
        """Rows for one rendered view (mask and camera-z depth of that view)."""
        for tr in tracks:
            pid = tr.person_id
            uv, inside = project_in_view(camera, tr.joints[frame], radius)
            zc = camera.to_camera(tr.joints[frame])[:, 2]
            vis = np.zeros(NUM_JOINTS, bool)
            if inside.any():
                px = np.clip(
                    np.rint(uv[inside]).astype(int), 0, [camera.width - 1, camera.height - 1]
                )
                own = mask[px[:, 1], px[:, 0]] == pid
                near = depth[px[:, 1], px[:, 0]] > zc[inside] - OCCLUSION_TOLERANCE
                vis[inside] = own & near
            m = mask == pid
            area = int(m.sum())
            if area:
                rows = np.flatnonzero(m.any(1))
                cols = np.flatnonzero(m.any(0))
                box = (
                    float(cols[0]) - 0.5,
                    float(rows[0]) - 0.5,
                    float(cols[-1]) + 0.5,
                    float(rows[-1]) + 0.5,
                )
            else:
                box = (np.nan,) * 4
            vuv, vin = project_in_view(camera, tr.vertices[frame], radius)
            ok = ~np.isnan(vuv[:, 0])
            full = (
                tuple(float(x) for x in (*vuv[ok].min(0), *vuv[ok].max(0)))
                if ok.any()
                else (np.nan,) * 4
            )
            c = self._cols
            c["frame"].append(frame)
            c["person_id"].append(pid)
            c["camera"].append(camera.name)
            c["joints2d"].append(uv.astype(np.float32).ravel())
            c["visible"].append(vis)
            for k, v in zip(("x0", "y0", "x1", "y1"), box, strict=True):
                c[k].append(v)
            c["mask_area"].append(area)
            for k, v in zip(("full_x0", "full_y0", "full_x1", "full_y1"), full, strict=True):
                c[k].append(v)

    def extend(self, other: ViewRows) -> None:
        """Append another accumulator's rows (e.g. a worker's); `table` sorts, so order is free."""
        for k, values in other._cols.items():
            self._cols[k].extend(values)

    def table(self, metadata: dict) -> pa.Table:
        c = self._cols
        n = len(c["frame"])
        order = sorted(range(n), key=lambda i: (c["frame"][i], c["person_id"][i], c["camera"][i]))
        arr = {
            "frame": pa.array(np.array(c["frame"], np.int32)[order]),
            "person_id": pa.array(np.array(c["person_id"], np.int16)[order]),
            "camera": pa.array([c["camera"][i] for i in order], type=pa.string()),
            "joints2d": _fixed(
                np.stack(c["joints2d"])[order] if n else np.zeros((0, 48), np.float32),
                2 * NUM_JOINTS,
            ),
            "visible": _fixed(
                np.stack(c["visible"])[order] if n else np.zeros((0, 24), bool),
                NUM_JOINTS,
                pa.bool_(),
            ),
        }
        for k in ("x0", "y0", "x1", "y1", "full_x0", "full_y0", "full_x1", "full_y1"):
            arr[k] = pa.array(np.array(c[k], np.float32)[order])
        arr["mask_area"] = pa.array(np.array(c["mask_area"], np.int32)[order])
        return pa.table({k: arr[k] for k in VIEW_COLUMNS}).replace_schema_metadata(
            {k: json.dumps(v) for k, v in metadata.items()}
        )


def board_tables(
    spec: ChArUcoSpec,
    poses: list[BoardPose],
    cameras: list[Camera],
    radii: dict[str, float],
    metadata: dict,
    room=None,
) -> tuple[pa.Table, pa.Table]:
    """Board poses per frame and the corners each camera sees (ids and distorted pixels; with
    `room`, the stage, not those the room hides: see `visible_corners`)."""
    poses_t = pa.table(
        {
            "frame": pa.array(np.arange(len(poses), dtype=np.int32)),
            "R": _fixed(np.stack([p.R for p in poses]).astype(np.float64), 9, pa.float64()),
            "t": _fixed(np.stack([p.t for p in poses]).astype(np.float64), 3, pa.float64()),
        }
    ).replace_schema_metadata({k: json.dumps(v) for k, v in metadata.items()})
    frames, cams, ids, uvs = [], [], [], []
    for f, pose in enumerate(poses):
        for cam in cameras:
            i, uv = visible_corners(spec, pose, cam, radii[cam.name], room)
            frames.append(f)
            cams.append(cam.name)
            ids.append(i.astype(np.int32))
            uvs.append(uv.astype(np.float32).ravel())
    views_t = pa.table(
        {
            "frame": pa.array(np.array(frames, np.int32)),
            "camera": pa.array(cams, type=pa.string()),
            "corner_ids": pa.array([x.tolist() for x in ids], type=pa.list_(pa.int32())),
            "corners2d": pa.array([x.tolist() for x in uvs], type=pa.list_(pa.float32())),
        }
    )
    return poses_t, views_t


def joint_names() -> list[str]:
    return list(JOINT_NAMES)


# -- readers ----------------------------------------------------------------------------------

PEOPLE_FILE = "truth/people.parquet"
VIEWS_FILE = "truth/views.parquet"
BOARD_POSES_FILE = "truth/board_poses.parquet"
BOARD_VIEWS_FILE = "truth/board_views.parquet"


def write_truth_tables(out: Path, tracks: list[PersonTrack], views: ViewRows, meta: dict) -> None:
    """`truth/people.parquet` and `truth/views.parquet` of a scene folder, atomically."""
    write_parquet(out / PEOPLE_FILE, people_table(tracks, meta))
    write_parquet(
        out / VIEWS_FILE,
        views.table(
            {
                **meta,
                "occlusion_tolerance_m": OCCLUSION_TOLERANCE,
                "pixel_convention": "OpenCV, pixel centres at integers",
            }
        ),
    )


def write_board_truth(out: Path, poses: pa.Table, views: pa.Table) -> None:
    """`truth/board_poses.parquet` and `truth/board_views.parquet` (from `board_tables`)."""
    write_parquet(out / BOARD_POSES_FILE, poses)
    write_parquet(out / BOARD_VIEWS_FILE, views)


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

    def row_index(self) -> dict[tuple[int, int], int]:
        """(frame, person id) -> row."""
        return {
            (int(f), int(p)): k
            for k, (f, p) in enumerate(zip(self.frame, self.person_id, strict=True))
        }

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


@dataclass(frozen=True)
class TruthViews:
    """Rows of `truth/views.parquet`: one per (frame, person, camera). Boxes: `box` is the
    person's mask box with edges at pixel-centre coordinates (`min column - 0.5`), NaN when the
    mask is empty; `full_box` bounds the projected mesh, occluded parts included (distorted
    image)."""

    frame: np.ndarray  # (M,) int64
    person_id: np.ndarray  # (M,) int64
    camera: np.ndarray  # (M,) str (object array)
    joints2d: np.ndarray  # (M, 24, 2) float32 distorted image pixels
    visible: np.ndarray  # (M, 24) bool
    box: np.ndarray  # (M, 4) float64 x0, y0, x1, y1
    full_box: np.ndarray  # (M, 4) float64
    mask_area: np.ndarray  # (M,) int64 pixels

    def __len__(self) -> int:
        return len(self.frame)

    def rows(self, keep: np.ndarray) -> TruthViews:
        return TruthViews(**{k: getattr(self, k)[keep] for k in self.__dataclass_fields__})


def has_scene_truth(scene_dir: str | Path) -> bool:
    """Whether `scene_dir` (a synthetic scene folder) carries per-person truth."""
    return (Path(scene_dir) / PEOPLE_FILE).is_file() and (Path(scene_dir) / VIEWS_FILE).is_file()


def _column(table: pa.Table, name: str, width: int, path: Path) -> np.ndarray:
    if name not in table.column_names:
        raise ValueError(f"{path}: column '{name}' is missing (columns: {table.column_names})")
    flat = table.column(name).combine_chunks().flatten().to_numpy(zero_copy_only=False)
    if flat.size != table.num_rows * width:
        raise ValueError(
            f"{path}: column '{name}' has {flat.size // max(table.num_rows, 1)} values per row, "
            f"expected {width}"
        )
    return np.asarray(flat).reshape(table.num_rows, width)


def _table(scene_dir: str | Path, rel: str, columns: tuple[str, ...]) -> tuple[pa.Table, Path]:
    """The truth table `rel` of a scene, which must hold `columns` (a missing one was a bare
    KeyError naming no file)."""
    path = Path(scene_dir) / rel
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no truth (only synthetic scenes carry it)")
    table = pq.read_table(path)
    missing = [c for c in columns if c not in table.column_names]
    if missing:
        raise ValueError(f"{path}: columns {missing} are missing (columns: {table.column_names})")
    return table, path


def read_scene_truth(scene_dir: str | Path) -> SceneTruth:
    """Load `truth/people.parquet` of a synthetic scene; raises FileNotFoundError when absent."""
    table, path = _table(
        scene_dir,
        PEOPLE_FILE,
        ("frame", "person_id", "betas", "global_orient", "body_pose", "transl", "joints3d"),
    )
    meta = table.schema.metadata or {}
    names = (
        tuple(json.loads(meta[b"joint_names"]))
        if b"joint_names" in meta
        else tuple(f"joint_{i}" for i in range(NUM_JOINTS))
    )
    body_model = json.loads(meta[b"body_model"]).get("name", "") if b"body_model" in meta else ""
    nb = table.schema.field("betas").type.list_size
    motion = (
        np.asarray(table.column("motion").to_pylist(), dtype=object)
        if "motion" in table.column_names
        else np.full(table.num_rows, "unknown", dtype=object)
    )

    def f32(name: str, width: int) -> np.ndarray:
        return _column(table, name, width, path).astype(np.float32)

    return SceneTruth(
        frame=table.column("frame").to_numpy().astype(np.int64),
        person_id=table.column("person_id").to_numpy().astype(np.int64),
        motion=motion,
        betas=f32("betas", nb),
        global_orient=f32("global_orient", 3),
        body_pose=f32("body_pose", 69).reshape(-1, 23, 3),
        transl=f32("transl", 3),
        joints_world=f32("joints3d", 3 * NUM_JOINTS).reshape(-1, NUM_JOINTS, 3),
        joint_names=names,
        body_model=body_model,
    )


def read_truth_views(scene_dir: str | Path, camera: str | None = None) -> TruthViews:
    """Load `truth/views.parquet` (all cameras, or one: KeyError naming the cameras if absent)."""
    table, path = _table(
        scene_dir,
        VIEWS_FILE,
        ("frame", "person_id", "camera", "joints2d", "visible", "x0", "y0", "x1", "y1")
        + ("full_x0", "full_y0", "full_x1", "full_y1", "mask_area"),
    )
    cameras = np.asarray(table.column("camera").to_pylist(), dtype=object)

    def f64(*names: str) -> np.ndarray:
        return np.stack([table.column(k).to_numpy().astype(np.float64) for k in names], 1)

    views = TruthViews(
        frame=table.column("frame").to_numpy().astype(np.int64),
        person_id=table.column("person_id").to_numpy().astype(np.int64),
        camera=cameras,
        joints2d=_column(table, "joints2d", 2 * NUM_JOINTS, path).reshape(-1, NUM_JOINTS, 2),
        visible=_column(table, "visible", NUM_JOINTS, path).astype(bool),
        box=f64("x0", "y0", "x1", "y1"),
        full_box=f64("full_x0", "full_y0", "full_x1", "full_y1"),
        mask_area=table.column("mask_area").to_numpy().astype(np.int64),
    )
    if camera is None:
        return views
    if camera not in set(cameras):
        raise KeyError(
            f"{path}: no camera '{camera}' in the truth views (cameras: {sorted(set(cameras))})"
        )
    return views.rows(cameras == camera)


def truth_mask_file(scene_dir: str | Path, camera: str) -> Path:
    """`truth/masks/<camera>.h5`: person-id masks (dataset `mask`, (T, H, W)) and depth."""
    return Path(scene_dir) / "truth" / "masks" / f"{camera}.h5"

"""The fused Parquet files: bodies (the tracks schema, world frame) and triangulated landmarks.

`fused/bodies.parquet` has every column and every metadata key of a tracks file
(gst.track.schema, docs/formats/tracks_parquet.md), one row per frame and person, with the
world-frame values filled and the single-camera ones null (`bbox`, `global_orient_cam`,
`transl_cam`, `joints2d`, `landmarks2d`, `landmarks_conf`), plus per-joint evidence columns
(docs/formats/fused_bodies.md).
`fused/landmarks.parquet` holds the robust triangulation of the 33 BlazePose landmarks
(docs/formats/fused_landmarks.md).
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from gst.atomic import atomic_write
from gst.body.markers import BLAZEPOSE_NAMES
from gst.body.skeleton import SMPL_JOINT_NAMES
from gst.fuse.fit import PersonFit
from gst.fuse.joint_map import JOINT_LANDMARKS, joint_landmark_indices
from gst.fuse.triangulate import PersonTriangulation
from gst.track.schema import file_metadata, tracks_schema

__all__ = [
    "JointEvidence",
    "joint_evidence",
    "write_bodies",
    "write_landmarks",
    "EXTRA_COLUMNS",
    "FusedBodies",
    "read_fused_bodies",
]

PARQUET_OPTIONS = {"compression": "zstd", "compression_level": 3, "version": "2.6"}

# extra columns of bodies.parquet: name -> (arrow type, unit, description)
SCORE_DESCRIPTION = (
    "share of the joints with landmarks that were triangulated in this frame (>= 2 views); the "
    "rest the fit filled"
)
EXTRA_COLUMNS: dict[str, tuple[pa.DataType, str, str]] = {
    "joint_views": (
        pa.list_(pa.uint8(), 24),
        "",
        "per joint, views of its least-seen landmark: the fewest cameras the triangulation used "
        "for any one of its landmarks",
    ),
    "joint_view_mask": (
        pa.list_(pa.int64(), 24),
        "",
        "per joint, bit c set when the triangulation used camera c (gst.fused.cameras order) for "
        "at least one of its landmarks",
    ),
    "joint_reprojection_px": (
        pa.list_(pa.float32(), 24),
        "px",
        "per joint, mean reprojection error of the fitted body's markers for its landmarks, "
        "full-image pixels, over the cameras that detected them; NaN: no landmark",
    ),
    "joint_gap_filled": (
        pa.list_(pa.bool_(), 24),
        "",
        "per joint, True when it has landmarks and one of them has fewer than 2 views in this "
        "frame (its position comes from the fit)",
    ),
    "observed": (pa.bool_(), "", "False for a frame inside a gap, filled by the fit alone"),
    "single_view": (
        pa.bool_(),
        "",
        "no landmark of the person was ever triangulated from two views (single-view terms)",
    ),
}


_TORSO = [
    SMPL_JOINT_NAMES.index(n) for n in ("left_hip", "right_hip", "left_shoulder", "right_shoulder")
]


@dataclass
class JointEvidence:
    views: np.ndarray  # (T, 24) uint8
    mask: np.ndarray  # (T, 24) int64 bit mask of cameras
    reprojection_px: np.ndarray  # (T, 24) float
    gap_filled: np.ndarray  # (T, 24) bool
    has_landmarks: np.ndarray  # (24,) bool

    def fitted_only(self) -> np.ndarray:
        """(T, 24) bool: joints whose place comes from the fit alone in a frame (the markers'
        residual 0): gap-filled joints, and the joints without landmarks (spine, neck, collars,
        which nothing triangulates) wherever one of the torso's hips and shoulders is gap-filled."""
        out = self.gap_filled.copy()
        out[:, ~self.has_landmarks] = self.gap_filled[:, _TORSO].any(1)[:, None]
        return out

    def camera_mask(self) -> np.ndarray:
        """(T, 24) int64: the cameras that measured each joint, for the C3D camera byte; the
        joints without landmarks take the torso's hips' and shoulders' cameras."""
        out = self.mask.copy()
        torso = np.bitwise_or.reduce(self.mask[:, _TORSO], axis=1)
        out[:, ~self.has_landmarks] = torso[:, None]
        return out


def joint_evidence(fit: PersonFit, tri: PersonTriangulation | None) -> JointEvidence:
    """Per-joint views, reprojection and gap flags of one person (tri aligned to fit.frames)."""
    T = len(fit.frames)
    C = fit.reprojection.shape[1]
    idx = joint_landmark_indices()
    used = np.zeros((T, 33, C), bool) if tri is None else tri.used
    views = np.zeros((T, 24), np.uint8)
    mask = np.zeros((T, 24), np.int64)
    reproj = np.full((T, 24), np.nan)
    bits = (1 << np.arange(C)).astype(np.int64)
    # Each landmark is triangulated from its own views: a head whose cameras each read the
    # nose and the near ear has every landmark from 2+ views while no camera used all three
    # (counting the cameras that used all of them flagged it gap-filled, residual 1 in the C3D)
    per_landmark = used.sum(2)  # (T, 33)
    for j, lms in enumerate(idx):
        if not lms:
            continue
        views[:, j] = per_landmark[:, lms].min(1)
        mask[:, j] = (used[:, lms].any(1) * bits).sum(1)
        with warnings.catch_warnings():  # a gap frame has no reading: NaN, not a warning
            warnings.simplefilter("ignore", RuntimeWarning)
            per_lm = np.nanmean(fit.reprojection[:, :, lms], axis=1)  # (T, len(lms))
            reproj[:, j] = np.nanmean(per_lm, axis=1)
    has = np.array([bool(x) for x in idx])
    gap = has[None] & (views < 2)
    return JointEvidence(views, mask, reproj, gap, has)


def write_bodies(
    path,
    fits: list[PersonFit],
    evidence: list[JointEvidence],
    *,
    fps: float,
    camera_names: list[str],
    model: dict,
    settings: dict,
    settings_sha256: str,
    stats: dict,
    world_up=(0.0, 0.0, 1.0),
) -> None:
    """Write `bodies.parquet`: rows sorted by frame, then person. `world_up`: `Rig.up`."""
    nb = fits[0].betas.shape[0] if fits else 10
    cols: dict[str, list] = {k: [] for k in ("frame", "person_id")}
    arrays: dict[str, list[np.ndarray]] = {
        k: []
        for k in ("global_orient", "body_pose", "betas", "transl_world", "joints3d")
        + tuple(EXTRA_COLUMNS)
        + ("score",)
    }
    for fit, ev in zip(fits, evidence, strict=True):
        T = len(fit.frames)
        cols["frame"].append(fit.frames)
        cols["person_id"].append(np.full(T, fit.person_id))
        arrays["global_orient"].append(fit.global_orient.reshape(T, 3))
        arrays["body_pose"].append(fit.body_pose.reshape(T, 69))
        arrays["betas"].append(np.repeat(fit.betas[None], T, 0))
        arrays["transl_world"].append(fit.transl)
        arrays["joints3d"].append(fit.joints.reshape(T, 72))
        arrays["joint_views"].append(ev.views)
        arrays["joint_view_mask"].append(ev.mask)
        arrays["joint_reprojection_px"].append(ev.reprojection_px)
        arrays["joint_gap_filled"].append(ev.gap_filled)
        arrays["observed"].append(fit.observed)
        arrays["single_view"].append(np.full(T, fit.single_view))
        # score: share of the joints with landmarks that were triangulated in this frame
        arrays["score"].append(1.0 - ev.gap_filled[:, ev.has_landmarks].mean(1))
    frame = np.concatenate(cols["frame"]) if fits else np.zeros(0, np.int64)
    person = np.concatenate(cols["person_id"]) if fits else np.zeros(0, np.int64)
    order = np.lexsort((person, frame))
    cat = {k: (np.concatenate(v)[order] if v else None) for k, v in arrays.items()}
    n = len(order)
    schema = tracks_schema(nb)
    extra_fields = [
        pa.field(k, t, metadata={"unit": u, "description": d})
        for k, (t, u, d) in EXTRA_COLUMNS.items()
    ]
    # the tracks format's `score` is a detection score; here it is the fit's own measure
    score = schema.field("score")
    score = score.with_metadata({**score.metadata, b"description": SCORE_DESCRIPTION.encode()})
    schema = pa.schema([score if f.name == "score" else f for f in schema] + extra_fields)

    def fixed(name: str, width: int, dtype=np.float32) -> pa.Array:
        if n == 0:
            return pa.array([], type=schema.field(name).type)
        flat = np.ascontiguousarray(cat[name].reshape(n, width).astype(dtype)).ravel()
        return pa.FixedSizeListArray.from_arrays(pa.array(flat), width)

    def nulls(name: str) -> pa.Array:
        return pa.nulls(n, type=schema.field(name).type)

    data = {
        "frame": pa.array(frame[order].astype(np.int64)),
        "time_s": pa.array(frame[order] / float(fps)),
        "person_id": pa.array(person[order].astype(np.int64)),
        "bbox": nulls("bbox"),
        "score": pa.array(cat["score"].astype(np.float32) if n else [], type=pa.float32()),
        "global_orient": fixed("global_orient", 3),
        "global_orient_cam": nulls("global_orient_cam"),
        "body_pose": fixed("body_pose", 69),
        "betas": fixed("betas", nb),
        "transl_cam": nulls("transl_cam"),
        "transl_world": fixed("transl_world", 3),
        "joints3d": fixed("joints3d", 72),
        "joints2d": nulls("joints2d"),
        "landmarks2d": nulls("landmarks2d"),  # tracks format 2; fused/landmarks.parquet has 3D
        "landmarks_conf": nulls("landmarks_conf"),
        "joint_views": fixed("joint_views", 24, np.uint8),
        "joint_view_mask": fixed("joint_view_mask", 24, np.int64),
        "joint_reprojection_px": fixed("joint_reprojection_px", 24),
        "joint_gap_filled": fixed("joint_gap_filled", 24, bool),
        "observed": pa.array(cat["observed"] if n else [], type=pa.bool_()),
        "single_view": pa.array(cat["single_view"] if n else [], type=pa.bool_()),
    }
    meta = file_metadata(
        fps=fps,
        model=model,
        calibration={"calibrated": True, "cameras": camera_names, "source": "calibration/rig.json"},
        axes={  # the tracks file's layout (gst.track.loop), and `world_up` as before
            "joints3d": "world",
            "world": {
                "description": "the rig's world (calibration/rig.json), metres",
                "up": [float(v) for v in world_up],
            },
            "world_up": [float(v) for v in world_up],
            "body": (
                "the body model's (gst.model.body_model) SMPL joint layout: global_orient "
                "rotates the body frame (x left, y up, z forward) into the world"
            ),
        },
        video={"name": "fused", "cameras": camera_names, "fps": fps},
        tracking=settings,
        smoothing=None,
        stats=stats,
        settings_sha256=settings_sha256,
        num_betas=nb,
    )
    # the file's own column table: score as here, and the fused columns (they were described in
    # `gst.fused` only)
    columns = json.loads(meta["gst.columns"])
    columns["score"]["description"] = SCORE_DESCRIPTION
    for k, (t, u, d) in EXTRA_COLUMNS.items():
        shape = [t.list_size] if pa.types.is_fixed_size_list(t) else []
        columns[k] = {"shape": shape, "unit": u, "frame": None, "description": d}
    meta["gst.columns"] = json.dumps(columns, sort_keys=True)
    units = json.loads(meta["gst.units"])
    units.update({k: u for k, (_, u, _) in EXTRA_COLUMNS.items() if u})
    meta["gst.units"] = json.dumps(units, sort_keys=True)
    meta["gst.fused"] = json.dumps(
        {
            "cameras": camera_names,
            "joint_landmarks": JOINT_LANDMARKS,
            "extra_columns": {
                k: {"unit": u, "description": d} for k, (_, u, d) in EXTRA_COLUMNS.items()
            },
            "null_columns": [
                "bbox",
                "global_orient_cam",
                "transl_cam",
                "joints2d",
                "landmarks2d",
                "landmarks_conf",
            ],
        },
        sort_keys=True,
    )
    table = pa.table(data, schema=schema.with_metadata(meta))
    atomic_write(path, lambda tmp: pq.write_table(table, tmp, **PARQUET_OPTIONS))


def write_landmarks(
    path, person_ids: list[int], frames: list[np.ndarray], tris: list[PersonTriangulation],
    camera_names: list[str], fps: float, world_up=(0.0, 0.0, 1.0),
) -> None:  # fmt: skip
    """Write `landmarks.parquet`: one row per frame and person, the 33 triangulated landmarks
    (`world_up`: `Rig.up`)."""
    C = len(camera_names)
    bits = (1 << np.arange(C)).astype(np.int64)
    rows = {k: [] for k in ("frame", "person_id", "xyz", "views", "mask", "err", "conf")}
    for pid, fr, tri in zip(person_ids, frames, tris, strict=True):
        T = len(fr)
        rows["frame"].append(fr)
        rows["person_id"].append(np.full(T, pid))
        rows["xyz"].append(tri.points.reshape(T, 99))
        rows["views"].append(tri.n_views)
        rows["mask"].append((tri.used * bits).sum(-1))
        rows["err"].append(tri.error)
        rows["conf"].append(tri.confidence)
    cat = {k: np.concatenate(v) if v else np.zeros((0,)) for k, v in rows.items()}
    order = np.lexsort((cat["person_id"], cat["frame"])) if len(cat["frame"]) else []
    n = len(order)

    def fixed(key: str, width: int, dtype) -> pa.Array:
        flat = np.ascontiguousarray(cat[key][order].reshape(n, width).astype(dtype)).ravel()
        return pa.FixedSizeListArray.from_arrays(pa.array(flat), width)

    fields = {
        "frame": ("", "video frame"),
        "time_s": ("s", "frame / fps"),
        "person_id": ("", "the fused track (as in bodies.parquet)"),
        "landmarks3d": ("m", "33 x 3 triangulated landmarks, world; NaN where < 2 views"),
        "views": ("", "per landmark, number of views used"),
        "view_mask": ("", "per landmark, bit c set when camera c was used"),
        "reprojection_px": ("px", "per landmark, mean error over the used views, full image"),
        "confidence": ("", "per landmark, in [0, 1]"),
    }
    data = {
        "frame": pa.array(cat["frame"][order].astype(np.int64)),
        "time_s": pa.array(cat["frame"][order] / float(fps)),
        "person_id": pa.array(cat["person_id"][order].astype(np.int64)),
        "landmarks3d": fixed("xyz", 99, np.float32),
        "views": fixed("views", 33, np.uint8),
        "view_mask": fixed("mask", 33, np.int64),
        "reprojection_px": fixed("err", 33, np.float32),
        "confidence": fixed("conf", 33, np.float32),
    }
    schema = pa.schema(
        [
            pa.field(k, data[k].type, metadata={"unit": u, "description": d})
            for k, (u, d) in fields.items()
        ],
        metadata={
            "gst.format": json.dumps("gst-capture/fused-landmarks"),
            "gst.format_version": "1",
            "gst.landmark_names": json.dumps(list(BLAZEPOSE_NAMES)),
            "gst.cameras": json.dumps(camera_names),
            "gst.fps": json.dumps(fps),
            "gst.axes": json.dumps({"world_up": [float(v) for v in world_up], "units": "m"}),
        },
    )
    table = pa.table(data, schema=schema)
    atomic_write(path, lambda tmp: pq.write_table(table, tmp, **PARQUET_OPTIONS))


@dataclass
class FusedBodies:
    """Rows of a fused bodies file (one per person and frame)."""

    person_id: np.ndarray  # (R,)
    frame: np.ndarray  # (R,)
    joints: np.ndarray  # (R, 24, 3) world, metres
    global_orient: np.ndarray  # (R, 3) axis-angle, body -> world
    body_pose: np.ndarray  # (R, 23, 3) axis-angle
    betas: np.ndarray  # (R, nb)
    transl: np.ndarray  # (R, 3) world, metres: the body model's translation
    joint_views: np.ndarray  # (R, 24) views of the joint's least-seen landmark
    gap_filled: np.ndarray  # (R, 24) bool
    observed: np.ndarray  # (R,) bool
    single_view: np.ndarray  # (R,) bool
    fps: float
    settings: dict  # the fusion's settings (FuseOptions as JSON)
    cameras: list[str]
    has_landmarks: np.ndarray  # (24,) bool: joints some landmark observes (the file's table)
    body_model: str = "anny"  # the body model the bodies were fitted with (`gst.model`)

    def __len__(self) -> int:
        return len(self.frame)

    def select(self, keep: np.ndarray) -> FusedBodies:
        """The rows where `keep` (a bool mask or row indices), the file-wide fields as they are."""
        per_row = ("person_id", "frame", "joints", "global_orient", "body_pose", "betas", "transl",
                   "joint_views", "gap_filled", "observed", "single_view")  # fmt: skip
        return replace(self, **{k: getattr(self, k)[keep] for k in per_row})


def read_fused_bodies(path: str | Path) -> FusedBodies:
    """Read `fused/bodies.parquet` (docs/formats/fused_bodies.md)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"fused bodies not found: {path} (run `python -m pipeline run fuse`, or train with "
            "distill=false)"
        )
    table = pq.read_table(path)
    meta = {k.decode(): v.decode() for k, v in (table.schema.metadata or {}).items()}
    missing = [
        c
        for c in ("frame", "person_id", "joints3d", "global_orient", "body_pose", "betas",
                  "joint_views", "joint_gap_filled", "observed", "single_view", "transl_world")
        if c not in table.column_names
    ]  # fmt: skip
    if missing or "gst.fused" not in meta:
        raise ValueError(
            f"{path}: not a fused bodies file (missing columns {missing} or 'gst.fused' metadata)"
        )

    def arr(name: str, width: int, dtype=np.float64) -> np.ndarray:
        col = table.column(name).combine_chunks()
        flat = np.asarray(col.flatten().to_numpy(zero_copy_only=False), dtype)
        return flat.reshape(len(table), width) if width > 1 else flat

    n = len(table)
    nb = len(table.column("betas")[0]) if n else 10
    fused_meta = json.loads(meta["gst.fused"])
    joint_names = json.loads(meta.get("gst.joint_names", "[]"))
    observed_by = fused_meta.get("joint_landmarks", {})
    if len(joint_names) != 24:
        raise ValueError(f"{path}: 'gst.joint_names' must list 24 joints")
    return FusedBodies(
        person_id=table.column("person_id").to_numpy(),
        frame=table.column("frame").to_numpy(),
        joints=arr("joints3d", 72).reshape(n, 24, 3),
        global_orient=arr("global_orient", 3),
        body_pose=arr("body_pose", 69).reshape(n, 23, 3),
        betas=arr("betas", nb),
        transl=arr("transl_world", 3),
        joint_views=arr("joint_views", 24, np.int64),
        gap_filled=arr("joint_gap_filled", 24, bool),
        observed=table.column("observed").to_numpy(zero_copy_only=False).astype(bool),
        single_view=table.column("single_view").to_numpy(zero_copy_only=False).astype(bool),
        fps=float(json.loads(meta.get("gst.fps", "30"))),
        settings=json.loads(meta.get("gst.tracking", "{}")),
        cameras=list(fused_meta.get("cameras", [])),
        has_landmarks=np.array([bool(observed_by.get(j)) for j in joint_names]),
        body_model=str(json.loads(meta.get("gst.model", "{}")).get("body_model", "anny")),
    )

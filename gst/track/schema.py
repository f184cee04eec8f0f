"""The tracks Parquet schema: columns, units, shapes and the self-describing file metadata.

The video name is not a column of the file: it is the Hive partition key, the folder
`video=<name>` the file sits in, and every dataset reader (pyarrow.dataset, pandas, polars,
duckdb) turns it back into a `video` column. It is also in the metadata (`gst.video`).

Array-valued columns are fixed-size lists of float32 holding the array in row-major (C) order;
their logical shape is in each field's metadata and in the file's `gst.columns` entry
(`joints3d` [24, 3] is x0, y0, z0, x1, ...). See docs/formats/tracks_parquet.md.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import pyarrow as pa

from gst.body.markers import BLAZEPOSE_NAMES
from gst.body.skeleton import SMPL_JOINT_NAMES

# Version 2 added the landmark model's 2D joints (landmarks2d, landmarks_conf) and the
# gst.landmark_names / gst.detector metadata; version-1 columns are unchanged.
FORMAT_NAME, FORMAT_VERSION = "gst-capture/tracks", 2


@dataclass(frozen=True)
class ColumnSpec:
    name: str
    shape: tuple[int, ...] | None  # None for scalars
    unit: str
    description: str
    frame: str | None = None  # "camera", "world", or "world|camera" (world when calibrated)
    nullable: bool = False


def column_specs(num_betas: int = 10) -> list[ColumnSpec]:
    J, L = len(SMPL_JOINT_NAMES), len(BLAZEPOSE_NAMES)
    return [
        ColumnSpec("frame", None, "", "0-based frame index in the video"),
        ColumnSpec("time_s", None, "s", "frame / fps"),
        ColumnSpec("person_id", None, "", "track id, stable across frames of one video"),
        ColumnSpec(
            "bbox",
            (4,),
            "px",
            "detection box x0, y0, x1, y1 on the raw frame, pixel-corner convention",
        ),
        ColumnSpec("score", None, "", "detection score"),
        ColumnSpec(
            "global_orient",
            (3,),
            "rad",
            "root orientation, axis-angle, in the frame of joints3d",
            "world|camera",
        ),
        ColumnSpec(
            "global_orient_cam", (3,), "rad", "root orientation, axis-angle, camera frame", "camera"
        ),
        ColumnSpec(
            "body_pose",
            (J - 1, 3),
            "rad",
            "joint rotations 1..23 relative to their parent, axis-angle",
        ),
        ColumnSpec("betas", (num_betas,), "", "body shape coefficients"),
        ColumnSpec("transl_cam", (3,), "m", "body model translation, camera frame", "camera"),
        ColumnSpec(
            "transl_world",
            (3,),
            "m",
            "body model translation for global_orient in world; null when uncalibrated",
            "world",
            nullable=True,
        ),
        ColumnSpec(
            "joints3d",
            (J, 3),
            "m",
            "3D joints; world frame when calibrated, else camera frame",
            "world|camera",
        ),
        ColumnSpec(
            "joints2d", (J, 2), "px", "joints projected into the raw frame, pixel-centre convention"
        ),
        ColumnSpec(
            "landmarks2d",
            (L, 2),
            "px",
            "the person model's 33 BlazePose landmarks on the raw frame, pixel-centre convention; "
            "null when the detector gives none (supplied boxes, background model)",
            nullable=True,
        ),
        ColumnSpec(
            "landmarks_conf",
            (L,),
            "",
            "confidence of each landmark in [0, 1] (visibility x presence); null with landmarks2d",
            nullable=True,
        ),
    ]


_SCALAR_TYPES = {
    "frame": pa.int64(),
    "time_s": pa.float64(),
    "person_id": pa.int64(),
    "score": pa.float32(),
}


def arrow_type(spec: ColumnSpec) -> pa.DataType:
    if spec.shape is None:
        return _SCALAR_TYPES[spec.name]
    n = 1
    for s in spec.shape:
        n *= s
    return pa.list_(pa.float32(), n)


def tracks_schema(num_betas: int = 10, metadata: dict[str, str] | None = None) -> pa.Schema:
    """The Arrow schema of a tracks file; `metadata` becomes the file's key-value metadata."""
    fields = []
    for spec in column_specs(num_betas):
        fmeta = {"unit": spec.unit, "description": spec.description}
        if spec.shape is not None:
            fmeta["shape"] = json.dumps(list(spec.shape))
        if spec.frame is not None:
            fmeta["frame"] = spec.frame
        fields.append(
            pa.field(
                spec.name,
                arrow_type(spec),
                nullable=spec.nullable or spec.name not in _SCALAR_TYPES,
                metadata=fmeta,
            )
        )
    return pa.schema(fields, metadata=metadata)


def columns_description(num_betas: int = 10) -> dict:
    return {
        s.name: {
            "shape": list(s.shape) if s.shape else [],
            "unit": s.unit,
            "frame": s.frame,
            "description": s.description,
        }
        for s in column_specs(num_betas)
    }


METADATA_KEYS = (
    "gst.format",
    "gst.format_version",
    "gst.joint_names",
    "gst.landmark_names",
    "gst.units",
    "gst.axes",
    "gst.fps",
    "gst.model",
    "gst.calibration",
    "gst.video",
    "gst.tracking",
    "gst.detector",
    "gst.smoothing",
    "gst.columns",
    "gst.stats",
    "gst.settings_sha256",
)


def file_metadata(
    *,
    fps: float,
    model: dict,
    calibration: dict,
    axes: dict,
    video: dict,
    tracking: dict,
    detector: dict | None = None,
    smoothing: dict | None,
    stats: dict,
    settings_sha256: str,
    num_betas: int = 10,
) -> dict[str, str]:
    """Schema metadata of a tracks file: every value is a JSON document (strings included)."""
    units = {
        "joints3d": "m",
        "transl_cam": "m",
        "transl_world": "m",
        "joints2d": "px",
        "landmarks2d": "px",
        "bbox": "px",
        "global_orient": "rad (axis-angle)",
        "body_pose": "rad (axis-angle)",
        "time_s": "s",
    }
    values = {
        "gst.format": FORMAT_NAME,
        "gst.format_version": FORMAT_VERSION,
        "gst.joint_names": list(SMPL_JOINT_NAMES),
        "gst.landmark_names": list(BLAZEPOSE_NAMES),
        "gst.units": units,
        "gst.axes": axes,
        "gst.fps": fps,
        "gst.model": model,
        "gst.calibration": calibration,
        "gst.video": video,
        "gst.tracking": tracking,
        "gst.detector": detector,
        "gst.smoothing": smoothing,
        "gst.columns": columns_description(num_betas),
        "gst.stats": stats,
        "gst.settings_sha256": settings_sha256,
    }
    return {k: json.dumps(v, sort_keys=True) for k, v in values.items()}


def parse_metadata(schema: pa.Schema) -> dict:
    """The `gst.*` metadata of a tracks schema as Python values (keys without the prefix)."""
    raw = schema.metadata or {}
    out = {}
    for k, v in raw.items():
        key = k.decode()
        if key.startswith("gst."):
            out[key[4:]] = json.loads(v.decode())
    if out.get("format") != FORMAT_NAME:
        raise ValueError(
            f"not a tracks file: metadata 'gst.format' is {out.get('format')!r}, expected "
            f"{FORMAT_NAME!r}"
        )
    version = out.get("format_version")
    if not isinstance(version, int) or not 1 <= version <= FORMAT_VERSION:
        raise ValueError(
            f"tracks format version {version!r}; this code reads versions 1 to {FORMAT_VERSION}"
            f"{' (update the package)' if isinstance(version, int) and version > 1 else ''}"
        )
    return out

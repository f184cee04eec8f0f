"""Reading tracks back: one file or a whole folder of videos, arrays in their logical shape, and
a long (one row per joint) table for plotting and group-bys. Returns pyarrow tables; call
`.to_pandas()` or `polars.from_arrow(...)` on them."""

from __future__ import annotations

import json
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as ds
import pyarrow.parquet as pq

from gst.track.schema import SMPL_JOINT_NAMES, parse_metadata
from gst.track.writer import PARTITION_PREFIX


def read_tracks(path: str | Path, videos: list[str] | None = None) -> pa.Table:
    """A tracks file, or a folder of `video=<name>/tracks.parquet` partitions (optionally only
    `videos`), as one table sorted by video, frame and person_id, with a `video` column either
    way."""
    path = Path(path)
    if path.is_dir() and path.name.startswith(PARTITION_PREFIX):
        # one video's folder: its name is the folder's (read below it, every row was null)
        name = unquote(path.name[len(PARTITION_PREFIX) :])
        table = read_tracks(path.parent, [name])
        return table if videos is None or name in videos else table.slice(0, 0)
    if path.is_file():
        table = pq.read_table(path, partitioning=None)
        name = _metadata(path, table.schema)["video"]["name"]  # in a dataset: the folder's
        table = table.add_column(0, "video", pa.array([name] * table.num_rows, pa.string()))
    elif path.is_dir():
        # the video name is text even where it looks like a number ("0001", "2"): the
        # partition's type is given, not inferred from the folder names
        partitioning = ds.partitioning(pa.schema([("video", pa.string())]), flavor="hive")
        dataset = ds.dataset(path, format="parquet", partitioning=partitioning)
        # every file is a tracks file of a version read here, and the table has the columns of
        # all of them (a dataset takes the first file's schema: the landmark columns of newer
        # files were dropped beside an older one), null where a file has none
        if not dataset.files:  # every video failed, or another folder: say so, not Arrow
            raise FileNotFoundError(
                f"{path}: no tracks here (expected video=<name>/tracks.parquet files)"
            )
        schemas = [pq.read_schema(f) for f in dataset.files]
        for f, schema in zip(dataset.files, schemas, strict=True):
            _metadata(Path(f), schema)
        if schemas:
            unified = pa.unify_schemas([s.remove_metadata() for s in schemas])
            unified = unified.append(pa.field("video", pa.string()))
            dataset = ds.dataset(path, format="parquet", partitioning=partitioning, schema=unified)
        flt = None if videos is None else pc.field("video").isin(videos)
        table = dataset.to_table(filter=flt)
    else:
        raise FileNotFoundError(f"{path}: no tracks file or folder here")
    if videos is not None and path.is_file():
        table = table.filter(pc.field("video").isin(videos))
    return table.sort_by(
        [("video", "ascending"), ("frame", "ascending"), ("person_id", "ascending")]
    )


def _metadata(path: Path, schema: pa.Schema) -> dict:
    try:
        return parse_metadata(schema)
    except ValueError as exc:  # its message names no file
        raise ValueError(f"{path}: {exc}") from exc


def read_metadata(path: str | Path) -> dict:
    """The self-describing metadata of one tracks file (joint names, units, axes, fps, model,
    calibration, ...), keys without the 'gst.' prefix."""
    return _metadata(Path(path), pq.read_schema(path))


def landmark_array(table: pa.Table) -> np.ndarray | None:
    """(N, 33, 3) landmarks (u, v, confidence) of a tracks table, or None when it has no rows
    or no landmark columns."""
    if "landmarks2d" not in table.column_names or table.num_rows == 0:
        return None
    return np.concatenate(
        [column_array(table, "landmarks2d"), column_array(table, "landmarks_conf")[..., None]], -1
    )


def column_array(table: pa.Table, name: str) -> np.ndarray:
    """A fixed-size-list column as float32 numpy in its logical shape, e.g. joints3d -> (N, 24, 3).
    Null entries (transl_world when uncalibrated) become NaN."""
    field = table.schema.field(name)
    shape_json = (field.metadata or {}).get(b"shape")
    if shape_json is None:
        raise KeyError(f"column '{name}' has no 'shape' metadata; it is not an array column")
    shape = json.loads(shape_json)
    col = table.column(name).combine_chunks()
    n = len(col)
    if col.null_count:
        out = np.full((n, int(np.prod(shape))), np.nan, np.float32)
        valid = col.is_valid().to_numpy(zero_copy_only=False)
        out[valid] = col.filter(col.is_valid()).flatten().to_numpy().reshape(-1, out.shape[1])
        return out.reshape(n, *shape)
    return col.flatten().to_numpy().reshape(n, *shape)


def long_format(table: pa.Table) -> pa.Table:
    """One row per (video, frame, person, joint): video, frame, time_s, person_id, joint_index,
    joint, x, y, z (joints3d, m) and u, v (joints2d, px). Tidy input for plots and group-bys."""
    j3 = column_array(table, "joints3d")
    j2 = column_array(table, "joints2d")
    n, J = j3.shape[:2]
    rep = np.repeat(np.arange(n), J)
    joint_index = np.tile(np.arange(J, dtype=np.int8), n)
    names = pa.DictionaryArray.from_arrays(
        pa.array(joint_index.astype(np.int32)), pa.array(SMPL_JOINT_NAMES)
    )
    return pa.table(
        {
            "video": table.column("video").take(rep),
            "frame": table.column("frame").take(rep),
            "time_s": table.column("time_s").take(rep),
            "person_id": table.column("person_id").take(rep),
            "joint_index": joint_index,
            "joint": names,
            "x": j3[..., 0].reshape(-1),
            "y": j3[..., 1].reshape(-1),
            "z": j3[..., 2].reshape(-1),
            "u": j2[..., 0].reshape(-1),
            "v": j2[..., 1].reshape(-1),
        }
    )

"""Crash-safe, resumable Parquet output for one video, in a Hive-style folder per video.

Layout (the output root is a Hive-partitioned dataset that pyarrow, pandas, polars and duckdb
read as a whole; nothing partial is ever inside it):

    <root>/video=<name>/tracks.parquet          the finished file (written once, atomically)
    <staging>/video=<name>/                     while tracking; default <staging> is the hidden
                                                sibling folder .<root name>.inprogress
        seg-000000.parquet, seg-000001.parquet  committed row groups, one Parquet file each
        progress.json                           settings, committed segments, next frame, state

The staging folder sits outside the dataset because polars and duckdb, given a folder or a
'**' glob, also read hidden and underscore-prefixed subfolders.

A commit first makes the segment durable (temporary name, fsync, rename), then rewrites
progress.json the same way. A kill at any moment leaves progress.json naming only complete
segments; a segment file it does not name is an orphan and is deleted on resume. Resume reads
progress.json, checks the run's settings are unchanged, and hands back the next frame and the
tracker state saved with the last commit, so a resumed run writes the same bytes as an
uninterrupted one. `finalize` concatenates and sorts the segments into tracks.parquet.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

import pyarrow as pa
import pyarrow.parquet as pq

from gst.atomic import atomic_path, atomic_write_text, fsync_dir

PROGRESS_VERSION = 1
FINAL_NAME = "tracks.parquet"
PARQUET_OPTIONS = {
    "compression": "zstd",
    "compression_level": 3,
    "version": "2.6",
    "write_statistics": True,
}


class ResumeError(RuntimeError):
    """Partial output exists but cannot be continued; the message says why and what to do."""


def settings_digest(settings: dict) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()


def default_staging_root(root: str | Path) -> Path:
    root = Path(root).absolute()
    return root.parent / f".{root.name}.inprogress"


PARTITION_PREFIX = "video="
MAX_NAME_BYTES = 255  # a folder name, on the common file systems


def partition_name(video: str) -> str:
    """`video=<name>`, the name percent-encoded as pyarrow's Hive partitioning expects; a name
    whose folder name would pass `MAX_NAME_BYTES` (about 27 CJK characters: 9 bytes each once
    encoded) is refused here, before any tracking, naming the video."""
    if not video:
        raise ValueError("video name must not be empty")
    name = PARTITION_PREFIX + quote(video, safe="")
    if len(name.encode()) > MAX_NAME_BYTES:
        raise ValueError(
            f"video name '{video}' is too long for its tracks folder: percent-encoded it takes "
            f"{len(name.encode())} bytes, a folder name at most {MAX_NAME_BYTES}; rename or link "
            "the file under a shorter name"
        )
    return name


def partition_dir(root: str | Path, video: str) -> Path:
    """<root>/video=<name> (`partition_name`)."""
    return Path(root) / partition_name(video)


def _write_json(path: Path, obj: dict) -> None:
    atomic_write_text(path, json.dumps(obj, sort_keys=True))


def _changed_keys(old, new, prefix: str = "") -> list[str]:
    """Dotted paths at which two JSON documents differ."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new)):
            out += _changed_keys(old.get(k), new.get(k), f"{prefix}{k}.")
        return out
    return [] if old == new else [prefix.rstrip(".")]


@dataclass
class ResumePoint:
    next_frame: int
    state: dict  # what the caller saved with the last commit
    segments: int
    rows: int


class TrackWriter:
    """Committed row groups for one video, resumable, finalised into one Parquet file."""

    def __init__(
        self,
        root: str | Path,
        video: str,
        schema: pa.Schema,
        settings: dict,
        staging_root: str | Path | None = None,
    ):
        self.video = video
        self.schema = schema.remove_metadata()
        self.settings = settings
        self.digest = settings_digest(settings)
        self.dir = partition_dir(root, video)
        self.final_path = self.dir / FINAL_NAME
        self.staging = partition_dir(staging_root or default_staging_root(root), video)
        self.progress_path = self.staging / "progress.json"
        self._progress: dict | None = None

    # -- state of the output ------------------------------------------------------------------
    def finished_digest(self) -> str | None:
        """The settings digest of an existing final file, or None when there is none."""
        if not self.final_path.exists():
            return None
        meta = pq.read_schema(self.final_path).metadata or {}
        raw = meta.get(b"gst.settings_sha256")
        return json.loads(raw) if raw else ""

    def _beside_dataset(self) -> Path:
        """Where finalize copies the file when the staging root is on another file system: in
        the folder that holds the dataset (the output root), on its file system."""
        return self.dir.parent.parent / f".{self.dir.name}.{FINAL_NAME}"

    def start(self, resume: bool = True) -> ResumePoint | None:
        """Prepare the staging folder. With `resume`, continue a matching partial run and return
        where it stopped; otherwise (or when there is none) start empty and return None."""
        stem, suffix = Path(FINAL_NAME).stem, Path(FINAL_NAME).suffix
        for leftover in self.dir.glob(f".{stem}.*tmp{suffix}"):  # older versions' finalize
            leftover.unlink(missing_ok=True)
        self._beside_dataset().unlink(missing_ok=True)  # a copy a kill interrupted
        if self.staging.exists() and not resume:
            shutil.rmtree(self.staging)
        if self.progress_path.exists():
            try:
                progress = json.loads(self.progress_path.read_text())
            except (OSError, json.JSONDecodeError) as exc:
                raise ResumeError(
                    f"{self.progress_path}: unreadable progress record ({exc}); delete "
                    f"{self.staging} or run without resume"
                ) from exc
            if progress.get("version") != PROGRESS_VERSION or progress.get("digest") != self.digest:
                changed = _changed_keys(
                    progress.get("settings", {}), json.loads(json.dumps(self.settings))
                )
                raise ResumeError(
                    f"{self.staging}: a partial run with different settings exists (changed: "
                    f"{changed}); run without resume to discard it"
                )
            self._check_segments(progress)
            self._progress = progress
        else:
            if self.staging.exists():
                shutil.rmtree(
                    self.staging
                )  # segments without a progress record were never committed
            self.staging.mkdir(parents=True)
            self._progress = {
                "version": PROGRESS_VERSION,
                "digest": self.digest,
                "settings": self.settings,
                "segments": [],
                "next_frame": None,
                "state": {},
            }
            return None
        seg = progress["segments"]
        return ResumePoint(
            progress["next_frame"], progress["state"], len(seg), sum(s["rows"] for s in seg)
        )

    def _check_segments(self, progress: dict) -> None:
        named = {s["file"] for s in progress["segments"]}
        for s in progress["segments"]:
            path = self.staging / s["file"]
            try:
                rows = pq.read_metadata(path).num_rows
            except (OSError, pa.ArrowException) as exc:
                raise ResumeError(
                    f"{path}: committed segment is missing or unreadable ({exc}); delete "
                    f"{self.staging} or run without resume"
                ) from exc
            if rows != s["rows"]:
                raise ResumeError(f"{path}: has {rows} rows, progress.json recorded {s['rows']}")
        for p in self.staging.iterdir():
            if p.name != "progress.json" and p.name not in named:
                p.unlink()  # an orphan from a commit that never completed

    def discard_staging(self) -> None:
        """Remove this video's partial work, if any."""
        shutil.rmtree(self.staging, ignore_errors=True)
        try:
            self.staging.parent.rmdir()
        except OSError:
            pass

    # -- writing ------------------------------------------------------------------------------
    def commit(self, table: pa.Table, next_frame: int, state: dict) -> None:
        """Durably add `table` as the next row group, with the frame and state to resume from."""
        if self._progress is None:
            raise RuntimeError("call start() before commit()")
        table = table.cast(self.schema) if table.schema != self.schema else table
        index = len(self._progress["segments"])
        name = f"seg-{index:06d}.parquet"
        with atomic_path(self.staging / name) as tmp:
            pq.write_table(table, tmp, row_group_size=max(len(table), 1), **PARQUET_OPTIONS)
        progress = dict(self._progress)
        progress["segments"] = [*self._progress["segments"], {"file": name, "rows": len(table)}]
        progress["next_frame"] = int(next_frame)
        progress["state"] = state
        _write_json(self.progress_path, progress)
        self._progress = progress

    def committed(self) -> pa.Table:
        """Every committed row so far, in order."""
        if self._progress is None:
            raise RuntimeError("call start() first")
        tables = [
            pq.read_table(self.staging / s["file"], schema=self.schema)
            for s in self._progress["segments"]
        ]
        return pa.concat_tables(tables) if tables else self.schema.empty_table()

    def finalize(self, metadata: dict[str, str], row_group_rows: int = 65536) -> Path:
        """Write tracks.parquet (with `metadata`) from the committed segments, sorted by frame
        then person_id, atomically, and remove the staging folder. (A segment may hold rows of
        earlier frames: the held rows of a person confirmed in it.)"""
        table = self.committed().sort_by([("frame", "ascending"), ("person_id", "ascending")])
        schema = self.schema.with_metadata(metadata)
        self.dir.mkdir(parents=True, exist_ok=True)
        # Written in the staging folder, outside the dataset, then renamed in: a temporary file
        # beside tracks.parquet, left by a kill before its rename, was read by polars and duckdb
        # (they read hidden files), every row twice after the rerun.
        staged = self.staging / f".{FINAL_NAME}"
        with (
            atomic_path(staged, unique=False) as tmp,
            pq.ParquetWriter(tmp, schema, **PARQUET_OPTIONS) as w,
        ):
            if len(table):
                w.write_table(
                    table.replace_schema_metadata(metadata), row_group_size=row_group_rows
                )
        try:
            os.replace(staged, self.final_path)
            fsync_dir(self.dir)
        except OSError as exc:  # a staging root on another file system
            if exc.errno != errno.EXDEV:
                raise
            # copied to the final file system beside the dataset, never inside it (a kill
            # during the copy left a hidden file in video=<name>/ that readers took as rows)
            outside = self._beside_dataset()
            with atomic_path(outside, unique=False) as tmp:
                shutil.copyfile(staged, tmp)
            os.replace(outside, self.final_path)
            fsync_dir(self.dir)
        self.discard_staging()
        return self.final_path

"""Track many videos through any `map(fn, items, description)` (a process pool, Ray): one work
item per video, or per chunk of a long video when chunking is on, then stitched in the caller.

Work items are plain picklable data: the detector and predictor travel as factories (e.g.
`functools.partial(GSTPredictor, checkpoint)`), built inside the worker. Every item is
idempotent, so an executor may retry it after a worker died: a whole-video item resumes its own
staging folder (gst.track.writer); a chunk item rewrites its chunk file atomically. The
finished file for a video is written once, by the caller, through the same TrackWriter as an
unchunked run (temporary name, fsync, rename).
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq

from calibration import Camera
from gst.cores import torch_threads
from gst.track.chunks import (
    ChunkingConfig,
    ChunkPlan,
    chunk_digest,
    plan_chunks,
    read_chunk,
    stitch_chunks,
    track_chunk,
)
from gst.track.detection import Detector
from gst.track.loop import (
    DETECTIONS_NOT_NEEDED,
    TrackOptions,
    TrackResult,
    VideoRun,
    plan_run,
    run_metadata,
    track_video,
)
from gst.track.predictor import Predictor
from gst.track.schema import tracks_schema
from gst.track.writer import TrackWriter, default_staging_root, partition_dir

MapFn = Callable[[Callable[[Any], Any], list, str], list]


@dataclass(frozen=True)
class VideoJob:
    """One video to track, with everything a worker needs to do it."""

    video: Path
    detector: Callable[[], Detector]
    predictor: Callable[[], Predictor]
    model: dict
    name: str | None = None
    camera: Camera | None = None
    world_up: tuple[float, float, float] | None = None
    options: TrackOptions = field(default_factory=TrackOptions)
    num_betas: int = 10
    threads: int | None = None  # torch threads inside the worker (None: leave as is)
    keep_extras: bool = False  # return each person's first extra outputs (e.g. Gaussians)
    detector_info: dict | None = None  # which person detector runs and why (gst.detector)
    # a folder where the detector's detections of the video are kept and replayed
    # (gst.track.detection_cache; whole videos only, not chunks)
    detections_cache: Path | None = None


@dataclass(frozen=True)
class _Item:
    job: VideoJob
    out_root: Path
    staging_root: Path
    chunk: ChunkPlan | None = None
    chunking: ChunkingConfig | None = None


@dataclass
class VideoOutcome:
    job: VideoJob
    result: TrackResult
    extras: dict[int, dict] = field(default_factory=dict)  # person id -> first row's extra outputs
    chunks: int = 1


def _chunk_path(staging_root: Path, name: str, index: int) -> Path:
    return partition_dir(staging_root / "chunks", name) / f"chunk-{index:05d}.parquet"


def _chunk_settings(job: VideoJob, chunking: ChunkingConfig) -> dict:
    return {"chunking": chunking.settings(job.options)}


def _run_settings(job: VideoJob) -> dict[str, Any]:
    """The job's settings as keywords of plan_run and track_video, written once."""
    return {
        "model": job.model,
        "camera": job.camera,
        "video_name": job.name,
        "options": job.options,
        "num_betas": job.num_betas,
        "world_up": job.world_up,
        "detector_info": job.detector_info,
    }


def _chunked_run(job: VideoJob, chunking: ChunkingConfig) -> VideoRun:
    """The job's run plan with the chunking in its settings (caller and workers agree)."""
    return plan_run(job.video, extra_settings=_chunk_settings(job, chunking), **_run_settings(job))


def run_item(item: _Item) -> Any:
    """Worker side: track one whole video (-> VideoOutcome) or one chunk (-> its record)."""
    # The job's own torch pool (None: leave it); put back afterwards, since an in-process
    # executor shares the caller's (a worker process's pool is its own anyway).
    with torch_threads(item.job.threads or None):
        return _run_item(item)


def _run_item(item: _Item) -> Any:
    job = item.job
    detector, predictor = job.detector(), job.predictor()
    if item.chunk is None:
        extras: dict[int, dict] = {}

        def keep(frame: int, person: int, extra: dict) -> None:
            extras.setdefault(person, extra)

        result = track_video(
            job.video,
            item.out_root,
            detector,
            predictor,
            staging_root=item.staging_root,
            on_extra=keep if job.keep_extras else None,
            detections_cache=job.detections_cache,
            # each person's first extras (their splat) exist only for the frames tracked now: a
            # kept finished file, or a resumed run, gave some people no splat, or nobody one
            resume=not job.keep_extras,
            **_run_settings(job),
        )
        return VideoOutcome(job, result, extras)
    run = _chunked_run(job, item.chunking)
    path = _chunk_path(item.staging_root, run.name, item.chunk.index)
    done = read_chunk(path, chunk_digest(run, item.chunk))
    if done is not None:  # a retry or a resumed stage run: the chunk is already there
        return done[1]
    return track_chunk(
        job.video,
        run,
        item.chunk,
        detector,
        predictor,
        tracks_schema(job.num_betas),
        job.options,
        job.num_betas,
        path,
    )


def check_unique_names(named: list[tuple[str, Path]]) -> None:
    """Refuse two videos under one output name (`video=<name>/`): the second one's tracks
    replaced the first one's without a word (GX010001.MP4 from two cameras' cards)."""
    by_name: dict[str, list[str]] = {}
    for name, video in named:
        by_name.setdefault(name, []).append(str(video))
    clashes = {n: v for n, v in by_name.items() if len(v) > 1}
    if clashes:
        listed = "; ".join(f"'{n}': {', '.join(v)}" for n, v in sorted(clashes.items()))
        raise ValueError(
            f"videos share an output name (their file name without its extension), so one "
            f"would overwrite the other's tracks: {listed}; rename the files"
        )


def track_videos(
    jobs: list[VideoJob],
    out_root: str | Path,
    *,
    map_fn: MapFn | None = None,
    staging_root: str | Path | None = None,
    chunking: ChunkingConfig | None = None,
    description: str = "track",
) -> list[VideoOutcome]:
    """Track every job's video into <out_root>/video=<name>/tracks.parquet, fanned out by `map_fn`.

    With `chunking`, a video longer than one chunk is split (see gst.track.chunks) and its chunks
    are separate items; this needs smoothing off and no extra outputs. Results are in job order.
    """
    check_unique_names([(job.name or Path(job.video).stem, Path(job.video)) for job in jobs])
    out_root = Path(out_root)
    staging_root = (
        Path(staging_root) if staging_root is not None else default_staging_root(out_root)
    )
    items: list[_Item] = []
    # job index -> (item indices, its run, its chunk plans); no items where the video's file is
    # already finished with these settings (a rerun reads it back, as an unchunked job does)
    chunked: dict[int, tuple[list[int], Any, list[ChunkPlan]]] = {}
    whole: dict[int, int] = {}  # job index -> item index
    for j, job in enumerate(jobs):
        plans = []
        if chunking is not None:
            if job.keep_extras:
                raise ValueError(
                    f"{job.video}: chunked tracking cannot keep per-person extras (Gaussians); "
                    "turn chunking off for --with-gaussians"
                )
            if job.options.smoothing is not None:
                raise ValueError(
                    f"{job.video}: chunked tracking cannot smooth; turn smoothing or chunking off"
                )
            run = _chunked_run(job, chunking)
            if run.end is not None:
                plans = plan_chunks(run.first, run.end, job.options, chunking)
        if len(plans) > 1 and _finished(job, run, out_root, staging_root):
            chunked[j] = ([], run, plans)
        elif len(plans) > 1:
            chunked[j] = (list(range(len(items), len(items) + len(plans))), run, plans)
            items += [_Item(job, out_root, staging_root, p, chunking) for p in plans]
        else:
            whole[j] = len(items)
            items.append(_Item(job, out_root, staging_root))
    results = (
        map_fn(run_item, items, description) if map_fn is not None else [run_item(x) for x in items]
    )
    outcomes: list[VideoOutcome] = []
    for j, job in enumerate(jobs):
        if j in chunked:
            _, run, plans = chunked[j]
            outcomes.append(_finish_chunked(job, run, plans, out_root, staging_root, chunking))
        else:
            outcomes.append(results[whole[j]])
    return outcomes


def _writer(job: VideoJob, run, out_root: Path, staging_root: Path) -> TrackWriter:
    """The writer of a chunked video's single Parquet file."""
    return TrackWriter(out_root, run.name, tracks_schema(job.num_betas), run.settings, staging_root)


def _finished(job: VideoJob, run, out_root: Path, staging_root: Path) -> bool:
    """The video's Parquet file is there, written with these settings."""
    writer = _writer(job, run, out_root, staging_root)
    return writer.finished_digest() == writer.digest


def _finish_chunked(
    job: VideoJob,
    run,
    plans: list[ChunkPlan],
    out_root: Path,
    staging_root: Path,
    chunking: ChunkingConfig,
) -> VideoOutcome:
    """Stitch the chunk files into the video's single Parquet file and clean up."""
    t0 = time.perf_counter()
    writer = _writer(job, run, out_root, staging_root)
    if writer.finished_digest() == writer.digest:
        stats = json.loads(pq.read_schema(writer.final_path).metadata[b"gst.stats"])
        result = TrackResult(
            writer.final_path,
            stats["rows"],
            stats["frames"],
            stats["persons"],
            None,
            0.0,
            DETECTIONS_NOT_NEEDED,
        )
        return VideoOutcome(job, result, chunks=len(plans))
    chunks = []
    for p in plans:
        path = _chunk_path(staging_root, run.name, p.index)
        got = read_chunk(path, chunk_digest(run, p))
        if got is None:
            raise RuntimeError(
                f"{job.video}: chunk {p.index} (frames {p.keep_from}..{p.end}) has no finished "
                f"file at {path}; its work item did not complete"
            )
        chunks.append(got)
    stitched = stitch_chunks(chunks, chunking.min_agreement)
    writer.start(resume=False)
    for p, table in zip(plans, stitched.tables, strict=True):
        writer.commit(table, p.end, {})
    meta = run_metadata(
        run,
        job.options,
        job.model,
        job.world_up,
        stitched.stats,
        writer.digest,
        job.num_betas,
        tracking_extra=_chunk_settings(job, chunking),
    )
    path = writer.finalize(meta, job.options.row_group_rows)
    shutil.rmtree(partition_dir(staging_root / "chunks", run.name), ignore_errors=True)
    s = stitched.stats
    return VideoOutcome(
        job,
        TrackResult(path, s["rows"], s["frames"], s["persons"], None, time.perf_counter() - t0),
        chunks=len(plans),
    )

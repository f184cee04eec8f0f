"""Track a long video in independent chunks and stitch the person ids at the chunk borders.

A chunk keeps the rows of frames [keep_from, end). It starts tracking `overlap` processed frames
earlier (its warm-up), from a fresh tracker. Those warm-up frames are also kept by the previous
chunk, so every person seen there has a row in both; a Hungarian matching on how often two ids
sit on the same detection in the overlap carries the previous chunk's ids over. Ids left
unmatched get new ids in the order the chunk created them, as one tracker over the whole video
would have done.

Exactness: the chunk size is a multiple of the loop's group size and chunks start on the group
grid, so every kept frame's crops are batched exactly as in an unchunked run and, with a
stateless detector (supplied boxes, the background model), the rows' numbers are the same
bytes. A stateful detector (BlazePose follows each person's region from frame to frame) starts
afresh in each warm-up, so its boxes and rows near a border differ a little from an unchunked
run; the overlap's rows are paired by box overlap, not by equal bytes. The ids equal the
unchunked ids whenever the association is unambiguous (the fresh tracker of the warm-up
re-acquires everyone the old one was following and nobody is occluded across a border).
Not exact either: a person whom the detector finds only now and then near a border (partly
hidden: every other frame). The unchunked tracker had confirmed them earlier and keeps them
through the misses; the warm-up's fresh tracker holds them tentative, and a tentative track
ends at its first miss, so with `min_hits` > 1 their rows after the border are lost until
they are found `min_hits` frames in a row (a review's check with a fifth of the detections
missing at random: 1-5 rows of a 60-frame clip lost in 10 of 16 settings).
Smoothing carries filter state across frames and is not exact under chunking, so it is
refused. The left/right smoother (`TrackOptions.unmirror`) looks `lag_s` ahead before it decides
a frame: each chunk tracks that far past its end and drops those rows, so its last frames are
decided as in an unchunked run (its first frames have the warm-up behind them). Chunking is
therefore opt-in and recorded in the file.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from scipy.optimize import linear_sum_assignment

from gst.atomic import atomic_path
from gst.detect.boxes import box_iou
from gst.track.detection import Detector
from gst.track.frames import STAT_KEYS, TrackingSession
from gst.track.loop import TrackOptions, VideoRun, tracked_groups
from gst.track.predictor import Predictor
from gst.track.writer import PARQUET_OPTIONS, settings_digest

CHUNK_META_KEY = b"gst.chunk"
# a chunk record's count of the detections still waiting for min_hits at its end (in its
# dropped_low_score; not a stat of the file)
PENDING_AT_END = "pending_at_end"


@dataclass(frozen=True)
class ChunkingConfig:
    """Split videos longer than `chunk_frames` processed frames; `overlap` frames are tracked
    twice (at least the tracker's `max_misses` + 1: `warm_up`)."""

    chunk_frames: int = 3000
    overlap: int = 30
    min_agreement: float = (
        0.5  # share of an id's overlap rows that must sit on one earlier id to inherit it
    )

    def __post_init__(self):
        if self.chunk_frames < 1 or self.overlap < 1:
            raise ValueError(
                f"chunking needs chunk_frames >= 1 and overlap >= 1, got {self.chunk_frames}, "
                f"{self.overlap}"
            )
        if not 0 < self.min_agreement <= 1:
            raise ValueError(f"min_agreement must be in (0, 1], got {self.min_agreement}")

    def settings(self, options: TrackOptions) -> dict:
        return {
            "chunk_frames": self.effective_size(options),
            "overlap": self.overlap,
            "warm_up": self.warm_up(options),
            "min_agreement": self.min_agreement,
        }

    def warm_up(self, options: TrackOptions) -> int:
        """Processed frames a chunk tracks before its own: `overlap`, and at least the tracker's
        `max_misses` + 1. A person hidden for exactly `max_misses` frames up to the border keeps
        their track in an unchunked run; a warm-up of `max_misses` frames (the stage's defaults:
        30 and 30) held no sighting of them, and they came back under a new id."""
        return max(self.overlap, options.tracker.max_misses + 1)

    def effective_size(self, options: TrackOptions) -> int:
        """Chunk size in processed frames, rounded up to whole groups (keeps batches exact)."""
        return math.ceil(self.chunk_frames / options.frames_per_group) * options.frames_per_group


@dataclass(frozen=True)
class ChunkPlan:
    index: int
    start: int  # first frame tracked (warm-up starts here)
    keep_from: int  # first frame whose rows this chunk contributes
    end: int  # frame after the chunk (exclusive)


def plan_chunks(
    first: int, end: int, options: TrackOptions, chunking: ChunkingConfig
) -> list[ChunkPlan]:
    """Chunks covering frames [first, end) on the stride grid, each keeping whole groups."""
    span = chunking.effective_size(options) * options.stride
    plans = []
    for i, keep_from in enumerate(range(first, end, span)):
        start = max(first, keep_from - chunking.warm_up(options) * options.stride)
        plans.append(ChunkPlan(i, start, keep_from, min(end, keep_from + span)))
    return plans


def _tail(run: VideoRun, options: TrackOptions) -> int:
    """Processed frames a chunk tracks past its end: the left/right smoother's look-ahead
    (`MirrorConfig.lag_s`), which decides a frame's labels only once it has seen that far; a
    chunk that stopped at its end decided its last frames blind (other labels than an
    unchunked run's). Their rows are the next chunk's, and dropped here."""
    if options.unmirror is None:
        return 0
    return math.ceil(options.unmirror.lag_s * run.info.fps / options.stride - 1e-9)


def chunk_digest(run: VideoRun, plan: ChunkPlan) -> str:
    return settings_digest({"run": run.settings, "chunk": [plan.start, plan.keep_from, plan.end]})


@dataclass(frozen=True)
class ChunkRecord:
    """What a finished chunk file records beside its rows (as JSON in its metadata): the digest
    of the settings and range it was tracked with, the first frame it keeps (earlier ones are
    the warm-up shared with the previous chunk), and the stats of the kept frames."""

    digest: str
    keep_from: int
    stats: dict[str, int]

    def to_json(self) -> str:
        return json.dumps({"digest": self.digest, "keep_from": self.keep_from, "stats": self.stats})

    @classmethod
    def from_json(cls, text: str | bytes) -> ChunkRecord:
        d = json.loads(text)
        return cls(
            str(d["digest"]), int(d["keep_from"]), {k: int(v) for k, v in d["stats"].items()}
        )


def read_chunk(path: Path, digest: str) -> tuple[pa.Table, ChunkRecord] | None:
    """A finished chunk file's (rows, record), or None when absent or written under other
    settings."""
    if not path.is_file():
        return None
    try:
        meta = pq.read_schema(path).metadata or {}
        record = ChunkRecord.from_json(meta[CHUNK_META_KEY])
    except (OSError, KeyError, ValueError, TypeError, pa.ArrowException):
        return None
    if record.digest != digest:
        return None
    return pq.read_table(path).replace_schema_metadata(None), record


def track_chunk(
    video_path: str | Path,
    run: VideoRun,
    plan: ChunkPlan,
    detector: Detector,
    predictor: Predictor,
    schema: pa.Schema,
    options: TrackOptions,
    num_betas: int,
    out_path: Path,
) -> ChunkRecord:
    """Track one chunk from a fresh tracker and write its rows (warm-up included, chunk-local
    ids) to `out_path` atomically. Returns the record stored with it: digest, keep_from and the
    stats of the kept frames only."""
    if options.smoothing is not None:
        raise ValueError(
            "chunked tracking cannot smooth (filter state would restart at every chunk); "
            "turn smoothing off or do not chunk"
        )
    session = TrackingSession(options.tracker, None)
    # groups close on the stride grid: a range whose end is off it ends its last group there
    stride = options.stride
    grid_end = plan.keep_from + -(-(plan.end - plan.keep_from) // stride) * stride
    warm = {k: 0 for k in STAT_KEYS}
    kept = None  # the stats at the chunk's end (the tail's frames are not its own)
    tables, last = [], None
    for g in tracked_groups(
        video_path,
        run,
        detector,
        predictor,
        session,
        schema,
        options,
        num_betas,
        start_frame=plan.start,
        end_frame=plan.end + _tail(run, options) * options.stride,
    ):
        frames = g.table.column("frame").to_numpy()
        tables.append(g.table.filter(pa.array(frames < plan.end)))
        if g.next_frame == plan.keep_from:
            warm = {k: session.stats[k] for k in STAT_KEYS}
        if g.next_frame == grid_end:
            kept = {k: session.stats[k] for k in STAT_KEYS}
        last = g.next_frame
    kept = kept or {k: session.stats[k] for k in STAT_KEYS}
    pending = 0
    if tables and last == grid_end:  # the video's end: detections still waiting for min_hits
        pending = len(session.pending)  # are counted, as track_video does (the next chunk, if
        kept["dropped_low_score"] += pending  # any, may confirm them: `stitch_chunks`)
    table = pa.concat_tables(tables) if tables else schema.empty_table()
    record = ChunkRecord(
        chunk_digest(run, plan),
        plan.keep_from,
        {**{k: int(kept[k] - warm[k]) for k in STAT_KEYS}, PENDING_AT_END: pending},
    )
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_path) as tmp:
        pq.write_table(
            table.replace_schema_metadata({CHUNK_META_KEY: record.to_json()}),
            tmp,
            row_group_size=max(len(table), 1),
            **PARQUET_OPTIONS,
        )
    return record


SAME_DETECTION_IOU = 0.5  # boxes of one frame in two chunks overlapping this much: one person


def _frame_boxes(table: pa.Table) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frames, (N, 4) boxes, person ids) of a table's rows."""
    boxes = np.asarray(
        table.column("bbox").combine_chunks().flatten().to_numpy(zero_copy_only=False)
    ).reshape(-1, 4)
    return table.column("frame").to_numpy(), boxes, table.column("person_id").to_numpy()


def match_ids(previous: pa.Table, warmup: pa.Table, min_agreement: float = 0.5) -> dict[int, int]:
    """Map the warm-up's ids to the previous chunk's ids (Hungarian on co-occurrence counts).

    In each overlap frame the two chunks' rows are paired by box overlap (Hungarian, IoU at
    least SAME_DETECTION_IOU): a stateless detector gives the same boxes in both, a stateful one
    (BlazePose's region tracking starts afresh in each chunk's warm-up) boxes a few pixels
    apart. A warm-up id inherits an earlier id only if more than `min_agreement` of its overlap
    rows sit on that id's rows."""
    pf, pb, pid = _frame_boxes(previous)
    wf, wb, wid = _frame_boxes(warmup)
    pairs: dict[tuple[int, int], int] = {}
    seen: dict[int, int] = {}
    # an id's rows where the previous chunk has rows too: a warm-up longer than the chunk
    # before it (overlap 30, chunk_frames 5) counted rows no vote could come from, and every
    # chunk's people got new ids
    shared = np.isin(wf, pf) if len(pf) else np.zeros(len(wf), bool)
    for local in wid[shared].tolist():
        seen[local] = seen.get(local, 0) + 1
    for frame in np.intersect1d(pf, wf):
        a, b = np.flatnonzero(pf == frame), np.flatnonzero(wf == frame)
        iou = box_iou(pb[a], wb[b])
        for r, c in zip(*linear_sum_assignment(-iou), strict=True):
            if iou[r, c] >= SAME_DETECTION_IOU:
                key = (int(pid[a[r]]), int(wid[b[c]]))
                pairs[key] = pairs.get(key, 0) + 1
    if not pairs:
        return {}
    olds = sorted({a for a, _ in pairs})
    news = sorted({b for _, b in pairs})
    votes = np.zeros((len(olds), len(news)))
    for (a, b), n in pairs.items():
        votes[olds.index(a), news.index(b)] = n
    rows, cols = linear_sum_assignment(-votes)
    return {
        news[c]: olds[r]
        for r, c in zip(rows, cols, strict=True)
        if votes[r, c] > 0 and votes[r, c] > min_agreement * seen[news[c]]
    }


@dataclass
class Stitched:
    tables: list[
        pa.Table
    ]  # each chunk's kept rows with video-wide ids, in (frame, person_id) order
    stats: dict
    inherited: list[dict[int, int]]  # per chunk: local id -> earlier id carried over the border


def stitch_chunks(
    chunks: list[tuple[pa.Table, ChunkRecord]], min_agreement: float = 0.5
) -> Stitched:
    """Give the chunks' rows video-wide ids: carried over the borders, else new in creation
    order."""
    next_id = 0
    previous: pa.Table | None = None
    previous_keep_from = previous_pending = 0
    out, inherited = [], []
    stats = {k: 0 for k in STAT_KEYS}
    for table, record in chunks:
        frame = table.column("frame").to_numpy()
        warm_mask = frame < record.keep_from
        warm, kept = table.filter(pa.array(warm_mask)), table.filter(pa.array(~warm_mask))
        carried = (
            match_ids(previous, warm, min_agreement) if previous is not None and len(warm) else {}
        )
        mapping = dict(carried)
        new_ids = sorted(set(kept.column("person_id").to_pylist()) - set(mapping))
        for local in new_ids:
            mapping[local] = next_id  # chunk-local ids grow in creation order, as global ids do
            next_id += 1
        if previous is not None and new_ids:
            # a person who came into view just before the border was not yet confirmed there
            # (min_hits): their first rows are this chunk's warm-up rows, and belong before it
            early = _unclaimed_rows(previous, previous_keep_from, warm, new_ids)
            # counted as dropped by the chunk before (waiting for min_hits at its end), rows now
            stats["dropped_low_score"] -= min(len(early), previous_pending)
            if len(early):
                early_ids = np.array([mapping[i] for i in early.column("person_id").to_numpy()])
                out[-1] = _sorted_rows(pa.concat_tables([out[-1], _with_ids(early, early_ids)]))
        local_ids = kept.column("person_id").to_numpy()
        kept = _sorted_rows(_with_ids(kept, np.array([mapping[i] for i in local_ids])))
        out.append(kept)
        inherited.append(carried)
        previous, previous_keep_from = kept, record.keep_from
        previous_pending = record.stats.get(PENDING_AT_END, 0)
        for k in STAT_KEYS:
            stats[k] += record.stats.get(k, 0)
    stats["persons"] = next_id
    stats["rows"] = sum(len(t) for t in out)  # the file's rows (held rows moved across borders)
    return Stitched(out, stats, inherited)


def _with_ids(table: pa.Table, ids: np.ndarray) -> pa.Table:
    column = pa.array(np.asarray(ids, dtype=np.int64))
    return table.set_column(table.schema.get_field_index("person_id"), "person_id", column)


def _sorted_rows(table: pa.Table) -> pa.Table:
    """In (frame, person_id) order, as the loop writes them."""
    order = np.lexsort((table.column("person_id").to_numpy(), table.column("frame").to_numpy()))
    return table.take(pa.array(order))


def _unclaimed_rows(previous: pa.Table, keep_from: int, warm: pa.Table, ids: list[int]) -> pa.Table:
    """The warm-up rows of the chunk-local `ids` (people new in this chunk) in the frames the
    previous chunk keeps (from its `keep_from` on) whose box no row of the previous chunk's
    frame covers (IoU below SAME_DETECTION_IOU): rows the previous chunk's tracker held back
    while the person was not yet confirmed. (The previous chunk's first row was taken for its
    first frame: a chunk with no rows at all, an empty scene until someone walked in, gave
    nothing back.)"""
    pf, pb, _ = _frame_boxes(previous)
    wf, wb, wid = _frame_boxes(warm)
    keep = np.zeros(len(wf), bool)
    for i in np.flatnonzero(np.isin(wid, ids) & (wf >= keep_from)):
        same = pf == wf[i]
        keep[i] = not same.any() or box_iou(pb[same], wb[i : i + 1]).max() < SAME_DETECTION_IOU
    return warm.filter(pa.array(keep))

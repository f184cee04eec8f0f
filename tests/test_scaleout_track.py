"""Chunked tracking: exact rows, stitched ids, resumable chunks (no Ray needed)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from gst.track import OneEuroConfig, SuppliedBoxes, TrackOptions
from gst.track.batch import track_videos
from gst.track.chunks import (
    ChunkingConfig,
    ChunkRecord,
    match_ids,
    plan_chunks,
    stitch_chunks,
)
from gst.track.mirror import MirrorConfig
from gst.track.schema import tracks_schema
from gst.track.tracker import TrackerConfig
from tests.scaleout_scenes import job, separated_walkers, write_clip
from tests.track_synthetic import render, walker_boxes, write_boxes_csv, write_video


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return write_clip(tmp_path_factory.mktemp("clip"), "clip", 60)


def _rows(path):
    return pq.read_table(path).replace_schema_metadata(None)


# (5, 12): a warm-up longer than the chunk before it gave every chunk's people new ids
@pytest.mark.parametrize("chunk_frames,overlap", [(12, 4), (20, 7), (5, 1), (5, 12)])
def test_chunked_rows_equal_unchunked(clip, tmp_path, chunk_frames, overlap):
    video, csv = clip
    plain = track_videos([job(video, csv)], tmp_path / "plain")[0]
    chunked = track_videos(
        [job(video, csv)],
        tmp_path / "chunked",
        chunking=ChunkingConfig(chunk_frames=chunk_frames, overlap=overlap),
    )[0]
    assert chunked.chunks == -(
        -60
        // ChunkingConfig(chunk_frames, overlap).effective_size(TrackOptions(frames_per_group=5))
    )
    assert chunked.chunks > 1
    assert _rows(chunked.result.path).equals(_rows(plain.result.path))
    assert len(set(_rows(plain.result.path).column("person_id").to_pylist())) == 3
    a, b = pq.read_schema(plain.result.path).metadata, pq.read_schema(chunked.result.path).metadata
    assert {k for k in a if a[k] != b[k]} == {b"gst.tracking", b"gst.settings_sha256"}
    assert json.loads(a[b"gst.stats"]) == json.loads(b[b"gst.stats"])
    assert json.loads(b[b"gst.tracking"])["chunking"]["overlap"] == overlap
    # Only the finished file is left: chunk files and staging are gone.
    assert not any((tmp_path / ".chunked.inprogress").rglob("*.parquet"))


def test_plan_chunks_cover_the_range_on_the_group_grid():
    opts = TrackOptions(stride=2, frames_per_group=4, tracker=TrackerConfig(max_misses=2))
    plans = plan_chunks(3, 70, opts, ChunkingConfig(chunk_frames=6, overlap=3))
    assert [p.keep_from for p in plans] == [3, 19, 35, 51, 67]  # 8 processed frames x stride 2
    assert plans[0].start == 3 and all(p.start == p.keep_from - 6 for p in plans[1:])
    assert [p.end for p in plans] == [19, 35, 51, 67, 70]
    # the warm-up is at least the tracker's max_misses + 1 processed frames
    longer = plan_chunks(
        3, 70, replace(opts, tracker=TrackerConfig(max_misses=5)), ChunkingConfig(6, 3)
    )
    assert all(p.start == p.keep_from - 12 for p in longer[1:])


def test_a_person_hidden_up_to_a_border_for_max_misses_frames_keeps_their_id(tmp_path):
    """Hidden for exactly `max_misses` frames up to the border, a person keeps their track in
    an unchunked run; a warm-up of `overlap == max_misses` frames (the stage's defaults, 30
    and 30) held no sighting of them, and they came back under a new id."""
    import functools

    from gst.track import BoxDepthPredictor, Detection
    from gst.track.batch import VideoJob
    from tests.track_synthetic import MODEL, crossing_clip

    _, boxes, video = crossing_clip(tmp_path, 30)
    misses = 3
    last_seen = 10 - misses - 1  # the border at frame 10
    dets = {
        i: [Detection(boxes[i][2], 0.9)]
        + ([Detection(boxes[i][0], 0.9)] if (i <= last_seen or i >= 10) else [])
        for i in range(30)
    }
    opts = TrackOptions(
        prefetch=0,
        frames_per_group=2,
        tracker=TrackerConfig(min_hits=1, max_misses=misses),
        unmirror=None,
    )
    ids = {}
    for name, chunking in (("whole", None), ("chunked", ChunkingConfig(10, misses))):
        job_ = VideoJob(
            video, functools.partial(SuppliedBoxes, dets), BoxDepthPredictor, MODEL, options=opts
        )
        table = _rows(track_videos([job_], tmp_path / name, chunking=chunking)[0].result.path)
        frames = table.column("frame").to_pylist()
        x0 = [b[0] for b in table.column("bbox").to_pylist()]
        people = table.column("person_id").to_pylist()
        ids[name] = sorted(
            {p for f, x, p in zip(frames, x0, people, strict=True) if abs(x - boxes[f][0][0]) < 1}
        )
    assert ids["whole"] == ids["chunked"] and len(ids["whole"]) == 1


def _table(frames, ids, boxes):
    schema = tracks_schema(10)
    n = len(frames)
    cols = {f.name: pa.nulls(n, f.type) for f in schema}
    cols["frame"] = pa.array(frames, pa.int64())
    cols["person_id"] = pa.array(ids, pa.int64())
    cols["bbox"] = pa.FixedSizeListArray.from_arrays(
        pa.array(np.asarray(boxes, np.float32).reshape(-1)), 4
    )
    return pa.Table.from_arrays([cols[f.name] for f in schema], schema=schema)


def test_match_ids_hungarian_and_agreement():
    box = {0: [0, 0, 10, 10], 1: [50, 0, 60, 10], 2: [100, 0, 110, 10]}
    prev = _table([8, 8, 9, 9], [5, 7, 5, 7], [box[0], box[1], box[0], box[1]])
    # Warm-up ids 0 and 1 swap relative to the previous chunk's 7 and 5; id 2 sits on nothing old.
    warm = _table([8, 8, 9, 9, 9], [1, 0, 1, 0, 2], [box[0], box[1], box[0], box[1], box[2]])
    assert match_ids(prev, warm) == {1: 5, 0: 7}
    # An id that sits on an old id in only 1 of 3 rows does not inherit it.
    warm2 = _table([8, 9, 10], [0, 0, 0], [box[0], box[2], box[2]])
    assert match_ids(prev, warm2) == {}


def test_stitch_gives_new_ids_in_creation_order_after_the_carried_ones():
    box = {0: [0, 0, 10, 10], 1: [50, 0, 60, 10]}
    stats = {
        "frames": 1,
        "rows": 0,
        "detections": 0,
        "dropped_nonfinite": 0,
        "dropped_low_score": 0,
    }
    c0 = _table([0, 1, 1], [0, 0, 1], [box[0], box[0], box[1]])
    c1 = _table([1, 1, 2, 2], [1, 0, 1, 0], [box[0], box[1], box[0], box[1]])  # ids swapped locally
    s = stitch_chunks([(c0, ChunkRecord("a", 0, stats)), (c1, ChunkRecord("b", 2, stats))])
    assert s.tables[1].column("person_id").to_pylist() == [0, 1]
    assert s.inherited[1] == {1: 0, 0: 1}
    assert s.stats["persons"] == 2 and s.stats["frames"] == 2


def test_chunking_refuses_smoothing_and_extras(clip, tmp_path):
    video, csv = clip
    smooth = TrackOptions(frames_per_group=5, smoothing=OneEuroConfig())
    with pytest.raises(ValueError, match="smooth"):
        track_videos([job(video, csv, options=smooth)], tmp_path, chunking=ChunkingConfig(10, 2))
    with pytest.raises(ValueError, match="extras"):
        track_videos([job(video, csv, keep_extras=True)], tmp_path, chunking=ChunkingConfig(10, 2))


def test_finished_chunks_are_reused_on_rerun(clip, tmp_path, monkeypatch):
    """A chunk whose file exists (an earlier, interrupted run) is not tracked again."""
    import gst.track.batch as batch

    video, csv = clip
    chunking = ChunkingConfig(chunk_frames=20, overlap=5)
    calls = []
    real = batch.track_chunk

    def counting(*args, **kw):
        calls.append(args[2].index)
        if args[2].index == 2 and calls.count(2) == 1:
            raise KeyboardInterrupt  # the run dies in the last chunk
        return real(*args, **kw)

    monkeypatch.setattr(batch, "track_chunk", counting)
    with pytest.raises(KeyboardInterrupt):
        track_videos([job(video, csv)], tmp_path / "out", chunking=chunking)
    out = track_videos([job(video, csv)], tmp_path / "out", chunking=chunking)[0]
    assert calls == [0, 1, 2, 2]
    reference = track_videos([job(video, csv)], tmp_path / "ref")[0]
    assert _rows(out.result.path).equals(_rows(reference.result.path))


def test_a_finished_chunked_video_is_not_tracked_again(clip, tmp_path, monkeypatch):
    """An unchunked job whose file is finished returns it; a chunked one tracked every chunk
    again (its chunk files are gone after stitching) and then found the finished file."""
    import gst.track.batch as batch

    video, csv = clip
    chunking = ChunkingConfig(chunk_frames=20, overlap=5)
    first = track_videos([job(video, csv)], tmp_path / "out", chunking=chunking)[0]
    calls = []
    monkeypatch.setattr(batch, "track_chunk", lambda *a, **k: calls.append(a[2].index))
    again = track_videos([job(video, csv)], tmp_path / "out", chunking=chunking)[0]
    assert calls == [] and again.result.path == first.result.path
    assert again.result.rows == first.result.rows > 0


class _Settling(SuppliedBoxes):
    """A stateful detector, as BlazePose's region tracking is: its boxes settle onto the true
    ones over its first frames (a few pixels off at first), so a chunk's warm-up, which starts
    it afresh, sees boxes that differ from the previous chunk's for the same people."""

    def __init__(self, boxes):
        super().__init__(boxes)
        self.calls = 0

    def detect(self, image, frame_index):
        self.calls += 1
        shift = 6.0 / self.calls
        return [
            replace(d, box=d.box + np.array([shift, shift, shift, shift], np.float32))
            for d in super().detect(image, frame_index)
        ]


def _plain_and_chunked(the_job, tmp_path):
    """The job tracked whole and in chunks of 20 frames (overlap 5): both outcomes."""
    plain = track_videos([the_job], tmp_path / "plain")[0]
    chunking = ChunkingConfig(chunk_frames=20, overlap=5)
    return plain, track_videos([the_job], tmp_path / "chunked", chunking=chunking)[0]


def test_a_stateful_detector_keeps_its_ids_across_chunk_borders(clip, tmp_path):
    """Rows of the overlap were paired only when frame and box were equal to the byte: with the
    default person model (stateful) every chunk gave everyone new ids (3 people -> 9)."""
    video, csv = clip

    def settling():
        return _Settling(SuppliedBoxes.from_file(csv, video.stem).boxes)

    plain, chunked = _plain_and_chunked(job(video, csv, detector=settling), tmp_path)
    assert chunked.chunks == 3
    ids = set(_rows(chunked.result.path).column("person_id").to_pylist())
    assert ids == set(_rows(plain.result.path).column("person_id").to_pylist()) == {0, 1, 2}


def test_match_ids_pairs_boxes_a_few_pixels_apart():
    prev = _table([8, 8], [5, 7], [[0, 0, 10, 20], [50, 0, 60, 20]])
    warm = _table([8, 8], [0, 1], [[51, 1, 61, 21], [1, 1, 11, 21]])  # another detector state
    assert match_ids(prev, warm) == {0: 7, 1: 5}
    far = _table([8], [0], [[20, 0, 30, 20]])  # no overlap with anyone: no id carried
    assert match_ids(prev, far) == {}


@pytest.mark.parametrize(
    "hidden, unmirror", [([2], MirrorConfig()), ([2], None), ([0, 1, 2], None)]
)
def test_a_person_entering_just_before_a_border_keeps_their_first_rows(tmp_path, hidden, unmirror):
    """Someone seen from frame 18 with a border at 20 was not yet confirmed in the first chunk
    (min_hits 3), and the second chunk kept only frames from 20: rows 18 and 19 were lost,
    while `gst.stats` still counted them. [0, 1, 2]: nobody before frame 18, so the first chunk
    has no rows at all (the rows were lost there still)."""
    walkers = separated_walkers()
    boxes = walker_boxes(walkers, 40)
    visible = np.ones(boxes.shape[:2], bool)
    visible[:18, hidden] = False
    video = write_video(tmp_path / "late.avi", render(walkers, boxes, 320, 240), 320, 240)
    csv = write_boxes_csv(tmp_path / "late.csv", boxes, "late", visible)
    # without the left/right smoother, whose look-ahead tracks the first chunk past its border
    # (long enough to confirm the newcomer there)
    options = TrackOptions(
        frames_per_group=5, batch_size=4, tracker=TrackerConfig(min_hits=3), unmirror=unmirror
    )
    plain, chunked = _plain_and_chunked(job(video, csv, options=options), tmp_path)
    assert chunked.chunks == 2
    assert min(_rows(plain.result.path).column("frame").to_pylist()) == (
        18 if len(hidden) == 3 else 0
    )
    assert _rows(chunked.result.path).equals(_rows(plain.result.path))
    stats = json.loads(pq.read_schema(chunked.result.path).metadata[b"gst.stats"])
    assert stats["rows"] == pq.read_table(chunked.result.path).num_rows == plain.result.rows


def test_detections_pending_at_the_end_of_an_off_grid_range_are_counted_in_chunks(tmp_path):
    """61 frames at stride 3 end off the grid (the last group ends at 63): the last chunk never
    saw its group end at the range's end, so someone seen only in the last two processed
    frames (min_hits 3) was left out of dropped_low_score, which an unchunked run counts."""
    walkers = separated_walkers()
    boxes = walker_boxes(walkers, 61)
    visible = np.ones(boxes.shape[:2], bool)
    visible[:55, 2] = False  # processed frames 57 and 60 only
    video = write_video(tmp_path / "end.avi", render(walkers, boxes, 320, 240), 320, 240)
    csv = write_boxes_csv(tmp_path / "end.csv", boxes, "end", visible)
    options = TrackOptions(
        frames_per_group=4, batch_size=4, stride=3, tracker=TrackerConfig(min_hits=3)
    )
    the_job = job(video, csv, options=options)
    plain = track_videos([the_job], tmp_path / "plain")[0]
    chunked = track_videos(
        [the_job], tmp_path / "chunked", chunking=ChunkingConfig(chunk_frames=4, overlap=3)
    )[0]
    assert chunked.chunks > 1
    for r in (plain, chunked):
        s = json.loads(pq.read_schema(r.result.path).metadata[b"gst.stats"])
        dropped = s["dropped_low_score"] + s["dropped_parts"] + s["dropped_nonfinite"]
        assert s["detections"] == s["rows"] + dropped, s
        assert s["dropped_low_score"] == 2


class _FlippingLandmarks(SuppliedBoxes):
    """Supplied boxes with stick-figure landmarks whose left/right labels flip for good from
    frame `flip` on: a stateless detector that gives the left/right smoother work."""

    flip = 18

    def detect(self, image, frame_index):
        from gst.track.mirror import LIMB_PAIRS

        out = []
        for d in super().detect(image, frame_index):
            x0, y0, x1, y1 = d.box
            cx, h = (x0 + x1) / 2, y1 - y0
            lm = np.zeros((33, 3), np.float32)
            lm[:] = (cx, y0 + h / 2, 1.0)
            dx = 0.06 * h * (-1 if frame_index >= self.flip else 1)
            for (left, right), y in zip(
                LIMB_PAIRS, (0.25, 0.4, 0.5, 0.55, 0.75, 0.95), strict=True
            ):
                lm[left, :2], lm[right, :2] = (cx + dx, y0 + y * h), (cx - dx, y0 + y * h)
            out.append(replace(d, landmarks=lm))
        return out


def test_the_left_right_smoother_decides_a_chunks_last_frames_as_an_unchunked_run(clip):
    """The smoother looks `lag_s` ahead before it decides a frame; a chunk stopped at its end
    and decided its last frames blind: the labels of frames 18-19 (a flip just before the
    border at 20) differed from an unchunked run's, 4 detections exchanged against 0."""
    video, csv = clip

    def detector():
        return _FlippingLandmarks(SuppliedBoxes.from_file(csv, video.stem).boxes)

    tmp = video.parent
    plain = track_videos([job(video, csv, detector=detector)], tmp / "flip_plain")[0]
    chunked = track_videos(
        [job(video, csv, detector=detector)],
        tmp / "flip_chunked",
        chunking=ChunkingConfig(chunk_frames=20, overlap=5),
    )[0]
    assert chunked.chunks == 3
    assert _rows(chunked.result.path).equals(_rows(plain.result.path))
    stats = [
        json.loads(pq.read_schema(r.result.path).metadata[b"gst.stats"]) for r in (plain, chunked)
    ]
    assert stats[0] == stats[1]


def test_per_person_extras_are_there_when_a_finished_file_exists(clip, tmp_path):
    """With --with-gaussians (`keep_extras`) a video whose finished tracks file was kept, or
    whose run resumed, replayed no frames: its people got no splat, and the stage failed on its
    missing splat folder (a rerun after a killed run failed every time)."""
    video, csv = clip

    def with_extras(**kw):
        return job(video, csv, keep_extras=True, predictor=_ExtraOutputs, **kw)

    first = track_videos([with_extras()], tmp_path / "out")[0]
    assert len(first.extras) == 3  # every tracked person's first extras
    again = track_videos([with_extras()], tmp_path / "out")[0]
    assert set(again.extras) == set(first.extras)
    plain = track_videos([job(video, csv)], tmp_path / "out")[0]
    assert plain.result.detections != "run"  # without extras the finished file is kept


class _ExtraOutputs:
    """The pixel-free predictor plus one per-crop output beyond the body (as Gaussians are)."""

    def __init__(self):
        from gst.track import BoxDepthPredictor

        self.inner = BoxDepthPredictor()

    def __call__(self, crops, K_crop):
        out = self.inner(crops, K_crop)
        out["gaussian_means"] = np.zeros((len(crops), 4, 3), np.float32)
        return out


def test_two_videos_under_one_name_are_refused(clip, tmp_path):
    """cam1/clip.avi and cam2/clip.avi both went to video=clip/: the second one's tracks
    replaced the first one's, and both outcomes named that file."""
    import shutil

    video, csv = clip
    other = tmp_path / "card2" / video.name
    other.parent.mkdir()
    shutil.copy(video, other)
    with pytest.raises(ValueError, match=r"share an output name.*'clip'.*card2"):
        track_videos([job(video, csv), job(other, csv)], tmp_path / "tracks")
    assert not (tmp_path / "tracks").exists()


def test_chunked_rows_equal_unchunked_at_a_given_rate_within_a_time_range(clip, tmp_path):
    """With the scene's rate (TrackOptions.fps) the last chunk's look-ahead read past `end_s`
    (its cap came from the time range at the file's rate, then dropped), and `start_s` with
    stride 2 failed on the grid ("start_frame 13 is not on the grid 0 + k * 2")."""
    video, csv = clip
    asked: list[int] = []

    class Recording:
        def __init__(self):
            self.inner = SuppliedBoxes.from_file(csv, video.stem)

        def detect(self, image, index):
            asked.append(index)
            return self.inner.detect(image, index)

    options = TrackOptions(frames_per_group=5, batch_size=4, fps=25.0, start_s=0.5, end_s=1.9)
    for stride in (1, 2):
        opts = replace(options, stride=stride)
        plain = track_videos(
            [job(video, csv, options=opts, detector=Recording)], tmp_path / f"plain{stride}"
        )[0]
        chunked = track_videos(
            [job(video, csv, options=opts, detector=Recording)],
            tmp_path / f"chunked{stride}",
            chunking=ChunkingConfig(chunk_frames=12, overlap=4),
        )[0]
        assert chunked.chunks > 1
        rows = _rows(plain.result.path)
        assert _rows(chunked.result.path).equals(rows)
        frames = np.array(rows.column("frame").to_pylist())
        # [0.5 s, 1.9 s) at 25 frames/s: frames 13 .. 47 (at the file's 30: 15 .. 56)
        assert frames.min() == 13 and frames.max() <= 47
        assert min(asked) == 13 and max(asked) <= 47  # nothing read outside the range
        np.testing.assert_allclose(rows.column("time_s").to_pylist(), frames / 25.0)
        a = json.loads(pq.read_schema(plain.result.path).metadata[b"gst.stats"])
        b = json.loads(pq.read_schema(chunked.result.path).metadata[b"gst.stats"])
        assert a == b
        asked.clear()


def test_a_person_confirmed_after_a_border_is_not_also_counted_as_dropped(tmp_path):
    """Someone who appears one frame before a chunk border waits for min_hits there: the chunk
    counted them as dropped, and the next chunk gave their early rows back to it, so the file's
    stats had `rows + dropped` one above `detections` (an unchunked run's stats differ)."""
    import functools

    from gst.track import BoxDepthPredictor, Detection
    from gst.track.batch import VideoJob
    from tests.track_synthetic import MODEL, crossing_clip

    _, boxes, video = crossing_clip(tmp_path, 20)
    dets = {
        i: [Detection(boxes[i][0], 0.9)] + ([Detection(boxes[i][2], 0.9)] if i >= 9 else [])
        for i in range(20)
    }
    opts = TrackOptions(
        prefetch=0, frames_per_group=5, tracker=TrackerConfig(min_hits=3), unmirror=None
    )
    found = {}
    for name, chunking in (("whole", None), ("chunked", ChunkingConfig(10, 4))):
        job_ = VideoJob(
            video, functools.partial(SuppliedBoxes, dets), BoxDepthPredictor, MODEL, options=opts
        )
        out = track_videos([job_], tmp_path / name, chunking=chunking)[0]
        found[name] = (
            _rows(out.result.path),
            json.loads(pq.read_schema(out.result.path).metadata[b"gst.stats"]),
        )
    (rows, stats), (chunk_rows, chunk_stats) = found["whole"], found["chunked"]
    assert chunk_rows.equals(rows)
    assert chunk_stats == stats
    dropped = sum(stats[k] for k in ("dropped_low_score", "dropped_parts", "dropped_nonfinite"))
    assert stats["detections"] == len(rows) + dropped

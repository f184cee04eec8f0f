"""The person detector's detections of a video are kept and replayed by the next run over the
same video (gst.track.detection_cache): the detector does not run again, the tracks are the
same; another video, other detector settings or code, a longer run or a damaged file run it."""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

from gst.track import SuppliedBoxes, TrackOptions
from gst.track import detection_cache as dc
from gst.track.detection import Detection
from tests.track_synthetic import H, W, crossing_clip, track_boxes, write_boxes_csv

N = 24
INFO = {"name": "fake", "config": {"threshold": 0.5}}


class CountingDetector:
    """Supplied boxes, each with landmarks made from its box (but for person 0's, none), that
    counts its calls."""

    def __init__(self, boxes_csv):
        self.inner = SuppliedBoxes.from_file(boxes_csv, video="clip")
        self.calls = 0

    def detect(self, frame, index):
        self.calls += 1
        out = []
        for k, d in enumerate(self.inner.detect(frame, index)):
            x0, y0, x1, y1 = d.box
            lm = None
            if k:
                t = np.linspace(0, 1, 33, dtype=np.float32)
                lm = np.c_[x0 + t * (x1 - x0), y0 + t * (y1 - y0), np.full(33, 0.9, np.float32)]
            out.append(Detection(d.box, 0.8 - 0.1 * k, landmarks=lm))
        return out


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    d = tmp_path_factory.mktemp("clip")
    _, boxes, video = crossing_clip(d, N, W, H)
    return video, write_boxes_csv(d / "boxes.csv", boxes, "clip")


def _track(video, out, det, cache, info=INFO, **options):
    return track_boxes(
        video,
        out,
        det,
        options=TrackOptions(**options),
        detector_info=info,
        detections_cache=cache,
        resume=False,
    )


def _rows(path):
    return pq.read_table(path).drop_columns(["time_s"]).to_pydict()


def test_a_second_run_replays_the_detections_and_writes_the_same_tracks(clip, tmp_path):
    video, boxes = clip
    cache = tmp_path / "cache"
    first = CountingDetector(boxes)
    a = _track(video, tmp_path / "a", first, cache)
    assert first.calls == N and len(list(cache.glob("detections-*.npz"))) == 1
    assert a.detections == "run and kept"
    again = CountingDetector(boxes)
    b = _track(video, tmp_path / "b", again, cache)
    assert again.calls == 0 and b.detections == "replayed"
    assert _rows(a.path) == _rows(b.path)
    # a shorter run replays the start of the longer one's file
    short = CountingDetector(boxes)
    _track(video, tmp_path / "c", short, cache, end_s=10 / 30)
    assert short.calls == 0


def test_the_kept_detections_are_those_found(clip, tmp_path):
    video, boxes = clip
    det = CountingDetector(boxes)
    rec = dc.RecordingDetector(det)
    found = {i: rec.detect(None, i) for i in range(0, N, 2)}
    path = tmp_path / "kept.npz"
    rec.save(path, N)
    back = dc.load_detections(path, 0, 2, N)
    assert sorted(back.starts) == sorted(found)
    for i, ds in found.items():
        assert len(back.detect(None, i)) == len(ds)
        for d, e in zip(ds, back.detect(None, i), strict=True):
            np.testing.assert_array_equal(d.box, e.box)
            assert d.score == e.score
            if d.landmarks is None:
                assert e.landmarks is None
            else:
                np.testing.assert_array_equal(d.landmarks, e.landmarks)
    assert dc.load_detections(path, 0, 2, N + 2) is None  # the file does not reach that far
    assert dc.load_detections(path, 0, 1, N) is None  # other frames


def test_a_run_whose_decoding_stopped_short_is_replayed_to_the_same_frame(clip, tmp_path):
    """A container may count a frame or two more than it holds: the run planned to N stops
    at N - 2, and so does every run over the same bytes; its file serves them."""
    _, boxes = clip
    rec = dc.RecordingDetector(CountingDetector(boxes))
    for i in range(N - 2):
        rec.detect(None, i)
    path = tmp_path / "short.npz"
    rec.save(path, N)
    back = dc.load_detections(path, 0, 1, N)
    assert back is not None and sorted(back.starts) == list(range(N - 2))
    # a file with a frame missing inside the range serves nothing
    gap = dc.RecordingDetector(CountingDetector(boxes))
    for i in [*range(5), *range(6, N)]:
        gap.detect(None, i)
    gap.save(tmp_path / "gap.npz", N)
    assert dc.load_detections(tmp_path / "gap.npz", 0, 1, N) is None


def test_a_cache_that_cannot_be_written_leaves_the_run_as_it_is(clip, tmp_path, caplog):
    video, boxes = clip
    blocked = tmp_path / "blocked"
    blocked.write_text("a file where the cache folder should be")
    det = CountingDetector(boxes)
    with caplog.at_level("WARNING", logger="gst.track"):
        res = _track(video, tmp_path / "a", det, blocked)
    assert det.calls == N and res.detections == "run" and "not kept" in caplog.text
    assert res.rows > 0


def test_another_video_settings_or_run_does_not_replay(clip, tmp_path):
    video, boxes = clip
    cache = tmp_path / "cache"
    _track(video, tmp_path / "a", CountingDetector(boxes), cache, end_s=12 / 30)
    # a longer run than the kept one
    longer = CountingDetector(boxes)
    _track(video, tmp_path / "b", longer, cache)
    assert longer.calls == N
    # other detector settings
    other = CountingDetector(boxes)
    _track(video, tmp_path / "c", other, cache, info={**INFO, "config": {"threshold": 0.6}})
    assert other.calls == N
    # other stride
    strided = CountingDetector(boxes)
    _track(video, tmp_path / "d", strided, cache, stride=2)
    assert strided.calls == N // 2
    # the same frames in another file: another video
    copy = tmp_path / "clip.avi"
    data = bytearray(video.read_bytes())
    copy.write_bytes(bytes(data))
    same = CountingDetector(boxes)
    _track(copy, tmp_path / "e", same, cache)
    assert same.calls == 0  # the key is the content, not the name
    data[-1] ^= 0xFF  # one byte changed
    copy.write_bytes(bytes(data))
    changed = CountingDetector(boxes)
    _track(copy, tmp_path / "f", changed, cache)
    assert changed.calls == N
    # without detector information (nothing says what found them) nothing is kept
    none = CountingDetector(boxes)
    _track(video, tmp_path / "g", none, tmp_path / "cache2", info=None)
    assert not (tmp_path / "cache2").exists()


def test_other_person_model_code_frames_or_stride_is_another_key(clip, monkeypatch, tmp_path):
    video, _ = clip
    module = tmp_path / "fake_person_model.py"
    module.write_text("THRESHOLD = 0.5\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(dc, "DETECTOR_MODULES", ("fake_person_model",))
    key = dc.detections_key(video, INFO, 0, 1)
    assert key == dc.detections_key(video, INFO, 0, 1)
    module.write_text("THRESHOLD = 0.6\n")  # the module's source changed
    assert dc.detections_key(video, INFO, 0, 1) != key
    assert dc.detections_key(video, INFO, 1, 1) != dc.detections_key(video, INFO, 0, 1)
    assert dc.detections_key(video, INFO, 0, 2) != dc.detections_key(video, INFO, 0, 1)


def test_a_damaged_file_is_not_used_and_is_written_again(clip, tmp_path, caplog):
    video, boxes = clip
    cache = tmp_path / "cache"
    _track(video, tmp_path / "a", CountingDetector(boxes), cache)
    (path,) = cache.glob("detections-*.npz")
    path.write_bytes(path.read_bytes()[:200])
    det = CountingDetector(boxes)
    with caplog.at_level("WARNING", logger="gst.track"):
        _track(video, tmp_path / "b", det, cache)
    assert det.calls == N and "not read" in caplog.text
    again = CountingDetector(boxes)
    _track(video, tmp_path / "c", again, cache)
    assert again.calls == 0

"""`track` on videos that are empty, over-announced, or whose detector fails mid-stream: a clear
error and nothing that looks finished, or a run that copes, and no thread left behind."""

import os
import struct
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest

from gst.track import BoxDepthPredictor, SuppliedBoxes, TrackOptions, track_video
from gst.track.detection import Detection
from gst.track.static_detector import StaticCameraDetector
from gst.video import VideoError, iter_frames, probe_video, read_frames
from tests.track_synthetic import crossing_clip, track_boxes


def test_a_video_without_frames_is_refused_and_nothing_is_written(tmp_path):
    """A container holding no frame probed as 'length unknown', decoded nothing, and `track`
    finalised an empty tracks.parquet that read as a finished video in which nobody moved."""
    path = tmp_path / "empty.avi"
    cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (320, 240)).release()
    assert probe_video(path).frame_count is None
    with pytest.raises(VideoError, match="empty.avi: no frame could be decoded"):
        track_boxes(path, tmp_path / "out", SuppliedBoxes({}), options=TrackOptions(prefetch=0))
    assert not list((tmp_path / "out").rglob("*.parquet"))


def _announcing_one_more(src: Path, dst: Path, more: int = 1) -> None:
    """An AVI whose headers announce `more` frames more than it holds (some cameras write that;
    negative: fewer than it holds)."""
    data = bytearray(src.read_bytes())
    avih, strh = data.find(b"avih"), data.find(b"strh")
    n = struct.unpack_from("<I", data, avih + 8 + 16)[0]
    struct.pack_into("<I", data, avih + 8 + 16, n + more)  # dwTotalFrames
    struct.pack_into("<I", data, strh + 8 + 32, n + more)  # dwLength
    dst.write_bytes(bytes(data))


def test_a_count_off_from_what_the_file_holds_is_said(tmp_path, caplog):
    """A container that announces fewer frames than it holds lost its tail silently (the file
    looked complete), and one whose last frame is missing ended one short without a word."""
    *_, video = crossing_clip(tmp_path, frames=30)
    under, over = tmp_path / "under.avi", tmp_path / "over.avi"
    _announcing_one_more(video, under, more=-10)
    _announcing_one_more(video, over, more=1)
    with caplog.at_level("WARNING", logger="gst.video"):
        assert len(list(iter_frames(under))) == 20
        assert len(list(iter_frames(under, stride=3))) == 7
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2 and all("announces 20 frames but holds more" in m for m in said)
    caplog.clear()
    with caplog.at_level("WARNING", logger="gst.video"):
        assert len(list(iter_frames(over))) == 30
        assert len(list(iter_frames(video))) == 30  # an exact count: nothing to say
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and "ended at frame 30, 1 before the 31 frames" in said[0]


def test_the_background_detector_takes_a_video_that_announces_one_frame_too_many(tmp_path):
    """The tracking loop accepts a container that over-announces by up to END_SLACK_FRAMES; the
    background detector sampled the announced last frame for its plate and refused the file."""
    *_, video = crossing_clip(tmp_path, frames=40)
    over = tmp_path / "over.avi"
    _announcing_one_more(video, over)
    assert probe_video(over).frame_count == 41 and len(list(iter_frames(over))) == 40
    detector = StaticCameraDetector(over)
    frame = next(iter_frames(over)).image
    assert detector.detect(frame, 0)


class _FailingDetector:
    def detect(self, image, index):
        if index == 12:
            raise ZeroDivisionError("detector failed at 12")
        return [Detection(np.array([10.0, 20.0, 60.0, 200.0]), 0.9)]


def test_a_detector_error_leaves_no_decode_thread_behind(tmp_path):
    """With prefetch, a failing detector left the decode thread (and its video capture) alive
    until the next garbage collection: the exception's traceback held the generators in a
    cycle and only the detector's stage was closed."""
    *_, video = crossing_clip(tmp_path, frames=40)
    with pytest.raises(ZeroDivisionError, match="at 12"):
        track_video(
            video,
            tmp_path / "out",
            _FailingDetector(),
            BoxDepthPredictor(),
            model={"name": "test", "version": "0"},
            options=TrackOptions(prefetch=4, frames_per_group=5),
        )
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and any(
        t.name == "video-decode" for t in threading.enumerate()
    ):
        time.sleep(0.05)
    assert not [t.name for t in threading.enumerate() if t.name == "video-decode"]


class _BrightColumn:
    """A stateless detector: the box of the frame's bright column."""

    def detect(self, image, index):
        xs = np.flatnonzero(image[60, :, 0] > 100)
        return [Detection(np.array([xs[0], 20.0, xs[-1] + 1, 100.0]), 0.9)]


def _column_video(path: Path, x0: int) -> None:
    vw = cv2.VideoWriter(str(path), 0, 30.0, (160, 120))  # uncompressed: the size is fixed
    for _ in range(10):
        frame = np.zeros((120, 160, 3), np.uint8)
        frame[20:100, x0 : x0 + 30] = 200
        vw.write(frame)
    vw.release()


def test_another_video_of_the_same_name_and_size_is_tracked_again(tmp_path):
    """The settings named a video by file name, byte size, frame size, rate and count only: a
    re-exported video with all of them equal got the earlier video's finished file back."""
    video = tmp_path / "cam.avi"
    boxes = []
    for x0 in (10, 100):
        _column_video(video, x0)
        result = track_video(
            video, tmp_path / "out", _BrightColumn(), BoxDepthPredictor(),
            model={"name": "test", "version": "0"}, options=TrackOptions(prefetch=0),
        )  # fmt: skip
        boxes.append(pq.read_table(result.path)["bbox"][0].as_py()[0])
    assert boxes == [10.0, 100.0]


def test_a_run_killed_after_its_last_commit_resumes_on_a_video_of_unknown_length(
    tmp_path, monkeypatch
):
    """A raw MJPEG stream announces no frame count. A run killed after committing its last
    group saved a resume point past the end (last frame + stride); every rerun then failed
    with 'decoding failed ... on the way to frame 63', as if the file were truncated."""
    from gst.track import writer

    raw = tmp_path / "raw.mjpeg"
    with open(raw, "wb") as fh:
        for i in range(60):
            frame = np.full((120, 160, 3), (i * 4) % 256, np.uint8)
            fh.write(cv2.imencode(".jpg", frame)[1].tobytes())
    assert probe_video(raw).frame_count is None
    options = TrackOptions(stride=7, frames_per_group=2, prefetch=0)

    def killed(self, *args, **kwargs):
        raise KeyboardInterrupt("killed before finalize")

    with monkeypatch.context() as m:
        m.setattr(writer.TrackWriter, "finalize", killed)
        with pytest.raises(KeyboardInterrupt):
            track_video(raw, tmp_path / "out", _OneBox(), BoxDepthPredictor(),
                        model={"name": "test", "version": "0"}, options=options)  # fmt: skip
    result = track_video(raw, tmp_path / "out", _OneBox(), BoxDepthPredictor(),
                         model={"name": "test", "version": "0"}, options=options)  # fmt: skip
    assert result.frames == 9 and result.resumed_from_frame == 63


def test_a_start_past_the_end_of_a_stream_of_unknown_length_says_so(tmp_path):
    """A raw stream gives no frame count, so a start past its end could not be checked before
    decoding, and the run said 'no frame could be decoded (an empty or unreadable video
    stream)', blaming a good file."""
    raw = tmp_path / "raw.mjpeg"
    with open(raw, "wb") as fh:
        for i in range(20):
            fh.write(cv2.imencode(".jpg", np.full((48, 64, 3), i * 10, np.uint8))[1].tobytes())
    assert probe_video(raw).frame_count is None
    with pytest.raises(VideoError, match=r"frame 125 \(5.0 s\): the start lies past the end"):
        track_video(raw, tmp_path / "out", _OneBox(), BoxDepthPredictor(),
                    model={"name": "test", "version": "0"},
                    options=TrackOptions(start_s=5.0, prefetch=0))  # fmt: skip
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*.parquet"))


class _OneBox:
    def detect(self, image, index):
        return [Detection(np.array([10.0, 20.0, 60.0, 100.0]), 0.9)]


def test_empty_tracks_say_why():
    """A clip shorter than `min_hits` processed frames gave 0 rows, exit 0 and no word."""
    from gst.track.scene import TrackSettings, nobody_tracked

    s = TrackSettings()
    assert nobody_tracked(5, 1, s) is None
    assert "track.min_hits=3" in nobody_tracked(0, 2, s)
    # `frames` counts processed frames: at stride 2, 5 of them are enough for min_hits 3 (the
    # warning blamed min_hits for anything under 6)
    assert "track.min_hits" in nobody_tracked(0, 2, TrackSettings(stride=2))
    assert "kept no one" in nobody_tracked(0, 5, TrackSettings(stride=2))
    assert "kept no one" in nobody_tracked(0, 40, s)


def test_a_raw_stream_says_its_frame_rate_is_a_guess(tmp_path, caplog):
    """A raw stream has no container to hold its rate: written at 60 frames/s, it is read at
    FFmpeg's default 25, and every time_s was 2.4 times too large without a word."""
    path = tmp_path / "cam.mjpeg"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 60, (64, 48))
    for i in range(5):
        writer.write(np.full((48, 64, 3), 40 * i, np.uint8))
    writer.release()
    with caplog.at_level("WARNING", logger="gst.video"):
        info = probe_video(path)
    assert info.fps == 25.0  # the decoder's guess, not the 60 it was written at
    assert any("raw MJPEG stream holds no frame rate" in m for m in caplog.messages)
    caplog.clear()
    with caplog.at_level("WARNING", logger="gst.video"):
        probe_video(path)  # a run probes a video several times: it was said each time
    assert not caplog.messages
    caplog.clear()
    with caplog.at_level("WARNING", logger="gst.video"):
        probe_video(crossing_clip(tmp_path, 3)[2])  # a container: no warning
    assert not caplog.messages


def test_a_kill_as_the_tracks_file_is_renamed_in_leaves_nothing_in_the_dataset(tmp_path):
    """finalize wrote its temporary file beside tracks.parquet: killed before the rename, the
    hidden file stayed in the dataset folder, and polars and duckdb (which read hidden files)
    counted every row twice once the rerun had written tracks.parquet."""
    import subprocess
    import sys

    raw = tmp_path / "clip.avi"
    vw = cv2.VideoWriter(str(raw), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (160, 120))
    for i in range(12):
        vw.write(np.full((120, 160, 3), i * 10, np.uint8))
    vw.release()
    out = tmp_path / "out"
    script = f"""
import os, signal
from pathlib import Path
import numpy as np
from gst.track import BoxDepthPredictor, TrackOptions, track_video
from gst.track.detection import Detection

class OneBox:
    def detect(self, image, index):
        return [Detection(np.array([10.0, 20.0, 60.0, 100.0]), 0.9)]

real = os.replace
def replace(src, dst, *a, **k):  # SIGKILL just before tracks.parquet is renamed into place
    if Path(dst).name == "tracks.parquet" and os.environ.get("KILL"):
        os.kill(os.getpid(), signal.SIGKILL)
    return real(src, dst, *a, **k)
os.replace = replace
track_video({str(raw)!r}, {str(out)!r}, OneBox(), BoxDepthPredictor(),
            model={{"name": "test", "version": "0"}},
            options=TrackOptions(frames_per_group=4, prefetch=0))
"""
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "KILL": "1"}
    killed = subprocess.run([sys.executable, "-c", script], cwd=root, env=env)
    assert killed.returncode == -9
    assert [p.name for p in (out / "video=clip").iterdir()] == []
    rerun = subprocess.run([sys.executable, "-c", script], cwd=root, env={**env, "KILL": ""})
    assert rerun.returncode == 0
    assert [p.name for p in (out / "video=clip").iterdir()] == ["tracks.parquet"]
    assert pq.read_table(out / "video=clip" / "tracks.parquet").num_rows == 12


def test_a_time_range_without_a_frame_is_named_not_blamed_on_the_video(tmp_path):
    """start_s 0.51 / end_s 0.52 at 30 frames/s (frames 16 to 16), end_s 0 or a negative time
    decoded nothing and failed with "no frame could be decoded (an empty or unreadable video
    stream)" though the file was fine; end before start was found only inside the worker."""
    from pydantic import ValidationError

    from gst.track.scene import TrackSettings

    video = tmp_path / "cam.avi"
    _column_video(video, 10)
    for start, end in ((0.21, 0.22), (0.05, 0.06)):
        with pytest.raises(ValueError, match="holds no frame"):
            track_video(
                video, tmp_path / "out", _BrightColumn(), BoxDepthPredictor(),
                model={"name": "test", "version": "0"},
                options=TrackOptions(prefetch=0, start_s=start, end_s=end),
            )  # fmt: skip
    for bad in ({"end_s": 0.0}, {"end_s": -5.0}, {"start_s": -1.0}, {"start_s": 2, "end_s": 1}):
        with pytest.raises(ValidationError):
            TrackSettings(**bad)


def test_reading_a_folder_without_tracks_says_so(tmp_path):
    """A tracks folder where every video failed gave "ArrowInvalid: Invalid sort key column"."""
    from gst.track import read_tracks

    with pytest.raises(FileNotFoundError, match="no tracks here"):
        read_tracks(tmp_path)


def test_detections_still_waiting_for_an_id_at_the_end_are_counted(tmp_path):
    """A person seen only on the last frames (fewer than min_hits) got no row and was counted
    nowhere: gst.stats' detections no longer added up to rows and the dropped counts."""
    from gst.track import read_metadata
    from gst.track.tracker import TrackerConfig

    video = tmp_path / "cam.avi"
    _column_video(video, 10)

    class _LastTwo:
        def detect(self, image, index):
            return [Detection(np.array([10.0, 20.0, 40.0, 100.0]), 0.9)] if index >= 8 else []

    result = track_video(
        video, tmp_path / "out", _LastTwo(), BoxDepthPredictor(),
        model={"name": "test", "version": "0"},
        options=TrackOptions(prefetch=0, unmirror=None, tracker=TrackerConfig(min_hits=3)),
    )  # fmt: skip
    stats = read_metadata(result.path)["stats"]
    dropped = stats["dropped_low_score"] + stats["dropped_parts"] + stats["dropped_nonfinite"]
    assert stats["detections"] == 2 and stats["rows"] == 0 and dropped == 2


def test_extraction_takes_a_video_that_announces_a_frame_too_many(tmp_path):
    """A container announcing one frame more than it holds: tracking took its last decodable
    frame as the end, extraction planned the announced count and failed on the missing frame,
    calling the file corrupt. check_videos now gives each camera the frames it really holds."""
    from gst.video import VideoError, check_videos

    src = tmp_path / "a.avi"
    _column_video(src, 10)  # 10 frames
    _announcing_one_more(src, tmp_path / "b.avi")
    _announcing_one_more(src, tmp_path / "c.avi", more=5)
    infos = check_videos({"a": src, "b": tmp_path / "b.avi"}, ["a", "b"])
    assert infos["a"].frames == infos["b"].frames == 10
    with pytest.raises(VideoError, match="different frame counts"):  # 5 missing: not slack
        check_videos({"a": src, "c": tmp_path / "c.avi"}, ["a", "c"])
    # a rate the container does not give (fps 0, allowed by the strict probe): counted as
    # announced (the check went through a reader that refuses an unknown rate)
    from dataclasses import replace

    from gst.video import held_frames, probe_video

    info = probe_video(tmp_path / "b.avi", "b", strict=True)
    assert held_frames(info) == 10 and held_frames(replace(info, fps=0.0)) == 11


def test_a_video_is_timed_at_the_rate_given_where_its_header_is_not_trusted(tmp_path):
    """A raw stream read at FFmpeg's 25 frames/s: the scene's `fps` (TrackOptions.fps) was
    ignored by `track`, so time_s, the time range and the file's rate all followed the guess."""
    _, boxes, video = crossing_clip(tmp_path, 24)  # written at 30 frames/s
    detector = SuppliedBoxes(
        {f: [Detection(b.astype(float), 0.9) for b in boxes[f]] for f in range(len(boxes))}
    )
    options = TrackOptions(prefetch=0, fps=60.0, start_s=0.1)
    res = track_boxes(video, tmp_path / "out", detector, options=options)
    table = pq.read_table(res.path)
    frames = np.array(table.column("frame").to_pylist())
    times = np.array(table.column("time_s").to_pylist())
    assert frames.min() >= 6  # 0.1 s at 60 frames/s (at the header's 30: frame 3)
    np.testing.assert_allclose(times, frames / 60.0)
    assert float(table.schema.metadata[b"gst.fps"]) == 60.0
    # the overlay shows the tracked frames (it read the range back at the file's rate: other
    # frames, and no row drawn on any)
    from gst.track.report import write_overlay

    out = write_overlay(video, res.path, tmp_path / "overlay.avi", fourcc="MJPG")
    assert probe_video(out).frame_count == 24 - 6  # frames 6 .. 23 (at 30: 3 .. 23)
    with pytest.raises(ValueError, match="fps must be > 0"):
        TrackOptions(fps=0.0)
    # not given, it is not in the run's settings: files tracked before it existed still resume
    assert "fps" not in TrackOptions().settings() and options.settings()["fps"] == 60.0


def test_negative_frame_indices_and_rates_are_refused_by_name(tmp_path):
    """read_frames(path, [-1, 2]) handed out frame 0 as frame -1; iter_frames(fps=0) died in
    a ZeroDivisionError at the first frame, fps NaN or negative timed every frame NaN or
    before the start."""
    *_, video = crossing_clip(tmp_path, frames=5)
    with pytest.raises(ValueError, match=f"{video.name}: frame indices must be >= 0, got -1"):
        list(read_frames(video, [-1, 2]))
    assert [f for f, _ in read_frames(video, [3, 0])] == [0, 3]
    for fps in (0.0, float("nan"), -25.0):
        with pytest.raises(ValueError, match=f"{video.name}: fps must be > 0 frames/s"):
            list(iter_frames(video, fps=fps))


def test_the_background_detector_takes_grey_and_bgra_frames_and_refuses_16_bit(tmp_path):
    """Grey and BGRA frames failed deep in OpenCV ("scn == m.cols"); a uint16 frame gave one
    box over the whole frame: the frame is converted or refused as the person model's is."""
    _, _, video = crossing_clip(tmp_path, 20)
    detector = StaticCameraDetector(video)
    frame = next(f for f in iter_frames(video) if f.index == 10).image
    want = [d.box.tolist() for d in detector.detect(frame, 10)]
    assert want
    bgra = cv2.cvtColor(frame, cv2.COLOR_BGR2BGRA)
    assert [d.box.tolist() for d in detector.detect(bgra, 10)] == want
    grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    assert detector.detect(grey, 10) and detector.detect(grey[..., None], 10)
    with pytest.raises(ValueError, match="uint8"):
        detector.detect(frame.astype(np.uint16) * 256, 10)

"""Streaming decode: stride, time range, exact resume position, prefetch, and clear errors."""

import cv2
import numpy as np
import pytest

from gst.video import VideoError, VideoTruncatedError, frame_range, iter_frames, probe_video

W, H, N, FPS = 96, 64, 30, 10.0


def numbered_frames():
    for i in range(N):
        f = np.full((H, W, 3), (i * 8) % 256, np.uint8)
        cv2.putText(f, str(i), (10, 50), cv2.FONT_HERSHEY_SIMPLEX, 1.2, (255, 255, 255), 2)
        yield f


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    path = tmp_path_factory.mktemp("v") / "clip.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (W, H))
    for f in numbered_frames():
        vw.write(f)
    vw.release()
    return path


def test_probe(video):
    info = probe_video(video)
    assert (info.width, info.height, info.fps, info.frame_count, info.name) == (
        W,
        H,
        FPS,
        N,
        "clip",
    )


def test_all_frames_and_times(video):
    frames = list(iter_frames(video))
    assert [f.index for f in frames] == list(range(N))
    assert [f.time_s for f in frames] == [i / FPS for i in range(N)]
    # brightness encodes the index (MJPG is lossy: compare a plain region)
    assert [int(round(f.image[5:15, 60:90].mean() / 8)) for f in frames] == list(range(N))


def test_stride_and_time_range(video):
    got = [f.index for f in iter_frames(video, stride=4, start_s=0.55, end_s=2.3)]
    assert got == [6, 10, 14, 18, 22]  # t in [0.55, 2.3): frames 6..22, every 4th from the first


def test_start_frame_resumes_exactly(video, caplog):
    full = {f.index: f.image for f in iter_frames(video, stride=3)}
    resumed = list(iter_frames(video, stride=3, start_frame=12))
    assert [f.index for f in resumed] == [12, 15, 18, 21, 24, 27]
    assert "not frame-exact" not in caplog.text  # an ordinary file seeks, not reads from 0
    for f in resumed:
        np.testing.assert_array_equal(f.image, full[f.index])
    with pytest.raises(ValueError, match="not on the grid"):
        iter_frames(video, stride=3, start_frame=13)
    assert list(iter_frames(video, start_frame=N)) == []


def test_a_transport_stream_starts_on_the_frame_asked_for(tmp_path, caplog):
    """MPEG-2 in a transport stream (as camcorders' .MTS are): OpenCV's seek lands on a keyframe
    or a frame late and reports the position asked for; the start is then reached by reading
    from the start, and every start gives the frame that a read from the start gives."""
    path = tmp_path / "clip.ts"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MPEG"), 30.0, (160, 120))
    if not vw.isOpened():
        pytest.skip("this OpenCV build writes no MPEG-2 transport stream")
    for i in range(60):
        f = np.zeros((120, 160, 3), np.uint8)
        cv2.putText(f, str(i), (10, 80), cv2.FONT_HERSHEY_SIMPLEX, 2, (255, 255, 255), 3)
        vw.write(f)
    vw.release()
    full = [f.image for f in iter_frames(path)]
    assert len(full) == 60
    for start in (1, 5, 13, 29, 44, 59):
        got = next(iter_frames(path, start_frame=start))
        assert got.index == start
        np.testing.assert_array_equal(got.image, full[start])
    assert "not frame-exact" in caplog.text
    assert "variable frame rate:" not in caplog.text  # its stamps start late, at a steady rate


def test_prefetch_gives_the_same_frames(video):
    a = list(iter_frames(video, stride=2))
    b = list(iter_frames(video, stride=2, prefetch=3))
    assert [f.index for f in a] == [f.index for f in b]
    assert all(np.array_equal(x.image, y.image) for x, y in zip(a, b, strict=True))


def test_prefetch_consumer_can_stop_early(video):
    it = iter_frames(video, prefetch=2)
    assert next(it).index == 0
    it.close()  # must not hang on the decode thread


def test_missing_and_garbage_files_name_the_file(tmp_path):
    with pytest.raises(VideoError, match="video .*nope.mp4: file not found"):
        probe_video(tmp_path / "nope.mp4")
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(np.random.default_rng(0).bytes(4000))
    with pytest.raises(VideoError, match="junk.mp4: OpenCV cannot open it"):
        list(iter_frames(junk))
    empty = tmp_path / "empty.mp4"  # was "cannot open it (not a video, truncated, ...)"
    empty.write_bytes(b"")
    with pytest.raises(VideoError, match="empty.mp4: the file is empty"):
        probe_video(empty)
    with pytest.raises(VideoError, match="a folder, not a video file"):  # was "file not found"
        probe_video(tmp_path)


def test_truncated_file_raises_after_the_good_frames(video, tmp_path):
    cut = tmp_path / "cut.avi"
    data = video.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    seen = []
    with pytest.raises(
        VideoTruncatedError, match=r"cut.avi: decoding failed at frame \d+ of 30"
    ) as err:
        for f in iter_frames(cut):
            seen.append(f.index)
    assert 5 < len(seen) < N and err.value.frame == len(seen)
    assert seen == list(range(len(seen)))


def test_frame_range_validation(video):
    info = probe_video(video)
    assert frame_range(info, None, None) == (0, N)
    assert frame_range(info, 1.0, 100.0) == (10, N)
    with pytest.raises(ValueError, match="must be after start"):
        frame_range(info, 2.0, 1.0)
    # math.ceil's bare "cannot convert float NaN to integer" named neither the video nor the bound
    with pytest.raises(ValueError, match="start must be a finite number of seconds.*got nan"):
        frame_range(info, float("nan"), None)
    with pytest.raises(ValueError, match="end must be a finite number of seconds.*got inf"):
        frame_range(info, None, float("inf"))
    with pytest.raises(ValueError, match="stride must be >= 1"):
        iter_frames(video, stride=0)


@pytest.mark.parametrize("stride", [2, 3, 4])
def test_truncated_file_raises_with_a_stride_too(video, tmp_path, stride):
    """With stride > 1 a damaged frame that falls on a skipped one (grabbed, not read) ended the
    stream silently, so a truncated video tracked with `stride: 2` gave a file that looked
    complete. Every cut point now raises, after the good frames."""
    data = video.read_bytes()
    for frac in np.linspace(0.4, 0.6, 9):
        cut = tmp_path / f"cut{frac:.3f}.avi"
        cut.write_bytes(data[: int(len(data) * frac)])
        seen = []
        with pytest.raises(VideoTruncatedError, match="of 30 announced") as err:
            for f in iter_frames(cut, stride=stride):
                seen.append(f.index)
        assert seen == list(range(0, len(seen) * stride, stride))
        assert seen[-1] < err.value.frame <= seen[-1] + stride


def test_a_start_past_the_end_is_an_error(video):
    """start_s beyond the video gave an empty frame range, and `track` an empty, finished file."""
    info = probe_video(video)
    with pytest.raises(VideoError, match=r"start 30.0 s is at or past the end .*30 frames, 3.000"):
        frame_range(info, 30.0, None)
    with pytest.raises(VideoError, match="past the end"):
        list(iter_frames(video, start_s=3.0))
    assert frame_range(info, 2.9, None) == (29, N)


def _mp4_boxes(buf: bytes, start: int, end: int):
    """(offset, size, type) of the ISO-BMFF boxes in buf[start:end]."""
    import struct

    i = start
    while i + 8 <= end:
        size, kind = struct.unpack_from(">I4s", buf, i)
        if size < 8:
            return
        yield i, size, kind.decode("latin-1")
        i += size


def write_variable_rate_mp4(path, n=48, fps=30.0, fast_from=24, size=(160, 120)):
    """An MPEG-4 file whose frames from `fast_from` on come twice as fast (as a phone that
    records at a variable rate writes them): OpenCV's writer makes a constant-rate file, and
    its sample-time table (moov/trak/mdia/minf/stbl/stts, one entry) gets a second entry. The
    moov box follows the media data, so no chunk offset moves."""
    import struct

    w, h = size
    vw = cv2.VideoWriter(str(path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    for k in range(n):
        img = np.zeros((h, w, 3), np.uint8)
        img[:, (3 * k) % w] = 255
        vw.write(img)
    vw.release()
    buf = bytearray(path.read_bytes())
    parents, start, end = [], 0, len(buf)
    for name in ("moov", "trak", "mdia", "minf", "stbl", "stts"):
        at, size_ = next((i, s) for i, s, kind in _mp4_boxes(buf, start, end) if kind == name)
        parents.append(at)
        start, end = at + 8, at + size_
    stts = parents.pop()
    count, delta = struct.unpack_from(">II", buf, stts + 16)
    assert struct.unpack_from(">I", buf, stts + 12)[0] == 1 and count == n
    body = struct.pack(">IIIIII", 0, 2, fast_from, delta, n - fast_from, delta // 2)
    new = struct.pack(">I4s", 8 + len(body), b"stts") + body
    old_size = struct.unpack_from(">I", buf, stts)[0]
    buf[stts : stts + old_size] = new
    for at in parents:  # every box around it grows as much
        struct.pack_into(">I", buf, at, struct.unpack_from(">I", buf, at)[0] + len(new) - old_size)
    path.write_bytes(bytes(buf))
    return path


def test_a_variable_frame_rate_is_named_once(tmp_path, video, caplog):
    """Times are frame / fps at the container's mean rate; a variable-rate file (phones) got
    times off by up to the ratio of its rates, and speeds with them, without a word."""
    vfr = write_variable_rate_mp4(tmp_path / "phone.mp4")
    assert probe_video(vfr).fps == pytest.approx(40.0)  # 48 frames in 1.2 s: the mean
    assert len(list(iter_frames(vfr))) == 48
    warnings = [r.getMessage() for r in caplog.records if "variable frame rate:" in r.getMessage()]
    assert len(warnings) == 1 and "phone.mp4" in warnings[0], warnings
    caplog.clear()
    steady = write_variable_rate_mp4(tmp_path / "steady.mp4", fast_from=48)  # one rate
    assert len(list(iter_frames(steady))) + len(list(iter_frames(video, stride=3))) == 58
    assert "variable frame rate:" not in caplog.text


def test_an_animated_gif_is_a_video_and_a_still_one_an_image(tmp_path):
    """An animated GIF (FFmpeg reads its frames) was refused as "a still image" because OpenCV
    has an image reader for GIF; a one-frame GIF or PNG still is one."""
    from PIL import Image

    from gst.video import still_image_error

    rng = np.random.default_rng(0)
    frames = [Image.fromarray(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)) for _ in range(6)]
    frames[0].save(tmp_path / "anim.gif", save_all=True, append_images=frames[1:], duration=40)
    frames[0].save(tmp_path / "still.gif")
    frames[0].save(tmp_path / "still.png")
    assert still_image_error(tmp_path / "anim.gif") is None
    assert probe_video(tmp_path / "anim.gif").frame_count == 6
    for still in ("still.gif", "still.png"):
        assert "a still image, not a video" in still_image_error(tmp_path / still)

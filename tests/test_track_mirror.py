"""Left/right landmark labels kept continuous in time (gst.track.mirror): BlazePose's whole-body
flips undone on walking and turning stick figures, nothing exchanged where nothing flipped."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.body.markers import BLAZEPOSE_MIRROR
from gst.track.detection import Detection
from gst.track.mirror import LabelSmoother, MirrorConfig, node_state, step_costs
from gst.track.read import column_array, read_tracks

FPS = 30.0
# BlazePose indices: (left, right) of shoulders, elbows, wrists, hips, knees, ankles
SHOULDER, ELBOW, WRIST = (11, 12), (13, 14), (15, 16)
HIP, KNEE, ANKLE = (23, 24), (25, 26), (27, 28)


def figure(
    t: float, heading_deg: float, x0: float = 0.0, speed: float = 1.2, reach: float = 0.24
) -> np.ndarray:
    """(33, 3) landmarks of a walking stick figure (metres: x lateral of the body, y up, z
    forward), turned by `heading_deg` about the vertical, walking along its own forward axis,
    seen by a pinhole camera 6 m away (1000 px focal); confidence 1. `reach`: how far out to
    the side the wrists are (elbows half way)."""
    phase = 2 * np.pi * 0.9 * t  # strides per second
    swing = 0.35 * np.sin(phase)
    pts = np.zeros((33, 3))
    pts[:] = (0.0, 1.6, 0.05)  # face and hands: near the head / wrists below
    for side, sign in ((0, 1.0), (1, -1.0)):  # left is +x in the body frame
        leg = swing if side == 0 else -swing
        arm = -0.6 * leg
        pts[SHOULDER[side]] = (0.18 * sign, 1.45, 0.0)
        pts[ELBOW[side]] = ((0.18 + (reach - 0.18) / 2 + 0.01) * sign, 1.15, 0.5 * arm)
        pts[WRIST[side]] = (reach * sign, 0.9, arm)
        pts[HIP[side]] = (0.1 * sign, 0.95, 0.0)
        pts[KNEE[side]] = (0.11 * sign, 0.5, 0.5 * leg)
        pts[ANKLE[side]] = (0.11 * sign, 0.08, leg)
    h = np.radians(heading_deg)
    rot = np.array([[np.cos(h), 0, np.sin(h)], [0, 1, 0], [-np.sin(h), 0, np.cos(h)]])
    world = pts @ rot.T + np.array([x0, 0, 0]) + rot[:, 2] * speed * t
    cam = world * [1, -1, 1] + [0, 1.0, 6.0]  # camera 6 m in front, y down
    uv = 1000 * cam[:, :2] / cam[:, 2:] + [960, 540]
    return np.c_[uv, np.ones(33)].astype(np.float32)


def run(frames, config=None) -> list[list[np.ndarray | None]]:
    """The frames' landmarks (per frame, per person) through a LabelSmoother, exchanged where
    it decides; every frame comes back once, in order."""
    smoother = LabelSmoother(config or MirrorConfig(), 1 / FPS)
    out = []
    for i, people in enumerate(frames):
        out += smoother.push(i, people)
    out += smoother.flush()
    assert [i for i, _ in out] == list(range(len(frames)))
    return [
        [lm[BLAZEPOSE_MIRROR] if flag else lm for lm, flag in zip(frames[i], flags, strict=True)]
        for i, flags in out
    ]


def walk(n: int, heading_deg: float, **kw) -> list[np.ndarray]:
    return [figure(i / FPS, heading_deg, **kw) for i in range(n)]


def flipped(lms: list[np.ndarray], frames) -> list[np.ndarray]:
    return [lm[BLAZEPOSE_MIRROR] if i in frames else lm for i, lm in enumerate(lms)]


@pytest.mark.parametrize("heading", [20.0, 60.0, 150.0])
@pytest.mark.parametrize("bad", [range(20, 30), [7], [7, 8, 40]])
def test_a_flipped_run_is_restored(heading, bad):
    truth = walk(60, heading)
    got = run([[lm] for lm in flipped(truth, set(bad))])
    for i, (lm,) in enumerate(got):
        np.testing.assert_array_equal(lm, truth[i], err_msg=f"frame {i}")


def test_without_the_smoother_the_flips_stay():
    """The check can fail: the flipped frames differ from the truth until undone."""
    truth = walk(40, 30.0)
    bad = flipped(truth, {10, 11, 12})
    assert not np.array_equal(bad[11], truth[11])
    got = run([[lm] for lm in bad])
    assert np.array_equal(got[11][0], truth[11])


def test_a_person_turning_around_keeps_their_labels():
    """A full turn in 2 s (left and right cross in the image twice): nothing is exchanged."""
    truth = [figure(i / FPS, 360.0 * i / 60, speed=0.3) for i in range(60)]
    got = run([[lm] for lm in truth])
    for i, (lm,) in enumerate(got):
        np.testing.assert_array_equal(lm, truth[i], err_msg=f"frame {i}")


@pytest.mark.parametrize("reach", [0.24, 0.9])
def test_a_quick_real_turn_between_two_processed_frames_keeps_the_labels(reach):
    """A person turning round between two processed frames (stride > 1, or missed frames) jumps
    like a flip; with arms spread (reach 0.9 m) the smoother kept the labels exchanged from the
    turn to the end of the video (every left angle a right one), as staying exchanged cost less
    within its look-ahead than jumping back."""
    truth = [figure(i / FPS, 0.0 if i < 45 else 180.0, speed=0.0, reach=reach) for i in range(120)]
    for config in (MirrorConfig(), MirrorConfig(lag_s=0.5)):  # the jump back alone, too
        got = run([[lm] for lm in truth], config)
        exchanged = [i for i, (lm,) in enumerate(got) if not np.array_equal(lm, truth[i])]
        assert exchanged == [], config


def test_a_track_that_starts_flipped_keeps_the_detected_labels_when_they_never_change():
    """No jump, no evidence: the landmark model's labels stand (the prior)."""
    truth = walk(30, 40.0)
    mirrored_all = [lm[BLAZEPOSE_MIRROR] for lm in truth]
    got = run([[lm] for lm in mirrored_all])
    for i, (lm,) in enumerate(got):
        np.testing.assert_array_equal(lm, mirrored_all[i])


def test_two_people_only_the_flipped_one_is_corrected():
    a = walk(50, 30.0, x0=-1.5)
    b = walk(50, -30.0, x0=1.5)
    got = run([[la, lb] for la, lb in zip(flipped(a, {15, 16, 17}), b, strict=True)])
    for i, (la, lb) in enumerate(got):
        np.testing.assert_array_equal(la, a[i], err_msg=f"frame {i}")
        np.testing.assert_array_equal(lb, b[i], err_msg=f"frame {i}")


def test_unsure_landmarks_carry_no_evidence():
    truth = walk(30, 30.0)
    unsure = [lm.copy() for lm in truth]
    for lm in unsure:
        lm[:, 2] = 0.2
    got = run([[lm] for lm in flipped(unsure, {10, 11})])
    # nothing could be compared, so nothing was exchanged: frames 10 and 11 stay as detected
    np.testing.assert_array_equal(got[10][0], unsure[10][BLAZEPOSE_MIRROR])
    np.testing.assert_array_equal(got[12][0], unsure[12])


def test_landmarks_without_a_position_are_not_compared():
    """A sure wrist with no position (NaN) is left out of the comparison: the flips around it
    are still undone, and the NaN stays where it was."""
    truth = walk(40, 30.0)
    for lm in truth[18:22]:
        lm[15, :2] = np.nan
    got = run([[lm] for lm in flipped(truth, {19, 20})])
    for i, (lm,) in enumerate(got):
        np.testing.assert_array_equal(lm, truth[i], err_msg=f"frame {i}")


@pytest.mark.parametrize("n_flip", [15, 20])
def test_a_frame_without_shoulders_neither_cuts_the_chain_nor_hides_the_next_flip(n_flip):
    """Shoulders without a position (NaN) in one frame: its torso length was NaN, so nothing
    linked to it (the person's chain restarted) and its step to the next frame carried no
    evidence; a flip starting right after it (half a second or more) stayed exchanged."""
    truth = walk(60, 30.0)
    truth[22][[SHOULDER[0], SHOULDER[1]], :2] = np.nan
    got = run([[lm] for lm in flipped(truth, set(range(23, 23 + n_flip)))])
    for i, (lm,) in enumerate(got):
        np.testing.assert_array_equal(lm, truth[i], err_msg=f"frame {i}")


def test_people_without_landmarks_and_short_streams_pass_unchanged():
    smoother = LabelSmoother(MirrorConfig(), 1 / FPS)
    lm = walk(1, 0.0)[0]
    for i, people in enumerate([[None], [None, lm], []]):
        assert smoother.push(i, people) == []  # fewer frames than the lag's 15
    assert smoother.flush() == [(0, [False]), (1, [False, False]), (2, [])]


def test_frames_wait_for_the_lag_and_flush_lets_them_all_out():
    """At 30 fps a 0.5 s lag holds 15 frames: the first leaves with the 16th; `flush` (the
    video's end, or a damaged video before its error is raised) decides the rest."""
    truth = walk(20, 30.0)
    smoother = LabelSmoother(MirrorConfig(lag_s=0.5), 1 / FPS)
    released = [len(smoother.push(i, [lm])) for i, lm in enumerate(truth)]
    assert released == [0] * 15 + [1] * 5
    assert [i for i, _ in smoother.flush()] == list(range(5, 20))
    with pytest.raises(ValueError, match="frame interval"):
        LabelSmoother(MirrorConfig(), 0.0)


def test_step_costs_are_symmetric_under_exchange_and_blind_to_translation():
    a, b = walk(2, 30.0)
    c = MirrorConfig()
    kept, exchanged = step_costs(a, b, c)
    assert kept < exchanged
    assert step_costs(a, b[BLAZEPOSE_MIRROR], c) == pytest.approx((exchanged, kept), rel=1e-5)
    moved = b.copy()
    moved[:, :2] += (250.0, -40.0)
    assert step_costs(a, moved, c) == pytest.approx((kept, exchanged), rel=1e-5)


@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(
        st.tuples(st.floats(0, 1), st.floats(0, 1)).map(lambda p: (min(p), max(p))),
        min_size=1,
        max_size=20,
    ),
    prior=st.floats(0.01, 5.0),
    start=st.sampled_from([None, 0]),
)
def test_no_evidence_of_a_jump_never_exchanges(steps, prior, start):
    """Where every step is at least as cheap kept as exchanged, the first node stays as detected
    (after a kept node, or free)."""
    assert node_state(start, steps, prior, 0.1) == 0


@given(st.floats(0.01, 1.0), st.integers(1, 10))
def test_a_node_after_an_exchanged_one_follows_it_when_the_step_is_smooth(prior, n):
    """Kept relative to an exchanged predecessor (cost 0) and a clear jump otherwise: exchanged,
    unless the prior over the following nodes outweighs the jump (here it never does)."""
    steps = [(0.0, 1.0)] + [(0.0, 1.0)] * (n - 1)
    assert node_state(1, steps, prior * 0.01, 0.1) == 1


def test_config_rejects_nonsense():
    with pytest.raises(ValueError, match="sigma"):
        MirrorConfig(sigma=0.0)


class FigureDetector:
    """One walking figure per frame, its labels exchanged in `flipped` frames."""

    def __init__(self, flipped):
        self.flipped = set(flipped)

    def detect(self, frame_bgr, frame_index):
        lm = figure(frame_index / FPS, 30.0)
        if frame_index in self.flipped:
            lm = lm[BLAZEPOSE_MIRROR]
        (x0, y0), (x1, y1) = lm[:, :2].min(0) - 20, lm[:, :2].max(0) + 20
        return [Detection(box=np.array([x0, y0, x1, y1]), landmarks=lm)]


@pytest.fixture(scope="module")
def figure_video(tmp_path_factory):
    import cv2

    path = tmp_path_factory.mktemp("mirror") / "walk.avi"
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (1920, 1080))
    for _ in range(30):
        out.write(np.full((1080, 1920, 3), 90, np.uint8))
    out.release()
    return path


@pytest.mark.parametrize("unmirror", [MirrorConfig(), None])
def test_the_track_loop_writes_continuous_labels_and_counts_the_exchanges(
    figure_video, tmp_path, unmirror
):
    from gst.track import BoxDepthPredictor, TrackOptions, column_array, read_tracks, track_video
    from gst.track.read import read_metadata

    flipped = {10, 11, 12, 13}
    res = track_video(
        figure_video,
        tmp_path / "out",
        FigureDetector(flipped),
        BoxDepthPredictor(),
        model={"name": "box-depth", "version": "test"},
        options=TrackOptions(unmirror=unmirror),
        resume=False,
    )
    table = read_tracks(res.path)
    frames = table.column("frame").to_numpy()
    got = column_array(table, "landmarks2d")
    exchanged = read_metadata(res.path)["stats"]["landmarks_exchanged"]
    assert flipped <= set(frames.tolist())
    for f, lm in zip(frames, got, strict=True):
        truth = figure(f / FPS, 30.0)
        if unmirror is None and f in flipped:
            truth = truth[BLAZEPOSE_MIRROR]
        np.testing.assert_allclose(lm, truth[:, :2], atol=1e-3, err_msg=f"frame {f}")
    assert exchanged == (len(flipped) if unmirror else 0)


@pytest.mark.parametrize("flip, crash", [((20, 28), 3), ((50, 58), 6)])
def test_a_resumed_run_decides_left_and_right_as_the_uninterrupted_one(tmp_path, flip, crash):
    """The smoother's state is saved with each committed group: a flip that starts at the frame
    a resumed run starts from is still seen as a jump (before: a cold smoother kept frames
    20-27 exchanged, and the bytes differed). In the last frames, which the smoother lets out
    together at the end, the exchanges are counted once (the committed stats held those of
    frames not yet committed, and a resume counted them again)."""
    import cv2

    from gst.track import BoxDepthPredictor, TrackOptions, track_video

    path = tmp_path / "walk.avi"
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (1920, 1080))
    for _ in range(60):
        out.write(np.full((1080, 1920, 3), 90, np.uint8))
    out.release()

    class FailsOnce(BoxDepthPredictor):
        calls = 0

        def __call__(self, crops, K):
            FailsOnce.calls += 1
            if FailsOnce.calls == crash:  # one call per group of 10 frames
                raise RuntimeError("killed")
            return super().__call__(crops, K)

    opts = TrackOptions(frames_per_group=10, prefetch=0)
    model = {"name": "box-depth", "version": "test"}
    flipped = FigureDetector(range(*flip))
    ref = track_video(path, tmp_path / "ref", flipped, BoxDepthPredictor(), model=model,
                      options=opts, resume=False)  # fmt: skip
    with pytest.raises(RuntimeError, match="killed"):
        track_video(path, tmp_path / "res", flipped, FailsOnce(), model=model, options=opts)
    res = track_video(path, tmp_path / "res", flipped, BoxDepthPredictor(), model=model,
                      options=opts)  # fmt: skip
    assert res.resumed_from_frame == 10 * (crash - 1)
    assert res.path.read_bytes() == ref.path.read_bytes()
    lm = column_array(read_tracks(res.path), "landmarks2d")
    truth = np.stack([figure(f / FPS, 30.0)[:, :2] for f in range(60)])
    np.testing.assert_allclose(lm, truth, atol=1e-3)  # every frame's labels put right


@settings(max_examples=10, deadline=None)
@given(cut=st.integers(0, 58), flip_start=st.integers(0, 50), gone=st.integers(0, 59))
def test_a_smoother_restarted_from_a_frames_state_decides_the_rest_alike(cut, flip_start, gone):
    """Two people, one flipped for a while, the other missing for a few frames: a smoother
    loaded with the state that came with frame `cut` decides frames cut+1.. exactly as the
    smoother that saw everything."""
    a, b = walk(60, 30.0), walk(60, -60.0, x0=1.5)
    frames = []
    for i in range(60):
        la = a[i][BLAZEPOSE_MIRROR] if flip_start <= i < flip_start + 9 else a[i]
        frames.append([la] + ([] if gone <= i < gone + 3 else [b[i]]))
    whole = LabelSmoother(MirrorConfig(), 1 / FPS, with_state=True)
    out = [x for i, p in enumerate(frames) for x in whole.push(i, p)] + whole.flush()
    state = json.loads(json.dumps(out[cut][2]))  # as it is saved
    again = LabelSmoother(MirrorConfig(), 1 / FPS, with_state=True)
    again.load_state_dict(state)
    rest = [x for i in range(cut + 1, 60) for x in again.push(i, frames[i])] + again.flush()
    assert [(i, f) for i, f, _ in rest] == [(i, f) for i, f, _ in out[cut + 1 :]]
    assert [s for *_, s in rest] == [s for *_, s in out[cut + 1 :]]

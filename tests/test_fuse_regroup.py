"""Regrouping crops into people by 3D agreement (gst.fuse.regroup): extraction ids exchanged for
a few frames and a crop that shows the other person come out as two clean tracks."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from crowd_people import walker_observations

from gst.body import load_body_model
from gst.fuse.regroup import regroup_people
from tests.fuse_fixtures import make_capture, observations

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def capture():
    # two people 1.4 m apart, walking; 6 cameras
    return make_capture(load_body_model("anny"), n_people=2, n_frames=8, n_cams=6, seed=4)


def _source(obs, clean):
    """Per (frame, camera) of obs: which clean person (0/1) its landmarks equal, -1 if none."""
    out = np.full(obs.rows.shape, -1)
    for k, c in enumerate(clean):
        fi = np.searchsorted(c.frames, obs.frames)
        same = np.isclose(obs.uv, c.uv[fi]).all((-1, -2)) & (obs.rows >= 0)
        out[same] = k
    return out


def test_exchanged_ids_and_a_wrong_crop_are_regrouped(capture):
    clean = observations(capture, noise_px=1.0, seed=3)
    a, b = observations(capture, noise_px=1.0, seed=3)
    for t in (4, 5):  # the extraction exchanged the two people in frames 4 and 5
        for name in ("uv", "confidence", "rows"):
            x, y = getattr(a, name), getattr(b, name)
            x[t], y[t] = y[t].copy(), x[t].copy()
    # frame 1, camera 2: person 1's crop shows person 2 (a noisier detection than person 2's own)
    a.uv[1, 2] = clean[1].uv[1, 2] + np.random.default_rng(0).normal(0, 3.0, (33, 2))
    a.rows[1, 2] = 999
    people, rep = regroup_people([a, b])
    assert rep.tracks == 2
    for track in people:
        src = _source(track, clean)
        kinds = set(src[(track.rows >= 0) & (track.rows != 999)].tolist())
        assert len(kinds) == 1 and -1 not in kinds, kinds  # one person per track, every crop
        assert track.frames.tolist() == list(range(8))
    # the wrong crop went to person 2's track, which keeps one crop per camera (its own):
    # person 1 has 5 views in frame 1, everything else has 6
    views = {k: (t.rows >= 0).sum(1) for t in people for k in {int(_source(t, clean).max())}}
    assert views[0].tolist() == [6, 5, 6, 6, 6, 6, 6, 6] and (views[1] == 6).all()
    assert 999 not in np.concatenate([t.rows.ravel() for t in people])


def test_the_tracks_gates_are_in_time_not_frames(capture):
    """The same capture filmed at twice the rate (frame numbers doubled, 60 fps) regroups as at
    30 fps: the gates were 0.3 m per frame and 15 frames whatever the rate (18 m/s and 0.25 s
    at 60 fps, 7.5 m/s, below a sprinter, at 25 fps)."""
    from dataclasses import replace

    people = observations(capture, noise_px=1.0, seed=3)
    for t in (4, 5):  # exchanged ids, as above: the gates decide who continues whom
        for name in ("uv", "confidence", "rows"):
            x, y = getattr(people[0], name), getattr(people[1], name)
            x[t], y[t] = y[t].copy(), x[t].copy()
    doubled = [replace(p, frames=2 * p.frames) for p in people]
    at30, rep30 = regroup_people(people, fps=30.0)
    at60, rep60 = regroup_people(doubled, fps=60.0)
    assert rep30.tracks == rep60.tracks == 2 and rep30.moved_crops == rep60.moved_crops
    for a, b in zip(at30, at60, strict=True):
        assert np.array_equal(a.rows, b.rows) and np.array_equal(2 * a.frames, b.frames)


def test_a_dropped_view_keeps_its_landmarks_as_read(monkeypatch):
    """A view the consensus both exchanged (legs read mirrored) and dropped (torso on someone
    else) got its confidences back but kept the exchanged pixels: left/right landmarks and
    their confidences no longer belonged together when it moved to another person."""
    import gst.fuse.regroup as rg
    from gst.fuse.consensus import LIMB_GROUPS, SWAP, ConsensusOptions, view_consensus

    cap = make_capture(load_body_model("anny"), n_people=1, n_frames=1, n_cams=6, seed=3)
    p = observations(cap)[0]
    legs = np.array(LIMB_GROUPS["legs"])
    left_legs = legs[legs % 2 == 1]  # BlazePose: odd = left
    uv, conf = p.uv.copy(), p.confidence.copy()
    uv[0, 0, legs] = p.uv[0, 0, SWAP[legs]]  # view 0 read the legs mirrored...
    uv[0, 0, np.setdiff1d(np.arange(33), legs)] += 80.0  # ...and the rest on someone else
    conf[0, 0, left_legs], conf[0, 0, SWAP[left_legs]] = 0.95, 0.35
    p.uv, p.confidence = uv, conf
    options = ConsensusOptions(temporal_weight=0)
    q, rep = view_consensus(p, options)
    assert rep.dropped[0, 0] and rep.swapped[0, 0].any()  # the case: exchanged and dropped
    monkeypatch.setattr(rg, "view_consensus", lambda obs, o: (q, rep))
    regroup_people([p], rg.RegroupOptions(consensus=options))
    assert np.allclose(q.uv[0, 0], uv[0, 0]) and np.allclose(q.confidence[0, 0], conf[0, 0])


def test_a_landmark_without_pixels_does_not_drop_its_view():
    """A landmark with NaN pixels but a confidence made the view's size NaN (`_extent`), so the
    view matched no skeleton and was dropped from its own person."""
    p = walker_observations()
    p.uv[2, 1, 30] = np.nan
    out, rep = regroup_people([p])
    assert rep.tracks == 1 and (out[0].rows >= 0).all()


@pytest.mark.parametrize("fps", [0.0, -30.0, float("nan")])
def test_a_frame_rate_that_is_no_rate_is_refused(fps):
    with pytest.raises(ValueError, match="fps"):
        regroup_people([walker_observations()], fps=fps)

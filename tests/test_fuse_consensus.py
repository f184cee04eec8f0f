"""View consensus (gst.fuse.consensus): a view showing the other person is dropped, a view with
its legs' left and right exchanged is put right, and clean views are left alone."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from crowd_people import walker_observations

from gst.body import load_body_model
from gst.fuse.consensus import (
    LIMB_GROUPS,
    SWAP,
    ConsensusOptions,
    exchange_groups,
    exchanges_against_body,
    readings_against_body,
    view_consensus,
)
from tests.fuse_fixtures import make_capture, observations

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def capture():
    return make_capture(load_body_model("anny"), n_people=2, n_frames=5, n_cams=6, seed=11)


def test_wrong_person_view_is_dropped_and_swapped_legs_are_put_right(capture):
    people = observations(capture, noise_px=1.0, seed=1)
    clean = [p.uv.copy() for p in people]
    p, other = people[0], people[1]
    p.uv[2, 1] = other.uv[2, 1]  # frame 2, camera 1 shows the other person
    p.uv[3, 4] = other.uv[3, 4]  # frame 3: two wrong views of six
    p.uv[3, 5] = other.uv[3, 5]
    legs = np.array(LIMB_GROUPS["legs"])
    p.uv[4, 2, legs] = clean[0][4, 2, SWAP[legs]]  # frame 4, camera 2: legs exchanged
    out, rep = view_consensus(p, ConsensusOptions())
    expected = np.zeros(rep.dropped.shape, bool)
    expected[2, 1] = expected[3, 4] = expected[3, 5] = True
    np.testing.assert_array_equal(rep.dropped, expected)
    assert (out.confidence[expected] == 0).all()
    assert (out.confidence[~expected] == p.confidence[~expected]).all()
    assert rep.swapped[4, 2, list(LIMB_GROUPS).index("legs")]
    assert rep.swapped.sum() == 1
    np.testing.assert_array_equal(out.uv[4, 2], clean[0][4, 2])
    # clean people pass untouched
    out1, rep1 = view_consensus(people[1], ConsensusOptions())
    assert not rep1.dropped.any() and not rep1.swapped.any()
    np.testing.assert_array_equal(out1.uv, people[1].uv)


def test_too_few_agreeing_views_change_nothing(capture):
    people = observations(capture, noise_px=1.0, seed=2)
    p = people[0]
    p.rows[:, 3:] = -1  # three cameras only
    p.confidence[:, 3:] = 0
    p.uv[:, 3:] = np.nan
    p.uv[1, 0] = people[1].uv[1, 0]  # one of three is wrong: 2 agree < min_agree 3
    _, rep = view_consensus(p, ConsensusOptions(min_agree=3))
    assert not rep.dropped[1].any()
    _, rep = view_consensus(p, ConsensusOptions(min_agree=2))
    assert rep.dropped[1].tolist() == [True, False, False, False, False, False]


def test_fitted_body_settles_an_even_split(capture):
    """Two of four views read the person mirrored (arms and legs in one, the arms in the
    other): the pair hypotheses of view_consensus cannot outvote them (2 against 2), the body
    can. Exactly those groups are flagged; exchanging them restores the clean landmarks."""
    people = observations(capture, noise_px=1.0, seed=3)
    p = people[0]
    p.rows[:, 4:] = -1  # four cameras
    p.confidence[:, 4:] = 0
    p.uv[:, 4:] = np.nan
    clean = p.uv.copy()
    arms = np.array(LIMB_GROUPS["arms"])
    limbs = np.array(LIMB_GROUPS["arms"] + LIMB_GROUPS["legs"])
    p.uv[2, 1, limbs] = clean[2, 1, SWAP[limbs]]  # frame 2, camera 1: arms and legs mirrored
    p.uv[2, 3, arms] = clean[2, 3, SWAP[arms]]  # frame 2, camera 3: the arms
    swap = exchanges_against_body(p, capture.markers[0], ConsensusOptions())
    expected = np.zeros(swap.shape, bool)
    expected[2, 1, [list(LIMB_GROUPS).index("arms"), list(LIMB_GROUPS).index("legs")]] = True
    expected[2, 3, list(LIMB_GROUPS).index("arms")] = True
    np.testing.assert_array_equal(swap, expected)
    fixed = exchange_groups(p, swap)
    np.testing.assert_array_equal(fixed.uv[:, :4], clean[:, :4])
    # a clean person, and a body missing for a frame (NaN markers), exchange nothing
    assert not exchanges_against_body(people[1], capture.markers[1]).any()
    gone = capture.markers[0].copy()
    gone[2] = np.nan
    assert not exchanges_against_body(p, gone)[2].any()


def test_the_fitted_body_chooses_between_two_readings_of_a_view(capture):
    """Two readings of some views (gst.fuse.relook): the view's own one and another. The other
    wins where it lies nearer the body: the views whose own reading showed the other person,
    never a view whose other reading is that person, or one without another reading."""
    people = observations(capture, noise_px=1.0, seed=5)
    p, someone = people[0], people[1]
    clean = p.uv.copy()
    p.uv[1, 2] = someone.uv[1, 2]  # frame 1, camera 2 read the other person
    other = np.full(p.uv.shape[:3] + (3,), np.nan)
    other[1, 2, :, :2] = clean[1, 2]  # ... and its second reading is right
    other[3, 4, :, :2] = someone.uv[3, 4]  # a second reading that is the other person
    other[..., 2] = np.where(np.isfinite(other[..., 0]), 0.9, np.nan)
    choose = readings_against_body(p, other, capture.markers[0], ConsensusOptions())
    expected = np.zeros(choose.shape, bool)
    expected[1, 2] = True
    np.testing.assert_array_equal(choose, expected)
    # a gain below 1 asks for a clearer win: second readings as good as the own ones (other
    # noise) are not taken, the right reading of the view that showed someone else still is
    rng = np.random.default_rng(6)
    again = np.concatenate(
        [clean + rng.normal(0, 1.0, clean.shape), np.full(clean.shape[:3] + (1,), 0.9)], -1
    )
    choose = readings_against_body(p, again, capture.markers[0], gain=0.5)
    np.testing.assert_array_equal(choose, expected)


def test_an_even_split_between_two_people_follows_the_frames_around_it(capture):
    """At frame 2 three of six views show the other person: the pairs cannot tell who is who
    (3 against 3); the person's skeleton at frames 1 and 3 can, so the temporal vote keeps the
    person's own three views and drops the other's."""
    people = observations(capture, noise_px=1.0, seed=4)
    p, other = people[0], people[1]
    wrong = [0, 2, 4]
    p.uv[2, wrong] = other.uv[2, wrong]
    without = view_consensus(p, ConsensusOptions(temporal_weight=0.0))[1]
    _, rep = view_consensus(p, ConsensusOptions(temporal_weight=1.0))
    assert rep.dropped[2].tolist() == [True, False, True, False, True, False]
    assert not rep.dropped[[0, 1, 3, 4]].any()
    # without the vote the even split is decided by the errors alone: here for the other person
    assert without.dropped[2].tolist() == [False, True, False, True, False, True]


@pytest.mark.parametrize("collapse", ["pixels", "scale"])
def test_a_view_of_no_size_is_dropped_without_numpy_warnings(collapse):
    """A view whose landmarks all lie on one pixel (or whose crop scale is 0) has a size and so
    an agreement limit of 0: its error over that limit was computed for every hypothesis
    (divide by zero / invalid value) although only agreeing views' are used."""
    p = walker_observations()
    if collapse == "pixels":
        p.uv[1, 2] = 100.0
    else:
        p.px_scale[1, 2] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, rep = view_consensus(p, ConsensusOptions())
    assert rep.dropped[1].tolist() == [False, False, True, False, False]
    assert not rep.dropped[[0, 2, 3, 4]].any()

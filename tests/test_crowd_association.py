"""Keypoint association across calibrated cameras (gst.data.keypoints): people 0.3 m apart
stay two, a person one camera sees keeps a single-view group, groups are cycle-consistent,
ids survive two players crossing, and bad input is refused or skipped, never a crash."""

import numpy as np
import pytest
from crowd_people import instances, person, rig
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gst.data.keypoints import (
    MIRROR,
    AssociationError,
    FrameMatch,
    InstanceError,
    MatchConfig,
    PersonGroup,
    PersonIdTracker,
    PersonInstance,
    TrackerConfig,
    match_frame,
)

RIG = rig("dome", 7)
RIG5 = rig("dome", 5, seed=1)  # the tracking tests: fewer cameras, faster


def consistent(match: FrameMatch, found: dict) -> bool:
    """Every instance in exactly one group, at most one instance per camera in a group."""
    seen = set()
    for g in match.groups:
        for cam, k in g.views.items():
            if (cam, k) in seen:
                return False
            seen.add((cam, k))
    return seen == {(c, k) for c, lst in found.items() for k in range(len(lst))}


def pure(match: FrameMatch, truth: dict) -> bool:
    """Each group holds one person only, and each person is one group."""
    owners = [{truth[c][k] for c, k in g.views.items()} for g in match.groups]
    people = [next(iter(o)) for o in owners if len(o) == 1]
    return all(len(o) == 1 for o in owners) and len(people) == len(set(people))


def test_purity_check_catches_a_swapped_view():
    """The checks the tests rely on fail on a corrupted answer (they can fail)."""
    found, truth = instances(RIG, [person(0, 0), person(0.3, 0)], noise_px=1.0, seed=1)
    m = match_frame(found, RIG)
    assert consistent(m, found) and pure(m, truth)
    g0, g1 = m.groups[0], m.groups[1]
    cam = next(c for c in g0.views if c in g1.views)
    swapped = [
        PersonGroup({**g0.views, cam: g1.views[cam]}, g0.skeleton, g0.errors, g0.mirrored),
        PersonGroup({**g1.views, cam: g0.views[cam]}, g1.skeleton, g1.errors, g1.mirrored),
    ]
    assert not pure(FrameMatch(swapped), truth)
    doubled = [PersonGroup({**g0.views}, None, {}, {}), *m.groups]
    assert not consistent(FrameMatch(doubled), found)


@pytest.mark.parametrize("heading", [0.0, np.pi / 2, 1.0])
def test_two_people_0_3_m_apart_stay_two(heading):
    """Side by side, one behind the other and diagonal: 0.3 m between their centres."""
    off = 0.3 * np.array([np.cos(heading), np.sin(heading)])
    people = [person(0, 0, 0.4), person(off[0], off[1], 2.5)]
    found, truth = instances(RIG, people, noise_px=1.5, dropout=0.1, seed=2)
    m = match_frame(found, RIG)
    assert consistent(m, found) and pure(m, truth)
    multi = [g for g in m.groups if not g.single_view]
    assert len(multi) == 2
    assert all(len(g.views) >= 5 for g in multi)
    # Each skeleton is its own person's, not a blend of the two.
    for g in multi:
        k = truth[next(iter(g.views))][next(iter(g.views.values()))]
        err = np.linalg.norm(g.skeleton - people[k], axis=1)
        assert np.nanmedian(err) < 0.03


def test_people_are_matched_in_a_world_of_any_up_axis_and_floor(caplog):
    """Heights were read as world z with the floor at 0: the same cameras and pixels in a y-up
    world lost 1 of 3 people, with the floor at 3.6 m all 3, in a camera's own frame 2 (they
    fell apart into single-view groups). Heights go along the rig's up; where the floor is
    evidently not at height 0 (a camera at or below it) they are not checked, and it is said."""
    from gst.data.keypoints.people import CrowdTracker

    people = [person(0, 0, 0.3), person(0.6, 0.2, 2.0), person(-0.5, 0.5, 1.0)]
    found, _ = instances(RIG5, people, noise_px=1.0, seed=1)
    y_up = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float)
    cam0 = RIG5.cameras[0]
    worlds = {
        "z-up": RIG5,
        "y-up": RIG5.transformed(y_up, np.zeros(3)),
        "floor at 3.6 m": RIG5.transformed(np.eye(3), np.array([0, 0, 3.6])),
        "camera 0's frame": RIG5.transformed(cam0.R, cam0.t),  # up carried over by R
    }
    for name, world in worlds.items():
        m = match_frame(found, world)
        assert sum(not g.single_view for g in m.groups) == 3, name
    with caplog.at_level("WARNING", logger="gst.data"):
        CrowdTracker(worlds["floor at 3.6 m"], 1 / 30)
    assert "the floor is not at height 0 there" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="gst.data"):
        CrowdTracker(worlds["y-up"], 1 / 30)
    assert not caplog.text


def test_noiseless_skeleton_is_exact():
    people = [person(0.2, -0.1, 1.0)]
    found, _ = instances(RIG, people)
    (g,) = match_frame(found, RIG).groups
    np.testing.assert_allclose(g.skeleton, people[0], atol=1e-6)


def test_a_person_one_camera_sees_keeps_a_single_view_group():
    only = RIG.names[3]
    people = [person(0, 0), person(0.6, 0.2), person(-0.5, 0.4)]
    found, truth = instances(RIG, people, noise_px=1.0, seed=3, cameras={2: [only]})
    m = match_frame(found, RIG)
    assert consistent(m, found) and pure(m, truth)
    single = [g for g in m.groups if g.single_view]
    assert len(single) == 1 and list(single[0].views) == [only]
    assert truth[only][single[0].views[only]] == 2 and single[0].skeleton is None
    assert sum(not g.single_view for g in m.groups) == 2


# Derandomized: about 1 % of random crowds hit the known swap below, so a random draw would make
# CI fail by chance; the draw is the same on every run and the known case is its own test.
@settings(
    max_examples=12, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
@given(
    n=st.integers(3, 5),
    seed=st.integers(0, 10_000),
    noise=st.floats(0.0, 2.0),
)
def test_crowds_are_grouped_consistently_and_purely(n, seed, noise):
    """Random crowds (centres >= 0.35 m apart, random headings), all cameras at once: a
    partition of the instances (cycle-consistent: A~B and B~C put A, B, C in one group) in
    which every group is one person."""
    _check_crowd(n, seed, noise)


@pytest.mark.xfail(
    strict=True,
    reason="known: in one camera two people 0.5 m apart each fit the other's instance and a "
    "third, nearer person fits both loosely; the depth-order penalty of the per-camera "
    "assignment then swaps the two views (about 1 % of random crowds: 3 of 300 on seeds "
    "1000-1099). A fix that asks the nearer person to fit about as well removed these but "
    "lowered association on the rendered crowd scenes, so it is not in",
)
def test_known_swap_when_a_nearer_person_fits_two_instances_loosely():
    _check_crowd(5, 577, 1.0)


def _check_crowd(n: int, seed: int, noise: float) -> None:
    rng = np.random.default_rng(seed)
    centres = []
    while len(centres) < n:
        c = rng.uniform(-0.8, 0.8, 2)
        if all(np.linalg.norm(c - o) >= 0.35 for o in centres):
            centres.append(c)
    people = [person(x, y, rng.uniform(-np.pi, np.pi)) for x, y in centres]
    found, truth = instances(RIG, people, noise_px=noise, dropout=0.1, seed=seed)
    m = match_frame(found, RIG)
    assert consistent(m, found)
    assert pure(m, truth)
    assert sum(not g.single_view for g in m.groups) == n


def test_a_mirrored_view_still_joins_its_person():
    """One camera's detector swapped the left and right of a person seen from behind."""
    people = [person(0, 0, 0.3), person(0.45, 0.1, 2.0)]
    found, truth = instances(RIG, people, noise_px=1.0, seed=4)
    cam = RIG.names[2]
    k = truth[cam].index(0)
    lm = found[cam][k].landmarks[MIRROR]
    found[cam][k] = PersonInstance.create(lm, found[cam][k].box)
    m = match_frame(found, RIG)
    assert pure(m, truth)
    g = m.groups[m.group_of(cam, k)]
    assert g.mirrored[cam] and len(g.views) == 7
    assert not any(v for c, v in g.mirrored.items() if c != cam)


def _walk(frames: int, gap: range) -> tuple[list, list]:
    """Two players walking towards each other along x, passing 0.3 m apart, plus one who
    stands; during `gap` nobody is detected (both hidden while they cross)."""
    out, truths = [], []
    for f in range(frames):
        x = -1.0 + 2.0 * f / (frames - 1)
        people = [person(x, 0.0, 0.0), person(-x, 0.3, np.pi), person(0.2, -0.8, 1.5)]
        if f in gap:
            out.append({c: [] for c in RIG5.names})
            truths.append({c: [] for c in RIG5.names})
            continue
        found, truth = instances(RIG5, people, noise_px=1.5, dropout=0.1, seed=f)
        out.append(found)
        truths.append(truth)
    return out, truths


@pytest.mark.parametrize("gap", [range(0), range(8, 12), range(7, 13)])
def test_ids_stay_with_players_who_cross(gap):
    """20 frames at 30 fps (3 m/s each), crossing at frame 10; with a 4- or 6-frame hole in
    the detections right at the crossing the constant-velocity model carries them through."""
    frames, truths = _walk(20, gap)
    tracker = PersonIdTracker(RIG5, 1 / 30)
    by_person: dict[int, set] = {}
    for f, (found, truth) in enumerate(zip(frames, truths, strict=True)):
        m = match_frame(found, RIG5)
        ids = tracker.update(f, m, found)
        assert len(ids) == len(m.groups) and len(set(ids)) == len(ids)
        for g, pid in zip(m.groups, ids, strict=True):
            for cam, k in g.views.items():
                by_person.setdefault(truth[cam][k], set()).add(pid)
    assert {k: len(v) for k, v in by_person.items()} == {0: 1, 1: 1, 2: 1}


def test_tracker_without_motion_model_would_swap():
    """The crossing test can fail: a tracker that forgets velocity (smoothing to zero speed
    by never updating it) swaps the two players across the hole."""
    frames, truths = _walk(20, range(7, 13))
    config = TrackerConfig(max_speed=20.0, smoothing=1e-9, velocity_time=None)
    tracker = PersonIdTracker(RIG5, 1 / 30, config)
    by_person: dict[int, set] = {}
    for f, (found, truth) in enumerate(zip(frames, truths, strict=True)):
        m = match_frame(found, RIG5)
        for g, pid in zip(m.groups, tracker.update(f, m, found), strict=True):
            for cam, k in g.views.items():
                by_person.setdefault(truth[cam][k], set()).add(pid)
    assert by_person[0] != {min(by_person[0])} or by_person[1] != {min(by_person[1])}


def test_bad_input_is_refused_or_skipped():
    people = [person(0, 0), person(0.5, 0)]
    found, truth = instances(RIG, people, noise_px=1.0, seed=5)
    # A camera that sees nobody: skipped with a note, the others still match.
    found[RIG.names[0]] = []
    m = match_frame(found, RIG)
    assert any("nobody" in note for note in m.notes) and pure(m, truth)
    # A frame where the detector finds nobody at all.
    empty = match_frame({c: [] for c in RIG.names}, RIG)
    assert empty.groups == []
    assert PersonIdTracker(RIG, 1 / 30).update(0, empty, {}) == []
    assert match_frame({}, RIG).groups == []
    # Landmarks with NaN: unseen, not poison; an instance of NaN only is a single-view note.
    cam = RIG.names[1]
    lm = found[cam][0].landmarks.copy()
    lm[:10, :2] = np.nan
    found[cam][0] = PersonInstance.create(lm)
    found[cam].append(PersonInstance.create(np.full((33, 3), np.nan)))
    m = match_frame(found, RIG)
    assert all(np.all(np.isfinite(g.skeleton[11:])) for g in m.groups if g.skeleton is not None)
    assert any("fewer than" in note for note in m.notes)
    assert consistent(m, found)
    # Malformed input: clear errors naming what is wrong.
    with pytest.raises(InstanceError, match=r"\(33, 3\)"):
        PersonInstance.create(np.zeros((17, 3)), where="camera c1")
    with pytest.raises(AssociationError, match="not in the rig"):
        match_frame({"nope": []}, RIG)
    with pytest.raises(AssociationError, match="increasing"):
        t = PersonIdTracker(RIG, 1 / 30)
        t.update(3, empty, {})
        t.update(2, empty, {})
    with pytest.raises(AssociationError, match="pair_gap"):
        MatchConfig(pair_gap=0)


def _one_camera_then_all(frames: int, first_multi: int) -> list[tuple[dict, dict]]:
    """Two players in every camera, and a third who stands at the back and is seen by one
    camera only until `first_multi`, by every camera from then on."""
    only = RIG5.names[0]
    out = []
    for f in range(frames):
        people = [person(-0.6, 0.0, 0.0), person(0.6, 0.2, np.pi), person(0.1, -1.0, 1.5)]
        cameras = {2: [only]} if f < first_multi else None
        out.append(instances(RIG5, people, noise_px=1.0, seed=f, cameras=cameras))
    return out


@pytest.mark.parametrize("continuation", [True, False])
def test_a_single_view_person_keeps_their_id_when_a_second_camera_sees_them(continuation):
    """The lab's bystander: one camera shows him for the first frames, then two. His single-view
    id goes on into 3D; without that continuation (the test's own check that it can fail) he
    gets a second id when the second camera starts to see him."""
    tracker = PersonIdTracker(RIG5, 1 / 30)
    if not continuation:
        tracker._continued_single_view = lambda *a: None
    by_person: dict[int, set] = {}
    for f, (found, truth) in enumerate(_one_camera_then_all(10, 5)):
        m = match_frame(found, RIG5)
        ids = tracker.update(f, m, found)
        assert len(set(ids)) == len(ids)
        for g, pid in zip(m.groups, ids, strict=True):
            for cam, k in g.views.items():
                by_person.setdefault(truth[cam][k], set()).add(pid)
    assert len(by_person[0]) == 1 and len(by_person[1]) == 1
    assert (len(by_person[2]) == 1) is continuation


def _priors_of_one_walker(config: TrackerConfig, seen: int, at: int):
    """A tracker fed one person walking +x at 1 m/s for `seen` frames (30 fps), then nobody:
    the person's prior at frame `at`, and their last skeleton."""
    tracker = PersonIdTracker(RIG5, 1 / 30, config)
    last = None
    for f in range(at + 1):
        if f < seen:
            last = person(f / 30, 0.0)
            group = PersonGroup({}, last, {}, {})
            tracker.update(f, FrameMatch([group]), {})
        elif f == at:
            (pid, prior), *others = tracker.predict(f)
            assert not others
            return prior, last
        else:
            tracker.update(f, FrameMatch([]), {})


def test_a_lost_person_is_not_carried_away_by_their_last_velocity():
    """Unseen for 10 frames after walking at 1 m/s, a person's prior moves on at most about
    (a frame + `coast`) x their speed; with the velocity kept for ever it walks on 0.37 m."""
    prior, last = _priors_of_one_walker(TrackerConfig(), seen=20, at=30)
    moved = prior[23:25].mean(0) - last[23:25].mean(0)
    assert 0.1 < moved[0] < 1.0 * (1 / 30 + 0.2) + 0.02
    prior, last = _priors_of_one_walker(TrackerConfig(coast=None), seen=20, at=30)
    assert (prior[23:25].mean(0) - last[23:25].mean(0))[0] > 0.3


def test_swinging_limbs_do_not_read_as_speed():
    """Arms and legs swinging 0.15 m forwards and back on alternate frames: the torso's velocity
    averaged over 0.2 s stays near the walking speed, where the old estimate (the centre of
    every body landmark, half the newest step) wobbles by metres per second."""
    for config, ok in ((TrackerConfig(), True), (TrackerConfig(velocity_time=None), False)):
        errors = []
        for seen in (20, 21):  # a swing each way on the last frame seen
            tracker = PersonIdTracker(RIG5, 1 / 30, config)
            limbs = np.zeros((33, 3))
            limbs[13:23, 0] = limbs[25:33, 0] = 0.15
            for f in range(seen):
                group = PersonGroup({}, person(f / 30, 0.0, pose=limbs * (-1) ** f), {}, {})
                tracker.update(f, FrameMatch([group]), {})
            (track,) = tracker._tracks  # one person all along
            errors.append(np.linalg.norm(track.velocity - [1.0, 0.0, 0.0]))
        assert (max(errors) < 0.35) == ok, (config, errors)


def test_a_remembered_person_left_as_two_single_view_groups_gets_one_id_per_frame():
    """Seen in 3D for four frames, then the matcher leaves the person as a single-view group in
    each of two cameras: one of them takes the remembered id, the other does not (both took it:
    two single-view rows with one id read as a two-view group without a body)."""
    tracker = PersonIdTracker(RIG5, 1 / 30)
    for f in range(4):
        found, _ = instances(RIG5, [person(0.01 * f, 0.0)], noise_px=0.5, seed=f)
        m = match_frame(found, RIG5)
        assert len(tracker.update(f, m, found)) == 1
    found, _ = instances(RIG5, [person(0.04, 0.0)], noise_px=0.5, seed=4)
    a, b = RIG5.names[:2]
    two = {a: found[a], b: found[b]}
    groups = [PersonGroup({a: 0}, None, {}, {}), PersonGroup({b: 0}, None, {}, {})]
    ids = tracker.update(4, FrameMatch(groups), two)
    assert len(set(ids)) == 2


def test_an_id_continued_by_its_box_is_not_given_again_by_a_fit_in_another_camera():
    """The order the test above missed: camera a keeps the remembered id by box overlap with its
    previous frame (its landmarks no longer fit), then camera b's single view fits the same
    remembered person by projection. Both took the id (a two-view group without a body)."""
    from gst.data.keypoints import PersonInstance

    tracker = PersonIdTracker(RIG5, 1 / 30)
    for f in range(4):
        found, _ = instances(RIG5, [person(0.01 * f, 0.0)], noise_px=0.5, seed=f)
        tracker.update(f, match_frame(found, RIG5), found)
    a, b = RIG5.names[:2]
    found, _ = instances(RIG5, [person(0.04, 0.0)], noise_px=0.5, seed=4)
    (kept,) = tracker.update(4, FrameMatch([PersonGroup({a: 0}, None, {}, {})]), {a: found[a]})
    later, _ = instances(RIG5, [person(0.05, 0.0)], noise_px=0.5, seed=5)
    off = found[a][0].landmarks.copy()
    off[:, :2] += np.random.default_rng(0).normal(0, 40, (33, 2))  # no longer fits
    groups = [PersonGroup({a: 0}, None, {}, {}), PersonGroup({b: 0}, None, {}, {})]
    view_a = [PersonInstance.create(off, found[a][0].box)]
    ids = tracker.update(5, FrameMatch(groups), {a: view_a, b: later[b]})
    assert kept in ids and len(set(ids)) == 2


def test_a_person_one_camera_sees_keeps_their_id_through_a_missed_frame():
    """Only the last frame's single-view boxes were remembered: a person one camera sees, whom
    the detector missed for one frame in four, came back with a new id each time (5 ids of 3
    frames each, all below extraction's min_track_frames, so every crop of them was dropped)."""
    tracker = PersonIdTracker(RIG5, 1 / 30)
    only = RIG5.names[2]
    ids_of_single = []
    for f in range(20):
        people = [person(0, 0, 0.0), person(0.9, 0.6, 2.0)]
        found, truth = instances(
            RIG5, people, noise_px=1.0, seed=f, cameras={1: [only] if f % 4 != 3 else []}
        )
        m = match_frame(found, RIG5)
        for g, pid in zip(m.groups, tracker.update(f, m, found), strict=True):
            cam, k = next(iter(g.views.items()))
            if truth[cam][k] == 1:
                ids_of_single.append(pid)
    assert len(ids_of_single) == 15 and len(set(ids_of_single)) == 1


@pytest.mark.parametrize("box", [(0.0, 0.0, np.inf, np.inf), (0.0, 0.0, 10.0, np.nan)])
def test_a_box_with_nan_or_inf_is_no_box(box):
    """A box with an inf side gave a person an infinite size, so every skeleton fit them with
    error 0 (the two people's views in that camera were exchanged); one with a NaN side took
    the other side's length as their size (10 px: they fit nobody and fell apart)."""
    people = [person(0, 0, 0.4), person(0.3, 0, 2.5)]
    found, truth = instances(RIG, people, noise_px=1.5, seed=2)
    cam = RIG.names[0]
    found[cam] = [PersonInstance.create(i.landmarks, box) for i in found[cam]]
    assert all(np.isnan(i.box).all() and np.isnan(i.scale) for i in found[cam])
    m = match_frame(found, RIG)
    assert consistent(m, found) and pure(m, truth)
    assert len(m.groups) == 2 and all(cam in g.views for g in m.groups)


@pytest.mark.parametrize(
    "field", ["max_speed", "slack", "max_gap", "coast", "velocity_time", "min_front"]
)
def test_a_setting_that_is_nan_is_refused(field):
    """TrackerConfig's checks (`max_speed <= 0`, `coast < 0`...) are False for NaN, which went
    through: a NaN speed gate or velocity time matched nobody, a new id every frame; a NaN
    min_front never found a pair behind a camera impossible."""
    cls = MatchConfig if field == "min_front" else TrackerConfig
    with pytest.raises(AssociationError, match=field):
        cls(**{field: float("nan")})


def test_a_prior_of_another_shape_is_refused_naming_it():
    found, _ = instances(RIG5, [person(0, 0)], noise_px=1.0, seed=1)
    with pytest.raises(AssociationError, match=r"prior 1 has shape \(17, 3\)"):
        match_frame(found, RIG5, priors=[person(0, 0), np.zeros((17, 3))])

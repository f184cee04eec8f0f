"""CrowdTracker: a person the detector misses in one camera is found there again from the other
cameras (refined with a landmark model, or projected), ids hold over frames, a person one camera
sees keeps a single-view crop, and frames or cameras with nobody are fine."""

import cv2
import numpy as np
import pytest
from crowd_people import instances, person, rig
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.data.extract.options import ExtractOptions
from gst.data.keypoints.instances import PersonInstance
from gst.data.keypoints.ownership import own_pixels
from gst.data.keypoints.people import CrowdConfig, CrowdTracker, _Candidate, _window
from gst.detect.blazepose import LANDMARK_SIZE, BodyRoi
from gst.detect.persons import skeleton_support

RIG = rig("dome", 5, seed=2)


def _scene(frames: int = 6):
    """Three people walking slowly; per frame their world landmarks."""
    out = []
    for f in range(frames):
        dx = 0.02 * f
        out.append(
            [person(dx, 0.0, 0.3), person(0.45 + dx, 0.1, 2.0), person(-0.4, 0.4 - dx, -1.0)]
        )
    return out


def _foreground(cam, people):
    fg = np.zeros((cam.height, cam.width), bool)
    for p in people:
        lm = np.c_[cam.project(p), np.ones(33)]
        fg |= skeleton_support(lm, fg.shape, 6)
    return fg


def _fake_model(frames, calls):
    """A landmark model that answers with the true person nearest the region's centre; its
    segmentation is that person's support where the image shows someone (pixels painted out
    with the empty background are nobody's, as the real model sees them). It reads only the
    people in that camera's picture (`calls["pictured"]`, camera -> person indices)."""

    def segment(camera, image, roi, origin):
        cam = RIG[camera]
        people = frames[calls["frame"]]
        # the image is the window of the frame at `origin`: its pixels are the frame's - origin
        pictured = calls.get("pictured", {}).get(camera, range(len(people)))
        hips = {k: cam.project(people[k][[23, 24]]).mean(axis=0) - origin for k in pictured}
        k = min(hips, key=lambda k: np.linalg.norm(hips[k] - roi.centre))
        calls["n"] += 1
        lm = np.c_[cam.project(people[k]) - origin, np.ones(33)]
        prob = skeleton_support(lm, image.shape[:2], 6) & np.any(image > 0, axis=2)
        return lm, 1.0, prob.astype(np.float32)

    return segment


def _run(
    refine: bool,
    hide: tuple[str, int] | None,
    single: int | None = None,
    workers: int = 1,
    stray: tuple[str, int] | None = None,
    scene: list | None = None,
    pictured: bool = False,
    **config,
):
    """Track the scene. `hide` = (camera, person) drops that detection; `stray` adds in that
    camera a detection of a fragment of that person (their lower body); `config` overrides
    CrowdConfig fields. `scene` replaces the three people's frames; with `pictured` the person
    whom only camera 1's detector finds is in every camera's picture."""
    frames = scene or _scene()
    calls = {"frame": 0, "n": 0}
    model = _fake_model(frames, calls) if refine else None
    cfg = CrowdConfig(refine=refine, **config)
    tracker = CrowdTracker(RIG, 1 / 30, cfg, model, workers=workers)
    outs = []
    for f, people in enumerate(frames):
        calls["frame"] = f
        only = 2 if single is None else single
        cams = {only: [RIG.names[1]]}
        found, truth = instances(RIG, people, noise_px=1.0, seed=f, cameras=cams)
        if hide is not None:
            cam, k = hide
            keep = [i for i, t in enumerate(truth[cam]) if t != k]
            found[cam] = [found[cam][i] for i in keep]
            truth[cam] = [truth[cam][i] for i in keep]
        if stray is not None:
            cam, k = stray
            legs = found[cam][truth[cam].index(k)].landmarks.copy()
            legs[:23, 2] = 0.0  # only the hips and legs were found
            found[cam].append(PersonInstance.create(legs))
            truth[cam].append(-1)
        # The single-view person is only in camera 1's picture.
        calls["pictured"] = {
            c.name: [
                k for k in range(len(people)) if k != only or c.name == RIG.names[1] or pictured
            ]
            for c in RIG
        }
        fg = {c.name: _foreground(c, [people[k] for k in calls["pictured"][c.name]]) for c in RIG}
        # The picture: someone wherever the foreground is; the empty scene is black.
        images = {c.name: np.where(fg[c.name][..., None], 200, 0).astype(np.uint8) for c in RIG}
        empty = {c.name: np.zeros((c.height, c.width, 3), np.uint8) for c in RIG}
        masks = {c: [i.mask for i in found[c]] for c in found}
        # instance masks for single-view people: their support in that camera
        for c, lst in found.items():
            masks[c] = [skeleton_support(inst.landmarks, fg[c].shape, 6) for inst in lst]
        out = tracker.process(f, found, fg, images, empty, masks)
        outs.append((out, truth, people))
    tracker.close()
    return outs, calls


def _who(view, cam, people):
    """The true people a view's mask is mostly made of (at least 20% of its pixels each),
    from the ownership of the foreground by the exact skeletons."""
    if cam.name != RIG.names[1]:
        people = people[:2] + [np.full((33, 3), np.nan)]
    truth = own_pixels(
        cam, _foreground(cam, [p for p in people if np.isfinite(p).all()]), people
    ).labels
    ids = truth[view.mask]
    ids = ids[ids > 0]
    return [k for k in range(len(people)) if np.count_nonzero(ids == k + 1) > 0.2 * len(ids)]


def test_a_person_the_detector_misses_is_refound_from_the_other_cameras():
    hidden = RIG.names[3]
    outs, calls = _run(refine=True, hide=(hidden, 0))
    assert calls["n"] > 0
    pids = set()
    for out, _, people in outs:
        multi = [p for p in out.people if not p.single_view]
        assert len(multi) == 2  # person 2 is seen by camera 1 only
        owner = {}
        for p in multi:
            for cam, view in p.views.items():
                who = _who(view, RIG[cam], people)
                assert len(who) <= 1
                if who:
                    owner.setdefault(who[0], set()).add(p.pid)
            if hidden in p.views and _who(p.views[hidden], RIG[hidden], people) == [0]:
                assert p.views[hidden].source == "refined"
                pids.add(p.pid)
        assert all(len(v) == 1 for v in owner.values())
    assert len(pids) == 1  # the same id every frame


def test_without_a_landmark_model_the_missed_view_is_projected():
    hidden = RIG.names[3]
    outs, _ = _run(refine=False, hide=(hidden, 0))
    sources = []
    for out, _, people in outs:
        for p in out.people:
            if hidden in p.views and _who(p.views[hidden], RIG[hidden], people) == [0]:
                sources.append(p.views[hidden].source)
    # Once person 0 is remembered (confirmed after a few frames), the view is projected.
    assert sources and set(sources) == {"projected"}
    assert len(sources) >= len(outs) - 3


def test_single_view_person_keeps_a_crop_and_empty_frames_are_fine():
    outs, _ = _run(refine=True, hide=None)
    for out, _, people in outs:
        single = [p for p in out.people if p.single_view]
        assert len(single) == 1 and list(single[0].views) == [RIG.names[1]]
        view = single[0].views[RIG.names[1]]
        assert view.source == "single" and _who(view, RIG[RIG.names[1]], people) == [2]
    tracker = CrowdTracker(RIG, 1 / 30)
    empty = tracker.process(
        0, {c: [] for c in RIG.names}, {c: np.zeros((2, 2), bool) for c in RIG.names}
    )
    assert empty.people == [] and any("nobody" in n for n in empty.notes)
    assert tracker.process(1, {}, {}).people == []


def test_a_single_view_neighbours_pixels_are_theirs_not_a_3d_persons():
    """A person only camera 1 sees, 0.4 m from a person every camera sees: without a refined
    mask, their pixels went to the nearest 3D person (the ownership knew no one else), whose
    view was then half made of them."""
    cam1 = RIG.names[1]
    scene = [
        [person(0.02 * f, 0.0, 0.3), person(1.5, 1.2, 2.0), person(0.02 * f + 0.4, 0.12, -1.0)]
        for f in range(6)
    ]
    outs, _ = _run(refine=False, hide=None, scene=scene, single=2)
    seen = 0
    for out, _, people in outs:
        for p in out.people:
            if not p.single_view and cam1 in p.views:
                seen += 1
                assert 2 not in _who(p.views[cam1], RIG[cam1], people)
    assert seen >= 6


def test_one_person_found_from_two_sides_is_one_and_two_side_by_side_are_two():
    """Two candidates, each refined in its own cameras and triangulated from them alone, lay
    0.155 m apart with hips 0.114 m apart: over both duplicate limits, so one person kept two
    ids (crowd_7001). Their views together fit one skeleton; two people 0.3 m apart do not."""
    tracker = CrowdTracker(RIG, 1 / 30)
    names = RIG.names

    def candidate(body, cams, seed):
        found, _ = instances(RIG, [body], noise_px=2.0, seed=seed)
        refined = {n: (found[n][0], np.zeros((2, 2))) for n in cams if found[n]}
        return _Candidate(body.copy(), False, None, refined)

    one = person(0.0, 0.0, 0.4)
    a, b = candidate(one, names[:2], 1), candidate(one, names[2:], 2)
    assert tracker._one_body(a, b) and tracker._one_body(b, a)
    beside = candidate(person(0.3, 0.0, 0.4), names[2:], 2)
    assert not tracker._one_body(a, beside)
    # what refuses them is `duplicate_fit`: their readings fit the joint skeleton within a
    # view's limit (MatchConfig.view_error 0.1), but 0.06-0.09 worse than their own
    assert CrowdTracker(RIG, 1 / 30, CrowdConfig(duplicate_fit=0.09))._one_body(a, beside)
    off = CrowdTracker(RIG, 1 / 30, CrowdConfig(duplicate_fit=0.0))
    assert not off._one_body(a, b)


@pytest.mark.parametrize("search", [True, False])
def test_someone_at_the_back_whom_one_detector_finds_is_looked_for_where_they_stand(search):
    """The lab's bystander: they stand apart (1.7 m from the nearest), every camera shows them,
    but only camera 1's detector finds them. Read as standing where their ankles' ray meets the
    others' ankle height, they are looked for in the other cameras and found: a person seen in 3D
    with one id. With the search off (the test's own check that it can fail) they stay
    single-view."""
    scene = [[person(0.5 + 0.02 * f, 0.3, 0.3), person(0.95, 0.4, 2.0), person(-1.2, 0.0, -1.0)]
             for f in range(6)]  # fmt: skip
    outs, _ = _run(refine=True, hide=None, scene=scene, pictured=True, single_view_search=search)
    ids = set()
    for out, _, people in outs:
        him = [
            p
            for p in out.people
            if all(
                np.median(np.linalg.norm(v.landmarks[:, :2] - RIG[n].project(people[2]), axis=1))
                < 5
                for n, v in p.views.items()
            )
        ]
        assert len(him) == 1
        ids.add(him[0].pid)
        if search:
            assert not him[0].single_view and len(him[0].views) >= 2
            np.testing.assert_allclose(him[0].skeleton[[23, 24]], people[2][[23, 24]], atol=0.02)
        else:
            assert him[0].single_view
    assert len(ids) == 1


def test_someone_one_detector_finds_among_others_is_not_looked_for_where_they_stand():
    """Within `standing_apart` of someone else (the three people of `_scene` stand 0.5-0.7 m
    apart) a single view is left as it is, even where every camera shows the person."""
    outs, calls = _run(refine=True, hide=None, pictured=True)
    for out, _, _ in outs:
        single = [p for p in out.people if p.single_view]
        assert len(single) == 1 and list(single[0].views) == [RIG.names[1]]
    far, _ = _run(refine=True, hide=None, pictured=True, standing_apart=0.3)
    # the gate is what keeps them single: at 0.3 m the search finds them in the other cameras
    assert all(not p.single_view for out, _, _ in far for p in out.people)


def test_cameras_on_worker_threads_give_the_same_people():
    """The cameras of a frame refined and masked on two threads: the same ids, views, sources,
    landmarks and masks as one after the other, views in the same (camera) order."""
    serial, _ = _run(refine=True, hide=(RIG.names[3], 0))
    threaded, _ = _run(refine=True, hide=(RIG.names[3], 0), workers=2)
    for (a, *_), (b, *_) in zip(serial, threaded, strict=True):
        assert [p.pid for p in a.people] == [p.pid for p in b.people]
        for p, q in zip(a.people, b.people, strict=True):
            assert list(p.views) == list(q.views)
            for cam in p.views:
                assert p.views[cam].source == q.views[cam].source
                np.testing.assert_array_equal(p.views[cam].landmarks, q.views[cam].landmarks)
                np.testing.assert_array_equal(p.views[cam].mask, q.views[cam].mask)


def _views(outs):
    return [{(p.pid, cam): v for p in out.people for cam, v in p.views.items()} for out, *_ in outs]


def test_views_of_people_standing_alone_keep_their_detection():
    """reuse_detections keeps a detection that fits its skeleton where no one overlaps the
    person: the same people, ids and views as looking again at every view (the default), fewer
    model calls, and the missed view is still refound by the model."""
    hidden = RIG.names[3]
    every, every_calls = _run(refine=True, hide=(hidden, 0))
    reused, reused_calls = _run(refine=True, hide=(hidden, 0), reuse_detections=True)
    assert 0 < reused_calls["n"] < every_calls["n"]
    for a, b, (_, _, people) in zip(_views(every), _views(reused), reused, strict=True):
        assert a.keys() == b.keys()
        for key, view in b.items():
            assert view.source == a[key].source
            who = _who(view, RIG[key[1]], people)
            assert who == _who(a[key], RIG[key[1]], people)
        assert any(cam == hidden and v.source == "refined" for (_, cam), v in b.items())


def test_reuse_is_a_stage_setting_and_checked():
    assert not ExtractOptions.from_settings().crowd.reuse_detections
    assert ExtractOptions.from_settings(reuse_detections=True).crowd.reuse_detections
    with pytest.raises(ValueError, match="reuse_fit"):
        CrowdConfig(reuse_fit=0.2)


def test_a_stray_detection_beside_a_person_makes_the_model_look_again():
    """A fragment of person 2 detected in camera 2, where no one overlaps them (that no
    candidate takes): their view there is not reused, so the fragment does not become a
    second, single-view person."""
    cam = RIG.names[2]
    clean, clean_calls = _run(refine=True, hide=None, single=0, reuse_detections=True)
    strayed, stray_calls = _run(
        refine=True, hide=None, single=0, stray=(cam, 2), reuse_detections=True
    )
    assert stray_calls["n"] > clean_calls["n"]
    for out, *_ in strayed:
        assert [p for p in out.people if p.single_view and cam in p.views] == []


@settings(max_examples=200, deadline=None)
@given(
    cx=st.floats(-100, 700),
    cy=st.floats(-100, 500),
    side=st.floats(4, 900),
    angle=st.floats(-np.pi, np.pi),
)
def test_the_window_holds_every_pixel_the_region_samples(cx, cy, side, angle):
    """The window passed to the landmark model holds the whole region: every crop pixel maps
    into it (or off the image), with a pixel to spare for the interpolation."""
    roi = BodyRoi((cx, cy), side, angle)
    x0, y0, x1, y1 = _window(roi, (480, 640, 3), 2)
    to_image = cv2.invertAffineTransform(roi.to_crop(LANDMARK_SIZE))
    u, v = np.meshgrid([0, LANDMARK_SIZE - 1], [0, LANDMARK_SIZE - 1])
    xy = np.c_[u.ravel(), v.ravel(), np.ones(4)] @ to_image.T
    # the pixels bilinear sampling reads at each corner, where they are in the image
    for axis, lo, hi, n in ((0, x0, x1, 640), (1, y0, y1, 480)):
        first = np.floor(xy[:, axis])
        read = np.r_[first, first + 1]
        read = read[(read >= 0) & (read < n)]
        assert np.all((read >= lo) & (read < hi))


def test_two_candidates_sharing_their_hips_are_one_person():
    """Two bodies cannot share their hips: candidates whose mid-hips lie within
    `duplicate_hips` are one person, however far apart their limbs were triangulated (the lab's
    kicking man, twice from different views: hips 2-4 cm apart, limbs 0.27-0.48 m); the one more
    cameras confirmed stays. People 0.3 m apart stay two."""
    from gst.data.keypoints.people import _Candidate

    rng = np.random.default_rng(0)
    base = rng.normal(0, 0.3, (33, 3))
    base[[23, 24]] = [[-0.1, 0.9, 0.0], [0.1, 0.9, 0.0]]
    other_limbs = base + rng.normal(0, 0.5, (33, 3))
    other_limbs[[23, 24]] = base[[23, 24]] + [0.03, 0.0, 0.0]  # hips 3 cm off, limbs far
    beside = base + [0.3, 0.0, 0.0]  # another person, 0.3 m to the side
    views = {n: (None, None) for n in RIG.names[:3]}
    a = _Candidate(base, False, None, dict(views))
    b = _Candidate(other_limbs, False, None, {RIG.names[0]: (None, None)})
    c = _Candidate(beside, False, None, dict(views))
    # the hips rule alone: these views are stand-ins, which the joint-fit rule (tested with
    # real readings in the test above) cannot read
    tracker = CrowdTracker(RIG, 1 / 30, CrowdConfig(duplicate_fit=0.0))
    kept = tracker._distinct([b, a, c])
    assert [k is a for k in kept] == [True, False] and kept[1] is c
    off = CrowdTracker(RIG, 1 / 30, CrowdConfig(duplicate_hips=0.0, duplicate_fit=0.0))
    assert len(off._distinct([b, a, c])) == 3
    # the kept one takes the views the other found in cameras it has none in, and is
    # triangulated again from them all
    b.refined[RIG.names[3]], b.fits[RIG.names[3]] = ("view", "mask"), 0.02
    again = []
    tracker._triangulate_refined = again.append
    tracker._distinct([b, a, c])
    assert a.refined[RIG.names[3]] == ("view", "mask") and a.fits[RIG.names[3]] == 0.02
    assert again == [a] and RIG.names[3] not in c.refined


@pytest.mark.parametrize("paint", ["covered", "owned"])
def test_a_person_whose_skeleton_slid_off_them_is_not_painted_out(paint):
    """Person A's remembered skeleton lies 0.25 m beside them, away from B (0.45 m on). Looking
    again at A, the model must see A: "covered" paints out only the pixels inside B's capsules,
    so A's own body stays in the picture; "owned" (before 2026-11-30) gives the side of A nearer
    to B's capsules than to A's slid ones to B and paints it out, and the model then answers
    where the slid skeleton already is (the crowd scenes' lost people)."""
    cam = RIG[0]
    a, b = person(0.0, 0.0, 0.3), person(0.45, 0.1, 2.0)
    slid = a - [0.25, 0.0, 0.0]
    fg = _foreground(cam, [a, b])
    image = np.where(fg[..., None], 200, 0).astype(np.uint8)
    seen = {}

    def segment(camera, window, roi, origin):
        seen[len(seen)] = (*origin, window.copy())
        return None

    tracker = CrowdTracker(RIG, 1 / 30, CrowdConfig(paint=paint), segment)
    cands = [_Candidate(slid, True, None), _Candidate(b, False, None)]
    tracker._refine_camera(cam.name, cands, [slid, b], fg, image, {}, {})
    x0, y0, window = seen[0]  # the look at A
    # A's own pixels: their support, away from B's (2 px margin)
    near_b = cv2.dilate(_foreground(cam, [b]).astype(np.uint8), np.ones((5, 5), np.uint8))
    only_a = _foreground(cam, [a]) & (near_b == 0)
    h, w = window.shape[:2]
    mine = only_a[y0 : y0 + h, x0 : x0 + w]
    painted = np.count_nonzero(mine & (window[..., 0] == 128)) / max(np.count_nonzero(mine), 1)
    if paint == "covered":
        assert painted < 0.02
    else:
        assert painted > 0.1  # 0.19 measured


def test_masks_that_do_not_pair_with_the_instances_are_refused_naming_the_camera():
    """masks[camera][i] is instance i's mask: a list shorter than the camera's instances was an
    IndexError from deep in `process` (the single-view person's mask), naming nothing."""
    people = _scene(1)[0]
    found, _ = instances(RIG, people, noise_px=1.0, seed=0, cameras={2: [RIG.names[1]]})
    fg = {c.name: _foreground(c, people) for c in RIG}
    masks = {
        c: [skeleton_support(i.landmarks, fg[c].shape, 6) for i in lst] for c, lst in found.items()
    }
    masks[RIG.names[1]] = masks[RIG.names[1]][:1]
    with pytest.raises(ValueError, match=f"frame 4, camera {RIG.names[1]}: 1 masks for 3"):
        CrowdTracker(RIG, 1 / 30, CrowdConfig(refine=False)).process(4, found, fg, masks=masks)


def test_a_model_answer_whose_presence_is_nan_is_no_view(monkeypatch):
    """The landmark model's presence gate (`min_presence`) let a NaN presence through."""
    real = _fake_model

    def nan_presence(frames, calls):
        segment = real(frames, calls)

        def answer(*args):
            lm, _, prob = segment(*args)
            return lm, float("nan"), prob

        return answer

    monkeypatch.setitem(globals(), "_fake_model", nan_presence)
    outs, calls = _run(refine=True, hide=(RIG.names[3], 0))
    assert calls["n"] > 0
    sources = {v.source for out, _, _ in outs for p in out.people for v in p.views.values()}
    assert "refined" not in sources and "detected" in sources

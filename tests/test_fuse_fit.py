"""The body fit (gst.fuse.fit) recovers known bodies from noisy 2D, flags joints with < 2 views,
and handles a person seen by a single camera."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from gst.body import load_body_model
from gst.body.markers import MarkerModel
from gst.fuse.fit import FitOptions, euler_xyz_from_matrix, fit_people
from gst.fuse.tables import joint_evidence
from gst.fuse.triangulate import triangulate_person
from tests.fuse_fixtures import make_capture, observations

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def body():
    return load_body_model("anny")


@pytest.fixture(scope="module")
def capture(body):
    return make_capture(body, n_people=2, n_frames=6, n_cams=4, seed=1)


def test_euler_inverse_of_joint_limit_convention():
    from gst.body.joint_limits import euler_xyz_to_matrix

    a = (torch.rand(200, 3, dtype=torch.float64) - 0.5) * 2.8
    a[:, 1] *= 0.5  # keep b inside (-pi/2, pi/2), where XYZ angles are unique
    np.testing.assert_allclose(euler_xyz_from_matrix(euler_xyz_to_matrix(a)), a, atol=1e-9)


def test_fit_recovers_known_bodies_from_noisy_2d(body, capture):
    people = observations(capture, noise_px=1.0, seed=2)
    tris = [triangulate_person(p) for p in people]
    fits = fit_people(body, MarkerModel.load(), people, tris, fps=30.0)
    err = np.linalg.norm(np.stack([f.joints for f in fits]) - capture.joints, axis=-1)
    # Tolerance: 1 px of noise at 600 px focal and 5 m is ~8 mm per view; joints without a
    # landmark of their own (spine, neck, collars) are inferred through the body model.
    assert err.mean() < 0.025, err.mean(1)
    assert np.median(err) < 0.02
    for f in fits:
        assert np.nanmedian(f.reprojection) < 2.0  # px, the noise level
        assert not f.single_view and f.observed.all()


@pytest.mark.parametrize("bad", ["confidence", "K"])
def test_one_non_finite_view_does_not_stop_the_fit_of_everyone_in_its_batch(body, capture, bad):
    """A NaN confidence or camera of one view (person 0, frame 3, camera 2) made the batched
    Hessian NaN: every step was refused, and both people kept their start (13 -> 18-19 mm).
    Such a view is no view, as in the triangulation."""
    people = observations(capture, noise_px=3.0, seed=1)
    clean = fit_people(body, MarkerModel.load(), people, [triangulate_person(p) for p in people],
                       fps=30.0)  # fmt: skip
    if bad == "confidence":
        people[0].confidence[3, 2, 15] = np.nan
    else:
        people[0].K[3, 2] = np.nan
    fits = fit_people(body, MarkerModel.load(), people, [triangulate_person(p) for p in people],
                      fps=30.0)  # fmt: skip
    for f, c, truth in zip(fits, clean, capture.joints, strict=True):
        err, err_clean = (np.linalg.norm(x.joints - truth, axis=-1).mean() for x in (f, c))
        assert err < err_clean + 0.002, (err, err_clean)


def test_joint_with_fewer_than_two_views_is_flagged_and_filled(body, capture):
    people = observations(capture, noise_px=0.5, seed=3)
    knee = 25  # left_knee landmark
    people[0].confidence[2, 1:, knee] = 0.0  # frame 2: the left knee is seen by camera 0 only
    tris = [triangulate_person(p) for p in people]
    # one view triangulates nothing: no view counts as used
    assert tris[0].n_views[2, knee] == 0 and np.isnan(tris[0].points[2, knee]).all()
    fits = fit_people(body, MarkerModel.load(), people, tris, fps=30.0)
    ev = joint_evidence(fits[0], tris[0])
    j_knee = 4  # SMPL left_knee
    assert ev.gap_filled[2, j_knee] and ev.views[2, j_knee] == 0
    assert ev.gap_filled.sum() == 1  # nothing else
    assert not ev.has_landmarks[3]  # spine1: model only, never "gap-filled"
    filled = fits[0].joints[2, j_knee]
    assert np.linalg.norm(filled - capture.joints[0, 2, j_knee]) < 0.05


def test_a_joint_whose_landmarks_are_each_triangulated_is_not_gap_filled(body, capture):
    """The head's nose and ears are triangulated each from its own views: cameras that read the
    nose and only their nearer ear leave no camera with all three, yet every landmark has two
    views. The head was flagged gap-filled (residual 1 in the C3D, a lower score)."""
    from gst.body.markers import BLAZEPOSE_NAMES

    people = observations(capture, noise_px=0.5, seed=3)
    left, right = BLAZEPOSE_NAMES.index("left_ear"), BLAZEPOSE_NAMES.index("right_ear")
    n_cams = people[0].confidence.shape[1]
    people[0].confidence[2, : n_cams // 2, right] = 0.0  # half the ring reads the left ear
    people[0].confidence[2, n_cams // 2 :, left] = 0.0  # the other half the right one
    tris = [triangulate_person(p) for p in people]
    assert not tris[0].used[2, [0, left, right]].all(0).any()  # no camera used all three
    fits = fit_people(body, MarkerModel.load(), people, tris, fps=30.0)
    ev = joint_evidence(fits[0], tris[0])
    head = 15  # SMPL head
    assert not ev.gap_filled[2, head] and not ev.fitted_only()[2, head]
    ears = tris[0].used[2, [left, right]].sum(1)
    assert ev.views[2, head] == min(ears.min(), tris[0].used[2, 0].sum()) >= 2
    assert bin(int(ev.mask[2, head])).count("1") == n_cams  # every camera gave a landmark
    assert not ev.gap_filled.any()


def test_single_view_person_is_fitted_and_marked(body, capture):
    people = observations(capture, noise_px=0.5, seed=4)
    p = people[1]
    p.confidence[:, 1:] = 0.0
    p.uv[:, 1:] = np.nan
    p.rows[:, 1:] = -1
    tris = [triangulate_person(q) for q in people]
    assert np.isnan(tris[1].points).all()
    fits = fit_people(body, MarkerModel.load(), people, tris, fps=30.0, options=FitOptions())
    assert fits[1].single_view and not fits[0].single_view
    assert np.isfinite(fits[1].joints).all()
    # one camera pins the body in 2D (depth is the prior's guess): reprojection still small
    assert np.nanmedian(fits[1].reprojection[:, 0]) < 3.0


def test_a_second_crop_without_usable_landmarks_is_no_second_view(body, capture):
    """The person has crops in every camera, but only one camera's landmarks carry confidence
    (the extraction projected the others): nothing is triangulated, so the fit is single-view
    and says so (was: two crops counted as two views)."""
    people = observations(capture, noise_px=0.5, seed=4)
    p = people[1]
    p.confidence[:, 1:] = 0.0
    tri = triangulate_person(p)
    assert np.isnan(tri.points).all()
    fit = fit_people(body, MarkerModel.load(), [p], [tri], 30.0)[0]
    assert fit.single_view


def test_single_view_start_stands_along_the_rigs_up_whatever_its_axis(body, capture):
    """A person one camera sees, in the same scene written in a y-down world (a Panoptic rig's
    `Rig.up` = (0, -1, 0)): the fit is the z-up world's, rotated. (The start assumed +Z up: the
    body started lying down and the fit ended metres away.)"""
    people = observations(capture, noise_px=0.5, seed=4)
    p = people[1]
    p.confidence[:, 1:] = 0.0
    p.uv[:, 1:] = np.nan
    p.rows[:, 1:] = -1
    Q = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # z-up world -> y-down world
    q = replace(p, Rt=np.concatenate([p.Rt[..., :3] @ Q.T, p.Rt[..., 3:]], -1))
    fits = [
        fit_people(body, MarkerModel.load(), [o], [triangulate_person(o)], 30.0, up=up)[0]
        for o, up in ((p, (0.0, 0.0, 1.0)), (q, (0.0, -1.0, 0.0)))
    ]
    assert fits[0].single_view and fits[1].single_view
    back = fits[1].joints @ Q  # y-down world -> z-up world
    assert np.linalg.norm(back - fits[0].joints, axis=-1).max() < 0.02


def test_gap_frames_are_inserted_and_static_frames_start_from_the_previous(body, capture):
    people = observations(capture, noise_px=0.0, seed=5)
    p = people[0].select(np.array([0, 1, 3, 4, 5]))  # frame 2 missing: a gap of one frame
    p.uv[4] = p.uv[3]  # frame 5 repeats frame 4: nobody moved
    tris = [triangulate_person(p)]
    fit = fit_people(body, MarkerModel.load(), [p], tris, fps=30.0)[0]
    assert fit.frames.tolist() == [0, 1, 2, 3, 4, 5]
    assert fit.observed.tolist() == [True, True, False, True, True, True]
    assert fit.static.tolist() == [False, False, False, False, False, True]
    mid = (fit.joints[1] + fit.joints[3]) / 2
    assert np.linalg.norm(fit.joints[2] - mid, axis=-1).mean() < 0.05


def test_gaps_longer_than_max_gap_s_are_left_out(body, capture):
    """Frames 2-4 unseen: at 30 fps (0.1 s = 3 frames) the fit fills them; at 20 fps (2 frames)
    the gap is too long, it has no frames and frames 1 and 5 are not neighbours."""
    p = observations(capture, noise_px=0.0, seed=5)[0].select(np.array([0, 1, 5]))
    tris = [triangulate_person(p)]
    filled = fit_people(body, MarkerModel.load(), [p], tris, fps=30.0)[0]
    assert filled.frames.tolist() == [0, 1, 2, 3, 4, 5]
    assert filled.observed.tolist() == [True, True, False, False, False, True]
    left = fit_people(body, MarkerModel.load(), [p], tris, fps=20.0)[0]
    assert left.frames.tolist() == [0, 1, 5] and left.observed.all()
    truth = capture.joints[0, [0, 1, 5]]
    assert np.linalg.norm(left.joints - truth, axis=-1).mean() < 0.03


def test_per_frame_limb_lengths_measure_the_data(body, capture):
    """Each frame fitted with its own shape: lengths match the true limbs on clean 2D, and a
    frame whose landmarks come from a body 8 % larger reads 8 % longer limbs, alone."""
    from gst.fuse.consistency import LIMB_SEGMENTS, per_frame_limb_lengths
    from tests.fuse_fixtures import project

    people = observations(capture, noise_px=0.3, seed=6)
    tris = [triangulate_person(p) for p in people]
    limbs = per_frame_limb_lengths(body, MarkerModel.load(), people, tris, fps=30.0)
    for k, per in enumerate(limbs):
        for name, (a, b) in LIMB_SEGMENTS.items():
            true = np.linalg.norm(capture.joints[k, :, a] - capture.joints[k, :, b], axis=-1)
            assert np.abs(per[name] - true).max() < 0.02, (k, name)
    # frame 3 of person 1 seen as a body scaled by 1.08 about its pelvis
    X = capture.markers[0, 3]
    c = capture.joints[0, 3, 0]
    people[0].uv[3] = project(capture.rig, c + 1.08 * (X - c))
    tris = [triangulate_person(p) for p in people]
    moved = per_frame_limb_lengths(body, MarkerModel.load(), people, tris, fps=30.0)
    for name in LIMB_SEGMENTS:
        ratio = moved[0][name] / limbs[0][name]
        assert 1.04 < ratio[3] < 1.12, (name, ratio)
        assert np.abs(np.delete(ratio, 3) - 1).max() < 1e-6  # frames are fitted independently


def test_the_marker_table_says_which_body_it_was_fitted_on():
    """The shipped table was fitted on the Anny default's rest pose; with `body_model: smpl`
    (a T-pose) its hand markers lie 6-8 cm off, and nothing said so."""
    table = MarkerModel.load()
    assert table.info["body_model"] == "anny"
    assert table.fitted_for("anny") is None
    warning = table.fitted_for("smpl")
    assert "fitted on the body 'anny', not 'smpl'" in warning
    assert "fit_markers --body smpl" in warning
    assert MarkerModel.fallback().fitted_for("smpl") is None  # says nothing of its body

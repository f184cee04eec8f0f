"""Robust N-view triangulation (gst.fuse.triangulate): exact on noiseless projections (OpenCV
projection as the reference), rejects a corrupted view, flags points seen by fewer than 2 views."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.camera import look_at_rotation
from gst.fuse.triangulate import TriangulationOptions, triangulate_points


def _rig(n_cams: int, rng: np.random.Generator):
    """Cameras on a ring around the origin looking at it, with different intrinsics."""
    K, Rt = [], []
    for c in range(n_cams):
        a = 2 * np.pi * c / n_cams + rng.uniform(-0.2, 0.2)
        pos = np.array([4 * np.cos(a), 4 * np.sin(a), rng.uniform(1.0, 2.5)])
        R = look_at_rotation(pos, np.array([0.0, 0.0, 1.0]))
        f = rng.uniform(300, 900)
        K.append(
            np.array([[f, 0, rng.uniform(100, 300)], [0, f, rng.uniform(100, 300)], [0, 0, 1]])
        )
        Rt.append(np.hstack([R, (-R @ pos)[:, None]]))
    return np.array(K), np.array(Rt)


def _project_cv(K, Rt, X):
    rvec, _ = cv2.Rodrigues(Rt[:3, :3])
    uv, _ = cv2.projectPoints(X.reshape(-1, 1, 3), rvec, Rt[:, 3], K, None)
    return uv.reshape(-1, 2)


def _observe(K, Rt, X):
    """(N, C, ...) batched inputs for N points seen by every camera."""
    N, C = len(X), len(K)
    uv = np.stack([_project_cv(K[c], Rt[c], X) for c in range(C)], axis=1)
    return np.broadcast_to(K, (N, C, 3, 3)), np.broadcast_to(Rt, (N, C, 3, 4)), uv


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n_cams=st.integers(2, 8),
    n_points=st.integers(1, 20),
)
def test_noiseless_projections_are_recovered_exactly(seed, n_cams, n_points):
    rng = np.random.default_rng(seed)
    K, Rt = _rig(n_cams, rng)
    X = rng.uniform([-1, -1, 0], [1, 1, 2], (n_points, 3))
    Kb, Rtb, uv = _observe(K, Rt, X)
    conf = rng.uniform(0.5, 1.0, (n_points, n_cams))
    out = triangulate_points(Kb, Rtb, uv, conf)
    np.testing.assert_allclose(out.points, X, atol=1e-7)
    assert out.used.all()
    assert np.nanmax(out.errors) < 1e-5
    assert (out.confidence > 0).all()


def test_one_corrupted_view_is_rejected():
    rng = np.random.default_rng(3)
    K, Rt = _rig(5, rng)
    X = rng.uniform([-1, -1, 0], [1, 1, 2], (40, 3))
    Kb, Rtb, uv = _observe(K, Rt, X)
    uv = uv + rng.normal(0, 0.5, uv.shape)  # detection noise
    bad = rng.integers(0, 5, len(X))
    uv[np.arange(len(X)), bad] += rng.uniform(40, 120, (len(X), 2)) * rng.choice(
        [-1, 1], (len(X), 2)
    )
    conf = np.ones((len(X), 5))
    plain = triangulate_points(Kb, Rtb, uv, conf, options=TriangulationOptions(max_rejections=0))
    robust = triangulate_points(Kb, Rtb, uv, conf)
    assert not robust.used[np.arange(len(X)), bad].any()  # every corrupted view dropped
    assert robust.used.sum(1).min() == 4  # and only it
    err_plain = np.linalg.norm(plain.points - X, axis=1)
    err_robust = np.linalg.norm(robust.points - X, axis=1)
    assert np.median(err_plain) > 0.02
    assert err_robust.max() < 0.01
    assert robust.error.max() < 2.0  # px, over the kept views


def test_the_outlier_test_counts_crop_pixels_on_large_crops():
    """The landmark model's noise is about constant in crop pixels: on crops 4x their stored size
    (a close or 4K camera), 2 crop px of noise is 8 full-image px, and a fixed 12 px dropped
    a good view of 45 % of the points. A 40 crop-px error is still dropped, and the reported
    errors stay in full-image pixels."""
    rng = np.random.default_rng(7)
    K, Rt = _rig(4, rng)
    X = rng.uniform([-1, -1, 0], [1, 1, 2], (400, 3))
    Kb, Rtb, uv = _observe(K, Rt, X)
    scale = 4.0  # crop side / stored size: uv and K in crop pixels, errors reported x 4
    noisy = (uv + rng.normal(0, 2.0 * scale, uv.shape)) / scale
    Kc = Kb * np.array([1 / scale, 1 / scale, 1.0])[:, None]
    conf, px = np.full((len(X), 4), 0.9), np.full((len(X), 4), scale)
    tri = triangulate_points(Kc, Rtb, noisy, conf, px)
    assert (tri.used.sum(1) < 4).mean() < 0.02, (tri.used.sum(1) < 4).mean()
    fixed = triangulate_points(
        Kc, Rtb, noisy, conf, px, TriangulationOptions(outlier_scales_with_crop=False)
    )
    assert (fixed.used.sum(1) < 4).mean() > 0.2  # the old rule
    assert 5 < np.nanmedian(tri.error) < 12  # full-image px: about 2 crop px x 4
    bad = noisy.copy()
    bad[:, 0] += 40.0  # crop px
    assert not triangulate_points(Kc, Rtb, bad, conf, px).used[:, 0].any()


def test_a_point_seen_along_nearly_one_line_by_two_facing_cameras_loses_its_confidence():
    """Two cameras facing each other see a point near the line through them along one ray: it
    slides along it without moving in either image, and was reported at full two-view
    confidence half a metre off. Confidence now scales with the rays' angle below 5 degrees."""
    rng = np.random.default_rng(5)
    K, Rt = [], []
    for x in (-5.0, 5.0):
        pos = np.array([x, 0.0, 1.5])
        R = look_at_rotation(pos, np.array([0.0, 0.0, 1.5]), up=np.array([0.0, 0.0, 1.0]))
        K.append(np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]]))
        Rt.append(np.hstack([R, (-R @ pos)[:, None]]))
    K, Rt = np.array(K), np.array(Rt)
    near = np.c_[rng.uniform(-1, 1, 50), rng.uniform(-0.03, 0.03, (50, 2)) + [0, 1.5]]
    away = np.c_[rng.uniform(-1, 1, 50), rng.uniform(0.8, 1.2, 50), rng.uniform(0.5, 2.5, 50)]
    for X, low in ((near, True), (away, False)):
        Kb, Rtb, uv = _observe(K, Rt, X)
        tri = triangulate_points(Kb, Rtb, uv + rng.normal(0, 1.0, uv.shape), np.ones((50, 2)))
        if low:
            assert np.median(tri.confidence) < 0.1, np.median(tri.confidence)
        else:
            assert np.median(tri.confidence) > 0.4
    off = TriangulationOptions(min_ray_angle_deg=0)
    Kb, Rtb, uv = _observe(K, Rt, near)
    plain = triangulate_points(Kb, Rtb, uv, np.ones((50, 2)), options=off)
    assert np.median(plain.confidence) > 0.4


def test_two_wrong_views_of_six_are_rejected_by_pair_consensus():
    """Two views agreeing on nothing drag the all-view point so that leaving one out cannot
    recover it; the pair hypotheses find the four that agree."""
    rng = np.random.default_rng(11)
    K, Rt = _rig(6, rng)
    X = rng.uniform([-1, -1, 0], [1, 1, 2], (60, 3))
    Kb, Rtb, uv = _observe(K, Rt, X)
    uv = uv + rng.normal(0, 0.5, uv.shape)
    bad = np.stack([rng.choice(6, 2, replace=False) for _ in X])  # (N, 2) distinct views
    rows = np.arange(len(X))[:, None]
    uv[rows, bad] += rng.uniform(40, 120, (len(X), 2, 2)) * rng.choice([-1, 1], (len(X), 2, 2))
    conf = rng.uniform(0.6, 1.0, (len(X), 6))
    loo = triangulate_points(Kb, Rtb, uv, conf)  # the default: leave-one-out only
    robust = triangulate_points(Kb, Rtb, uv, conf, options=TriangulationOptions(consensus_views=8))
    assert not robust.used[rows, bad].any()  # both wrong views dropped
    assert (robust.used.sum(1) == 4).all()  # and only they
    err_loo = np.linalg.norm(loo.points - X, axis=1)
    err_robust = np.linalg.norm(robust.points - X, axis=1)
    assert err_robust.max() < 0.01
    assert (err_loo > 0.02).sum() >= 3  # leave-one-out alone misses some (7 of these 60)


def test_points_with_fewer_than_two_views_are_flagged():
    rng = np.random.default_rng(5)
    K, Rt = _rig(4, rng)
    X = rng.uniform([-1, -1, 0], [1, 1, 2], (3, 3))
    Kb, Rtb, uv = _observe(K, Rt, X)
    conf = np.ones((3, 4))
    conf[0, 1:] = 0.0  # one view only
    uv[1, :3] = np.nan  # one view only (unobserved)
    conf[2, 2:] = 0.1  # two views above the confidence threshold
    out = triangulate_points(Kb, Rtb, uv, conf)
    assert np.isnan(out.points[:2]).all() and (out.confidence[:2] == 0).all()
    # a view that triangulated nothing is not a view used (was [1, 1, 2]: a NaN landmark in
    # landmarks.parquet with views 1 and a view_mask bit, counted in the report's "used" error)
    assert out.n_views.tolist() == [0, 0, 2]
    assert not out.used[:2].any()
    np.testing.assert_allclose(out.points[2], X[2], atol=1e-7)


def test_px_scale_reports_errors_in_full_image_pixels():
    rng = np.random.default_rng(7)
    K, Rt = _rig(3, rng)
    X = rng.uniform([-1, -1, 0], [1, 1, 2], (10, 3))
    Kb, Rtb, uv = _observe(K, Rt, X)
    uv[:, 0] += [3.0, 4.0]  # 5 px off in view 0
    a = triangulate_points(
        Kb, Rtb, uv, np.ones((10, 3)), options=TriangulationOptions(outlier_px=1e9)
    )
    b = triangulate_points(
        Kb,
        Rtb,
        uv,
        np.ones((10, 3)),
        px_scale=np.full((10, 3), 2.0),
        options=TriangulationOptions(outlier_px=1e9),
    )
    np.testing.assert_allclose(b.errors, 2 * a.errors, rtol=1e-9)


def test_a_camera_with_nan_calibration_spoils_no_point():
    """One camera's K or [R | t] not numbers (seen or not): the others still triangulate, and
    that view is not counted (was: every point NaN, reported with error 0 and confidence 1)."""
    rng = np.random.default_rng(5)
    K, Rt = _rig(4, rng)
    X = rng.uniform([-1, -1, 0], [1, 1, 2], (6, 3))
    Kb, Rtb, uv = (np.array(a) for a in _observe(K, Rt, X))
    conf = np.ones((6, 4))
    for bad_K in (True, False):
        Kc, Rtc = Kb.copy(), Rtb.copy()
        (Kc if bad_K else Rtc)[:, 3] = np.nan
        out = triangulate_points(Kc, Rtc, uv, conf)
        np.testing.assert_allclose(out.points, X, atol=1e-7)
        assert not out.used[:, 3].any() and out.used[:, :3].all()
        assert (out.n_views == 3).all()


def test_views_through_one_centre_give_no_point_and_no_error():
    """Two views from the same place (a camera listed twice): no depth, so no point, no used
    views and no confidence (was: a singular solve that failed the whole batch)."""
    rng = np.random.default_rng(6)
    K, Rt = _rig(2, rng)
    Rt[1] = Rt[0]
    X = np.array([[0.1, -0.2, 1.2], [0.3, 0.2, 0.8]])
    Kb, Rtb, uv = _observe(K, Rt, X)
    uv = uv + rng.normal(0, 0.01, uv.shape)
    out = triangulate_points(Kb, Rtb, uv, np.ones((2, 2)))
    assert np.isnan(out.points).all()
    assert not out.used.any() and (out.confidence == 0).all()


def test_the_outlier_distance_is_a_fuse_setting():
    """It was fixed in code: a user of close or 4K cameras could not widen it."""
    import pytest
    from pydantic import ValidationError

    from gst.fuse.settings import FuseSettings

    assert FuseSettings(outlier_px=30).fuse_options().triangulation.outlier_px == 30
    assert FuseSettings().fuse_options().triangulation.outlier_px == 12
    with pytest.raises(ValidationError):
        FuseSettings(outlier_px=0)


def test_a_camera_with_a_singular_intrinsic_matrix_spoils_no_point():
    """One view's K finite but not invertible (a zero focal length from a broken crop): that
    view is no evidence, as a NaN camera is (was: numpy's bare 'Singular matrix' for the batch,
    naming neither the camera nor the point)."""
    rng = np.random.default_rng(8)
    K, Rt = _rig(4, rng)
    X = rng.uniform([-1, -1, 0], [1, 1, 2], (5, 3))
    Kb, Rtb, uv = (np.array(a) for a in _observe(K, Rt, X))
    Kb[:, 3] = 0.0
    out = triangulate_points(Kb, Rtb, uv, np.ones((5, 4)))
    np.testing.assert_allclose(out.points, X, atol=1e-7)
    assert not out.used[:, 3].any() and (out.n_views == 3).all()
    assert np.isnan(out.errors[:, 3]).all()


def test_zero_confidence_views_are_not_used_even_with_min_confidence_zero():
    """min_confidence 0: a view with no confidence (projected, not read) weighs nothing in the
    DLT and the refinement, so it is not a view used (was: counted in used / n_views and
    halving the point's confidence)."""
    rng = np.random.default_rng(9)
    K, Rt = _rig(4, rng)
    X = rng.uniform([-1, -1, 0], [1, 1, 2], (3, 3))
    Kb, Rtb, uv = _observe(K, Rt, X)
    conf = np.array([[0.9, 0.9, 0.9, 0.0]] * 3)
    out = triangulate_points(Kb, Rtb, uv, conf, options=TriangulationOptions(min_confidence=0))
    ref = triangulate_points(Kb, Rtb, uv, conf)
    np.testing.assert_allclose(out.points, X, atol=1e-7)
    assert (out.n_views == 3).all() and not out.used[:, 3].any()
    np.testing.assert_allclose(out.confidence, ref.confidence)

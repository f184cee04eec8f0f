"""Triangulation: batched DLT and pycolmap's robust estimator against known points."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.camera import Camera, Rig
from calibration.synthetic import ring_rig
from calibration.triangulate import triangulate_dlt, triangulate_robust

RIG = ring_rig(6, seed=4)


def observe(points, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    px = np.stack([c.project(points) for c in RIG])
    return px + rng.normal(0, noise, px.shape)


@settings(max_examples=25, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(-1.2, 1.2), st.floats(-1.2, 1.2), st.floats(0.0, 2.0)),
        min_size=1,
        max_size=30,
    )
)
def test_dlt_recovers_exact_points(pts):
    X = np.array(pts, dtype=float)
    tri = triangulate_dlt(RIG, observe(X))
    np.testing.assert_allclose(tri.points, X, atol=1e-7)
    assert np.nanmax(tri.errors_px) < 1e-5 and (tri.n_views == len(RIG)).all()


def test_dlt_with_noise_and_missing_views():
    rng = np.random.default_rng(1)
    X = rng.uniform([-1, -1, 0], [1, 1, 2], (500, 3))
    px = observe(X, noise=0.5, seed=2)
    visible = rng.uniform(size=px.shape[:2]) < 0.6
    visible[:, 0] = False  # point 0: seen by nobody
    visible[:, 1] = False
    visible[:2, 1] = True  # point 1: exactly two views
    px[~visible] = np.nan  # NaN marks unseen too
    tri = triangulate_dlt(RIG, px)
    assert np.isnan(tri.points[0]).all() and tri.n_views[1] == 2
    ok = tri.n_views >= 2
    err = np.linalg.norm(tri.points[ok] - X[ok], axis=1)
    assert np.median(err) < 0.005 and err.max() < 0.05  # 0.5 px noise at ~3 m
    assert np.nanmean(tri.errors_px) < 1.0


def test_robust_triangulation_ignores_a_wrong_view():
    rng = np.random.default_rng(3)
    X = rng.uniform([-1, -1, 0.2], [1, 1, 1.8], (40, 3))
    px = observe(X, noise=0.3, seed=4)
    px[2] += 60.0  # camera 2 reports a different person's joint
    dlt = triangulate_dlt(RIG, px)
    robust = triangulate_robust(RIG, px)
    assert not robust.used[2].any() and robust.used[[0, 1, 3, 4, 5]].sum() >= 0.95 * 5 * len(X)
    err_robust = np.linalg.norm(robust.points - X, axis=1)
    err_dlt = np.linalg.norm(dlt.points - X, axis=1)
    assert np.median(err_robust) < 0.005 < np.median(err_dlt)


def test_shape_errors():
    with pytest.raises(ValueError, match="cameras=6"):
        triangulate_dlt(RIG, np.zeros((5, 3, 2)))
    with pytest.raises(ValueError, match="visible"):
        triangulate_dlt(RIG, np.zeros((6, 3, 2)), visible=np.ones((6, 4), bool))


def test_robust_triangulation_with_thin_prism_lenses_and_skew():
    """H36M's lens model (radial, tangential and thin-prism terms) and a skewed K: COLMAP's
    FULL_OPENCV has neither, so the lens is undone first (before: a ValueError for every
    H36M-imported camera, and skew silently dropped)."""
    from calibration.camera import Rig

    dist = np.array([-0.2, 0.05, 0.001, -0.002, 0.01, 0.0, 0.0, 0.0, 0.002, 0.0, -0.002, 0.0])
    cams = []
    for c in RIG:
        K = c.K.copy()
        K[0, 1] = 2.0  # skew
        cams.append(c.replace(K=K, dist=dist))
    rig = Rig(tuple(cams))
    X = np.random.default_rng(5).uniform([-1, -1, 0.2], [1, 1, 1.8], (20, 3))
    px = np.stack([c.project(X) for c in rig])
    robust = triangulate_robust(rig, px)
    np.testing.assert_allclose(robust.points, X, atol=1e-6)
    assert robust.used.all() and np.nanmax(robust.errors_px) < 1e-4


def test_dlt_gives_no_point_behind_the_cameras():
    """Two side-by-side cameras, pixels whose rays diverge in front of them: the linear solution
    lies behind both, where OpenCV's projection folds it back onto its pixels with 0 px error.
    No point, and no error."""
    K = [[800, 0, 400], [0, 800, 300], [0, 0, 1]]
    left = Camera.create("L", K, [], np.eye(3), [0.0, 0, 0], 800, 600)
    right = Camera.create("R", K, [], np.eye(3), [-0.5, 0, 0], 800, 600)
    rig = Rig((left, right), up=(0.0, -1.0, 0.0))
    tri = triangulate_dlt(rig, np.array([[[380.0, 300.0]], [[420.0, 300.0]]]))
    assert np.isnan(tri.points).all() and np.isnan(tri.errors_px).all() and not tri.used.any()
    ok = triangulate_dlt(rig, np.array([[[420.0, 300.0]], [[380.0, 300.0]]]))  # converging
    assert ok.points[0, 2] > 0 and np.nanmax(ok.errors_px) < 1e-6


def test_no_points_give_empty_results_like_the_robust_path():
    """An empty frame (no points): the DLT crashed reshaping (0,) into (0, 4)."""
    for triangulate in (triangulate_dlt, triangulate_robust):
        tri = triangulate(RIG, np.zeros((len(RIG), 0, 2)))
        assert tri.points.shape == (0, 3)

"""pycolmap rig bundle adjustment of cameras and board poses, from perturbed starts."""

import cv2
import numpy as np
import pytest

from calibration.bundle import BAOptions, BoardBundleAdjuster, BundleAdjustmentError, CameraState
from calibration.posegraph import (
    chain_poses,
    invert,
    pairwise_edges,
    robust_mean_pose,
    rotation_angle_deg,
)
from calibration.synthetic import make_scene, synthetic_detections


def perturb(T, rng, rot_deg=1.0, trans=0.03):
    d = np.eye(4)
    d[:3, :3] = cv2.Rodrigues(rng.normal(size=3) * np.radians(rot_deg) / np.sqrt(3))[0]
    d[:3, 3] = rng.normal(size=3) * trans
    return d @ T


@pytest.fixture(scope="module")
def problem():
    scene = make_scene(n_cameras=5, n_frames=40, seed=11)
    dets = synthetic_detections(scene, noise_px=0.0, seed=0)
    ref = scene.rig[0]
    rng = np.random.default_rng(0)
    cams, obs = {}, {}
    for c in scene.rig:
        cam_from_rig = c.world_to_cam @ invert(ref.world_to_cam)
        K = c.K.copy()
        K[0, 0] *= 1.03
        K[1, 1] *= 0.98
        K[:2, 2] += [6.0, -4.0]
        cams[c.name] = CameraState(
            c.name,
            c.width,
            c.height,
            K,
            c.dist * 0.5,
            cam_from_rig if c.name == ref.name else perturb(cam_from_rig, rng),
        )
        obs[c.name] = {d.frame: (d.ids, d.corners) for d in dets[c.name]}
    frames = {d.frame for v in dets.values() for d in v}
    rig_from_board = {f: perturb(ref.world_to_cam @ scene.world_from_board[f], rng) for f in frames}
    return scene, cams, ref.name, rig_from_board, obs


def _adjuster(problem, observations=None, options: BAOptions | None = None):
    """The adjuster started from the perturbed problem, on its own observations by default."""
    scene, cams, ref, rig_from_board, obs = problem
    points = scene.board.object_points()
    return BoardBundleAdjuster(
        cams, ref, rig_from_board, points, observations or obs, options=options
    )


def test_bundle_adjustment_recovers_exact_truth(problem):
    scene = problem[0]
    ba = _adjuster(problem, options=BAOptions(loss="trivial", max_outlier_rounds=0))
    result = ba.result(ba.run())
    for c in scene.rig:
        s = result.cameras[c.name]
        np.testing.assert_allclose(s.K, c.K, rtol=1e-6, atol=1e-4)
        np.testing.assert_allclose(s.dist[:4], c.dist[:4], atol=1e-6)
        truth = c.world_to_cam @ invert(scene.rig[0].world_to_cam)
        assert rotation_angle_deg(s.cam_from_rig[:3, :3], truth[:3, :3]) < 1e-5
        np.testing.assert_allclose(s.cam_from_rig[:3, 3], truth[:3, 3], atol=1e-6)
        assert result.residuals[c.name].max() < 1e-4
    for f, T in result.rig_from_board.items():
        np.testing.assert_allclose(
            T, scene.rig[0].world_to_cam @ scene.world_from_board[f], atol=1e-6
        )


def test_residuals_match_colmap_projection(problem):
    ba = _adjuster(problem)
    ours = ba.residuals()
    for iid in list(ours)[:20]:
        img = ba.rec.image(iid)
        for k, p2d in enumerate(img.points2D):
            xyz = ba.rec.point3D(p2d.point3D_id).xyz
            ref_err = np.linalg.norm(
                np.asarray(img.project_point(xyz)) - p2d.xy
            )  # COLMAP's own math
            assert ours[iid][k] == pytest.approx(ref_err, abs=1e-6)


def test_outliers_are_removed_in_rounds(problem):
    scene, obs = problem[0], problem[4]
    rng = np.random.default_rng(3)
    noisy = {}
    for n, views in obs.items():
        noisy[n] = {}
        for f, (ids, px) in views.items():
            px = px + rng.normal(0, 0.3, px.shape)
            if rng.uniform() < 0.2:
                px[0] += 15.0
            noisy[n][f] = (ids, px)
    ba = _adjuster(problem, noisy)
    rounds = ba.run()
    result = ba.result(rounds)
    assert rounds[0]["removed"] > 0 and rounds[-1]["removed"] == 0
    assert all(r.max() < rounds[-1]["limit_px"] for r in result.residuals.values())
    for c in scene.rig:
        assert abs(result.cameras[c.name].K[0, 0] / c.fx - 1) < 0.005


def test_unknown_solver_is_reported(problem):
    ba = _adjuster(problem, options=BAOptions(linear_solver="MAGIC"))
    with pytest.raises(BundleAdjustmentError, match="MAGIC"):
        ba.run()


def test_pose_graph_chains_cameras_without_a_common_frame():
    rng = np.random.default_rng(2)
    truth = {f"c{i}": perturb(np.eye(4), rng, 40, 2.0) for i in range(4)}
    boards = {f: perturb(np.eye(4), rng, 30, 1.0) for f in range(6)}
    seen = {"c0": [0, 1], "c1": [1, 2, 3], "c2": [3, 4], "c3": [4, 5]}  # a chain, nobody sees all
    views = {c: {f: truth[c] @ boards[f] for f in fs} for c, fs in seen.items()}
    poses, reference = chain_poses(list(views), pairwise_edges(views), reference="c0")
    for c in truth:
        np.testing.assert_allclose(poses[c], truth[c] @ invert(truth["c0"]), atol=1e-9)
    mean, inliers = robust_mean_pose(
        np.stack([truth["c1"]] * 5 + [perturb(truth["c1"], rng, 20, 1)])
    )
    np.testing.assert_allclose(mean, truth["c1"], atol=1e-9)
    assert inliers.tolist() == [True] * 5 + [False]

"""The single-view pose fit of track (gst.track.pose_fit): it moves a perturbed body's markers
onto landmarks made from the true body, keeps bodies without evidence as they are, and its
prior and gate hold the network's pose."""

import numpy as np
import pytest
import torch

from gst.body import load_body_model
from gst.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from gst.track.loop import TrackOptions, pose_fitter
from gst.track.pose_fit import PoseFitConfig, PoseFitter, disagreement

S = 256


@pytest.fixture(scope="module")
def fitter():
    return PoseFitter(load_body_model("anny"))


def _bodies(fitter, n, seed):
    """True bodies 3 m in front of a 256 px crop camera, their markers' pixels as confident
    landmarks, and the same bodies with every local rotation perturbed (the 'network')."""
    g = torch.Generator().manual_seed(seed)
    theta = 0.25 * torch.randn(n, 23, 3, generator=g)
    root = axis_angle_to_matrix(torch.tensor([[np.pi, 0.0, 0.0]]).repeat(n, 1))  # upright
    betas = 0.5 * torch.randn(n, 10, generator=g)
    transl = torch.tensor([0.0, 0.1, 3.0]).repeat(n, 1)
    K = torch.tensor([[400.0, 0, 127.5], [0, 400.0, 127.5], [0, 0, 1]]).repeat(n, 1, 1)
    X, J, _, _ = fitter.skeleton.forward(betas, root, theta, transl)
    uv = (X / X[..., 2:]) @ K.transpose(1, 2)
    lm = torch.cat([uv[..., :2], torch.full_like(uv[..., :1], 0.95)], -1)
    noisy = theta + 0.15 * torch.randn(n, 23, 3, generator=g)
    R = torch.cat([root[:, None], axis_angle_to_matrix(noisy)], 1)
    _, Jn, _, _ = fitter.skeleton.forward(betas, root, noisy, transl)
    return R.numpy(), betas.numpy(), transl.numpy(), Jn.numpy(), K.numpy(), lm.numpy(), J.numpy()


def _pixels(J, K):
    return ((J / J[..., 2:]) @ K.transpose(0, 2, 1))[..., :2]


def test_the_fit_brings_a_perturbed_body_onto_its_landmarks(fitter):
    R, betas, t, J_net, K, lm, J_true = _bodies(fitter, 6, seed=1)
    out = fitter(R, betas, t, J_net, K, lm, S)
    assert out.fitted.all()
    before = np.linalg.norm(_pixels(J_net, K) - _pixels(J_true, K), axis=-1).mean()
    after = np.linalg.norm(_pixels(out.joints_cam, K) - _pixels(J_true, K), axis=-1).mean()
    assert after < 0.4 * before
    # and in 3D (root-aligned) it moves towards the truth too
    rel = lambda J: J - J[:, :1]  # noqa: E731
    assert (
        np.abs(rel(out.joints_cam) - rel(J_true)).mean() < np.abs(rel(J_net) - rel(J_true)).mean()
    )
    # the returned joints are the returned pose's
    theta = matrix_to_axis_angle(torch.as_tensor(out.rotmats[:, 1:]))
    _, J, _, _ = fitter.skeleton.forward(
        torch.as_tensor(betas), torch.as_tensor(out.rotmats[:, 0]), theta,
        torch.as_tensor(out.transl_cam),
    )  # fmt: skip
    assert np.allclose(J.numpy(), out.joints_cam, atol=1e-4)


def test_the_fit_keeps_the_networks_depth(fitter):
    """Depth was fitted too, from the 2D size of the landmarks alone: the same depth came out
    whatever the network said (0.6 m too far: the fit still gave 2.92-3.07 m for 3 m), and a
    wrong limb pose moved it by up to 7 cm where the network's was right."""
    R, betas, t, J_net, K, lm, _ = _bodies(fitter, 6, seed=4)
    far = t.copy()
    far[:, 2] += 0.6
    for given, J in ((t, J_net), (far, J_net + (far - t)[:, None])):
        out = fitter(R, betas, given, J, K, lm, S)
        assert out.fitted.all()
        np.testing.assert_allclose(out.transl_cam[:, 2], given[:, 2], atol=1e-5)


def test_bodies_without_enough_evidence_stay_the_networks(fitter):
    R, betas, t, J_net, K, lm, _ = _bodies(fitter, 3, seed=2)
    lm[0, :, 2] = 0.2  # nothing confident
    lm[1] = np.nan  # nothing detected
    out = fitter(R, betas, t, J_net, K, lm, S)
    assert out.fitted.tolist() == [False, False, True]
    assert np.array_equal(out.rotmats[:2], R[:2]) and np.array_equal(out.transl_cam[:2], t[:2])
    assert np.array_equal(out.joints_cam[:2], J_net[:2])


def test_the_prior_and_the_gate_hold_the_networks_pose(fitter):
    R, betas, t, J_net, K, lm, _ = _bodies(fitter, 4, seed=3)
    stiff = PoseFitter(load_body_model("anny"), PoseFitConfig(pose_prior=1e6))
    out = stiff(R, betas, t, J_net, K, lm, S)
    assert np.abs(out.rotmats[:, 1:] - R[:, 1:]).max() < 1e-2  # only the body as a whole moved
    far = disagreement(J_net, K, lm)
    assert (far > 0).all()
    gated = PoseFitter(
        load_body_model("anny"), PoseFitConfig(min_disagreement=far.max() / S + 1e-3)
    )
    assert not gated(R, betas, t, J_net, K, lm, S).fitted.any()
    with pytest.raises(ValueError, match="min_disagreement"):
        PoseFitConfig(min_disagreement=-1)


def test_with_no_gate_a_body_whose_disagreement_cannot_be_measured_is_fitted(fitter):
    """`min_disagreement` 0 is "every body", but a body with enough confident landmarks and
    fewer than 4 of the compared joints (disagreement reads 0 there: `0 > 0`) stayed the
    network's: a head-and-shoulders crop."""
    R, betas, t, J_net, K, lm, _ = _bodies(fitter, 1, seed=4)
    lm[0, 13:, 2] = 0.1  # face and shoulders only: 13 sure landmarks, 2 compared joints
    assert disagreement(J_net, K, lm)[0] == 0.0 and (lm[0, :, 2] >= 0.5).sum() >= 8
    assert fitter(R, betas, t, J_net, K, lm, S).fitted.all()


def test_track_refuses_a_pose_fit_without_a_body_model():
    class NoBody:
        def __call__(self, crops, K):
            raise AssertionError("not called")

    options = TrackOptions(pose_fit=PoseFitConfig())
    with pytest.raises(ValueError, match="body model"):
        pose_fitter(NoBody(), options.pose_fit, 10)
    assert pose_fitter(NoBody(), None, 10) is None


def test_a_body_the_solve_cannot_keep_finite_stays_the_networks(fitter):
    R, betas, t, J_net, K, lm, _ = _bodies(fitter, 2, seed=4)
    R[0, 5] = np.nan  # a broken prediction: the fit must not invent a body for it
    out = fitter(R, betas, t, J_net, K, lm, S)
    assert out.fitted.tolist() == [False, True]
    assert np.array_equal(out.rotmats[0], R[0], equal_nan=True)
    assert np.isfinite(out.rotmats[1]).all()

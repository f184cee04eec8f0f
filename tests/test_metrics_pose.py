"""MPJPE, PA-MPJPE and vertex error against numpy / scipy references, with hypothesis properties."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import procrustes as scipy_procrustes
from scipy.spatial.transform import Rotation

from gst.metrics.pose import mpjpe, pa_mpjpe, procrustes_align, similarity_procrustes, vertex_error


def _umeyama_numpy(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Reference: Umeyama (1991) similarity fit of one point set (N, 3), written out in numpy."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    s_c, d_c = src - mu_s, dst - mu_d
    cov = d_c.T @ s_c / len(src)
    u, sv, vt = np.linalg.svd(cov)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt))])
    rot = u @ d @ vt
    scale = np.trace(np.diag(sv) @ d) / (s_c**2).sum(1).mean()
    return scale * src @ rot.T + (mu_d - scale * rot @ mu_s)


def _scipy_aligned(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Second reference: scipy's proper-rotation fit (align_vectors) of the centred sets, then
    the scale."""
    s_c, d_c = src - src.mean(0), dst - dst.mean(0)
    rot, _ = Rotation.align_vectors(d_c, s_c)
    r = rot.apply(s_c)
    scale = (r * d_c).sum() / (s_c**2).sum()
    return scale * r + dst.mean(0)


def _random_pose(rng: np.random.Generator, b: int, j: int) -> np.ndarray:
    return rng.normal(scale=0.4, size=(b, j, 3))


def _similarity(rng: np.random.Generator, x: np.ndarray, scale: float) -> np.ndarray:
    rot = Rotation.random(random_state=rng).as_matrix()
    return scale * x @ rot.T + rng.normal(scale=3.0, size=3)


# --- MPJPE --------------------------------------------------------------------------------------


def test_mpjpe_matches_numpy():
    rng = np.random.default_rng(0)
    p, g = _random_pose(rng, 4, 17), _random_pose(rng, 4, 17)
    ref = np.linalg.norm(p - g, axis=-1).mean(-1)
    np.testing.assert_allclose(
        mpjpe(torch.from_numpy(p), torch.from_numpy(g)).numpy(), ref, rtol=1e-12
    )
    # Root-aligned with the mean of two hips as root.
    pr, gr = p - p[:, [1, 2]].mean(1, keepdims=True), g - g[:, [1, 2]].mean(1, keepdims=True)
    ref_root = np.linalg.norm(pr - gr, axis=-1).mean(-1)
    np.testing.assert_allclose(
        mpjpe(torch.from_numpy(p), torch.from_numpy(g), root=[1, 2]).numpy(), ref_root, rtol=1e-12
    )


def test_mpjpe_root_alignment_ignores_translation():
    rng = np.random.default_rng(1)
    p, g = torch.from_numpy(_random_pose(rng, 3, 24)), torch.from_numpy(_random_pose(rng, 3, 24))
    shifted = p + torch.tensor([1.0, -2.0, 0.5])
    torch.testing.assert_close(mpjpe(shifted, g, root=0), mpjpe(p, g, root=0))
    assert (mpjpe(shifted, g) > mpjpe(p, g)).any()


def test_mpjpe_valid_mask_equals_subset():
    rng = np.random.default_rng(2)
    p, g = torch.from_numpy(_random_pose(rng, 2, 10)), torch.from_numpy(_random_pose(rng, 2, 10))
    valid = torch.ones(2, 10, dtype=torch.bool)
    valid[:, [3, 7]] = False
    keep = [i for i in range(10) if i not in (3, 7)]
    torch.testing.assert_close(mpjpe(p, g, valid=valid), mpjpe(p[:, keep], g[:, keep]))
    torch.testing.assert_close(pa_mpjpe(p, g, valid=valid), pa_mpjpe(p[:, keep], g[:, keep]))


def test_shape_errors_name_the_culprit():
    with pytest.raises(ValueError, match=r"pred has shape \(4, 3\)"):
        mpjpe(torch.zeros(4, 3), torch.zeros(4, 3))
    with pytest.raises(ValueError, match="same shape"):
        pa_mpjpe(torch.zeros(1, 4, 3), torch.zeros(1, 5, 3))
    with pytest.raises(ValueError, match="valid has shape"):
        mpjpe(torch.zeros(1, 4, 3), torch.zeros(1, 4, 3), valid=torch.ones(4))
    with pytest.raises(ValueError, match="root"):
        mpjpe(torch.zeros(1, 4, 3), torch.zeros(1, 4, 3), root=9)


# --- PA-MPJPE -----------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), joints=st.integers(4, 30), scale=st.floats(0.05, 20.0))
def test_pa_mpjpe_zero_for_similarity_copy(seed, joints, scale):
    rng = np.random.default_rng(seed)
    g = _random_pose(rng, 1, joints)
    p = _similarity(rng, g[0], scale)[None]
    err = pa_mpjpe(torch.from_numpy(p), torch.from_numpy(g)).item()
    assert err < 1e-9
    # And the aligned copy lands on the truth, even in float32.
    aligned = procrustes_align(torch.from_numpy(p).float(), torch.from_numpy(g).float())
    assert (aligned.double() - torch.from_numpy(g)).abs().max() < 1e-4


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    joints=st.integers(4, 30),
    scale=st.floats(0.05, 20.0),
    noise=st.floats(0.0, 0.5),
)
def test_pa_mpjpe_invariant_to_similarity_of_prediction(seed, joints, scale, noise):
    rng = np.random.default_rng(seed)
    g = _random_pose(rng, 1, joints)
    p = g + rng.normal(scale=noise, size=g.shape)
    p_moved = _similarity(rng, p[0], scale)[None]
    a = pa_mpjpe(torch.from_numpy(p), torch.from_numpy(g)).item()
    b = pa_mpjpe(torch.from_numpy(p_moved), torch.from_numpy(g)).item()
    assert b == pytest.approx(a, rel=1e-7, abs=1e-10)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), joints=st.integers(4, 30), batch=st.integers(1, 5))
def test_pa_mpjpe_matches_numpy_and_scipy_references(seed, joints, batch):
    rng = np.random.default_rng(seed)
    g = _random_pose(rng, batch, joints)
    p = np.stack(
        [_similarity(rng, g[i] + rng.normal(scale=0.1, size=g[i].shape), 1.3) for i in range(batch)]
    )
    got = pa_mpjpe(torch.from_numpy(p), torch.from_numpy(g)).numpy()
    ref_umeyama = np.array(
        [np.linalg.norm(_umeyama_numpy(p[i], g[i]) - g[i], axis=-1).mean() for i in range(batch)]
    )
    ref_scipy = np.array(
        [np.linalg.norm(_scipy_aligned(p[i], g[i]) - g[i], axis=-1).mean() for i in range(batch)]
    )
    np.testing.assert_allclose(got, ref_umeyama, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(got, ref_scipy, rtol=1e-6, atol=1e-9)


def test_reflection_is_not_allowed():
    """A mirrored pose is a different pose: proper rotations only (scipy.spatial.procrustes would
    accept the mirror image, since it allows any orthogonal matrix)."""
    rng = np.random.default_rng(5)
    g = _random_pose(rng, 1, 12)
    mirrored = g * np.array([-1.0, 1.0, 1.0])
    _, _, disparity = scipy_procrustes(g[0], mirrored[0])
    assert disparity < 1e-20  # orthogonal Procrustes: reflection makes it perfect
    err = pa_mpjpe(torch.from_numpy(mirrored), torch.from_numpy(g)).item()
    ref = np.linalg.norm(_umeyama_numpy(mirrored[0], g[0]) - g[0], axis=-1).mean()
    assert err > 0.05 and err == pytest.approx(ref, rel=1e-9)
    sim = similarity_procrustes(torch.from_numpy(mirrored), torch.from_numpy(g))
    assert torch.linalg.det(sim.rotation).item() == pytest.approx(1.0, abs=1e-12)


def test_degenerate_prediction_gives_finite_error():
    g = torch.from_numpy(_random_pose(np.random.default_rng(6), 2, 8))
    p = torch.zeros_like(g)  # every joint at one point: scale collapses to 0
    err = pa_mpjpe(p, g)
    assert torch.isfinite(err).all()
    ref = (g - g.mean(1, keepdim=True)).norm(dim=-1).mean(-1)  # best fit is the centroid
    torch.testing.assert_close(err, ref)


def test_pa_mpjpe_gradient_is_finite():
    rng = np.random.default_rng(7)
    g = torch.from_numpy(_random_pose(rng, 2, 17)).float()
    p = (
        g + 0.05 * torch.randn(g.shape, generator=torch.Generator().manual_seed(0))
    ).requires_grad_(True)
    pa_mpjpe(p, g).sum().backward()
    assert torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0


# --- vertex error -------------------------------------------------------------------------------


def test_vertex_error_alignments():
    rng = np.random.default_rng(8)
    g = torch.from_numpy(_random_pose(rng, 2, 200))
    p = g + 0.01 * torch.from_numpy(rng.normal(size=g.shape))
    moved = p + torch.tensor([0.3, 0.0, -0.2])
    np.testing.assert_allclose(
        vertex_error(p, g).numpy(), (p - g).norm(dim=-1).mean(-1).numpy(), rtol=1e-12
    )
    assert (vertex_error(moved, g) > vertex_error(p, g)).all()
    torch.testing.assert_close(
        vertex_error(moved, g, align="translation"), vertex_error(p, g, align="translation")
    )
    rotated = torch.from_numpy(_similarity(rng, moved[0].numpy(), 2.0))[None].expand(2, -1, -1)
    torch.testing.assert_close(
        vertex_error(rotated, g[:1].expand(2, -1, -1), align="procrustes")[0],
        vertex_error(p[:1], g[:1], align="procrustes")[0],
    )
    with pytest.raises(ValueError, match="align must be"):
        vertex_error(p, g, align="icp")


def test_points_without_truth_may_be_nan_where_valid_leaves_them_out():
    """A joint with no truth is often NaN: leaving it out with `valid` equals dropping it (a
    weight of 0 did not cancel NaN: MPJPE read NaN and PA-MPJPE's SVD failed)."""
    g = torch.Generator().manual_seed(0)
    pred, gt = (
        torch.randn(2, 24, 3, generator=g, dtype=torch.float64),
        torch.randn(2, 24, 3, generator=g, dtype=torch.float64),
    )
    valid = torch.ones(2, 24, dtype=torch.bool)
    valid[0, 5] = False
    holed = gt.clone()
    holed[0, 5] = float("nan")
    keep = [j for j in range(24) if j != 5]
    for metric in (
        mpjpe,
        pa_mpjpe,
        lambda p, t, valid=None: vertex_error(p, t, "translation", valid),
    ):
        got = metric(pred, holed, valid=valid)
        assert torch.isfinite(got).all()
        torch.testing.assert_close(got[0], metric(pred[:1, keep], gt[:1, keep])[0])


def test_root_aligned_mpjpe_with_the_root_left_out_still_aligns():
    """`valid` says which joints are scored; the root still places each pose (zeroing left-out
    points before taking the root turned root alignment off)."""
    gt = torch.randn(1, 24, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    valid = torch.ones(1, 24, dtype=torch.bool)
    valid[0, 0] = False
    assert float(mpjpe(gt + torch.tensor([5.0, 0, 0], dtype=torch.float64), gt, 0, valid)) < 1e-9


def test_pa_mpjpe_is_undefined_below_three_joints():
    """A similarity fits one or two points exactly: a pose 5 m off with one or two joints
    scored reported PA-MPJPE 0 (a perfect score) instead of no score."""
    gt = torch.randn(3, 24, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    pred = gt + torch.randn(3, 24, 3, generator=torch.Generator().manual_seed(3)).double() + 5
    valid = torch.zeros(3, 24, dtype=torch.bool)
    valid[0, :1], valid[1, :2], valid[2, :3] = True, True, True
    got = pa_mpjpe(pred, gt, valid)
    assert torch.isnan(got[:2]).all() and float(got[2]) > 0.01


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_one_non_finite_sample_is_nan_not_the_whole_batch(bad):
    """A scored joint that is NaN or Inf in one sample gives that sample NaN, as mpjpe does;
    the batched SVD failed for the whole batch (LinAlgError)."""
    g = torch.Generator().manual_seed(4)
    gt = torch.randn(3, 17, 3, generator=g, dtype=torch.float64)
    pred = gt + 0.05 * torch.randn(3, 17, 3, generator=g, dtype=torch.float64)
    broken = pred.clone()
    broken[1, 3] = bad
    for metric in (pa_mpjpe, lambda p, t: vertex_error(p, t, "procrustes")):
        got = metric(broken, gt)
        assert torch.isnan(got[1])
        torch.testing.assert_close(got[[0, 2]], metric(pred[[0, 2]], gt[[0, 2]]))
    assert torch.isnan(similarity_procrustes(gt, broken).scale[1])

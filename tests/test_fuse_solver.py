"""The body fit's machinery: the joints-only forward equals the body model, its analytic Jacobian
equals finite differences, the linearised energy's gradient equals autograd's, and the Schur
step of the Levenberg-Marquardt solver equals a dense solve of the same normal equations."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.body import load_body_model
from gst.body.kinematics import MarkerSkeleton, left_jacobian, rodrigues
from gst.body.markers import MarkerModel
from gst.body.rotations import axis_angle_to_matrix
from gst.fuse.fit import _limits_tensor, _neighbours
from gst.fuse.objective import Coverage, Floor, Points, Views, Weights, cost, linearise
from gst.fuse.solver import BodyState, levenberg_marquardt, schur_step

torch.set_num_threads(1)
D = torch.float64


@pytest.fixture(scope="module")
def body():
    return load_body_model("anny", dtype=D)


@pytest.fixture(scope="module")
def skeleton(body):
    return MarkerSkeleton(body, MarkerModel.load(), 10)


def _state(B, seed, scale=0.6):
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(B, 10, generator=g, dtype=D),
        rodrigues(torch.randn(B, 3, generator=g, dtype=D)),
        torch.randn(B, 23, 3, generator=g, dtype=D) * scale,
        torch.randn(B, 3, generator=g, dtype=D),
    )


def test_forward_matches_the_body_model_and_marker_model(body, skeleton):
    betas, root, theta, transl = _state(5, 0)
    X, J, G, local = skeleton.forward(betas, root, theta, transl)
    out = body(betas, theta, root, transl, vertex_ids=torch.zeros(1, dtype=torch.long),
               return_transforms=True)  # fmt: skip
    np.testing.assert_allclose(J, out.joints, atol=1e-12)
    np.testing.assert_allclose(G, out.joint_transforms[..., :3, :3], atol=1e-12)
    np.testing.assert_allclose(X, MarkerModel.load().positions(out), atol=1e-6)  # float32 table
    np.testing.assert_allclose(local, axis_angle_to_matrix(theta), atol=1e-12)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(0.0, 1.2))
def test_marker_jacobian_equals_finite_differences(skeleton, seed, scale):
    B = 2
    betas, root, theta, transl = _state(B, seed, scale)
    X, *_, dX = skeleton.forward(betas, root, theta, transl, jacobian=True)
    p0 = torch.cat([torch.zeros(B, 3, dtype=D), transl, theta.reshape(B, 69), betas], 1)

    def f(p):
        return skeleton.forward(
            p[:, 75:], rodrigues(p[:, :3]) @ root, p[:, 6:75].reshape(B, 23, 3), p[:, 3:6]
        )[0]

    eps = 1e-6
    num = torch.stack(
        [(f(p0 + eps * e) - f(p0 - eps * e)) / (2 * eps) for e in torch.eye(85, dtype=D)], -1
    )
    np.testing.assert_allclose(dX, num, atol=2e-7)


def test_left_jacobian_first_order():
    g = torch.Generator().manual_seed(3)
    v = torch.randn(50, 3, generator=g, dtype=D) * 1.5
    v[0] = 0.0
    dv = torch.randn(50, 3, generator=g, dtype=D) * 1e-6
    lhs = rodrigues(v + dv)
    rhs = rodrigues((left_jacobian(v) @ dv[..., None])[..., 0]) @ rodrigues(v)
    assert (lhs - rhs).abs().max() < 1e-11


@pytest.mark.parametrize("fn", [rodrigues, left_jacobian])
def test_float32_rotations_keep_their_small_angle_terms(fn):
    """In float32, 1 - cos t is 0 below about 3e-4 rad and t - sin t keeps few digits below
    0.1 rad: the closed forms lost the first-order term of the left Jacobian (errors ~1e-4,
    a thousand times float32's rounding) at angles the body fit's steps make."""
    g = torch.Generator().manual_seed(5)
    axes = torch.nn.functional.normalize(torch.randn(400, 3, generator=g, dtype=D), dim=-1)
    angles = 10 ** torch.linspace(-7, 0.5, 400, dtype=D)
    v = axes * angles[:, None]
    ref = fn(v)
    err = (fn(v.float()).double() - ref).abs().amax(dim=(-1, -2))
    assert float(err.max()) < 1e-6, float(angles[err.argmax()])


def _problem(body, skeleton, B=4, C=3, seed=0):
    """Random cameras looking at random bodies, landmarks with noise, two people."""
    betas, root, theta, transl = _state(B, seed, 0.5)
    transl = transl * 0.3
    X, *_ = skeleton.forward(betas, root, theta, transl)
    g = torch.Generator().manual_seed(seed + 1)
    ang = torch.rand(C, generator=g, dtype=D) * 6.28
    K = torch.tensor([[500.0, 0, 128], [0, 500.0, 128], [0, 0, 1]], dtype=D)
    Rts = []
    for a in ang:
        pos = torch.stack([4 * torch.cos(a), 4 * torch.sin(a), torch.tensor(1.0, dtype=D)])
        z = -pos / pos.norm()
        x = torch.linalg.cross(z, torch.tensor([0, 0, 1.0], dtype=D))
        x = x / x.norm()
        y = torch.linalg.cross(z, x)
        R = torch.stack([x, y, z])
        Rts.append(torch.cat([R, (-R @ pos)[:, None]], 1))
    Rt = torch.stack(Rts)[None].expand(B, C, 3, 4)
    Kb = K.expand(B, C, 3, 3)
    ev = Views(Kb, Rt, torch.zeros(B, C, X.shape[1], 2, dtype=D),
               torch.ones(B, C, X.shape[1], dtype=D),
               torch.full((B, C), 1.5, dtype=D), torch.full((B,), 3.0, dtype=D))  # fmt: skip
    uv, _ = ev.project(X)
    ev.uv = uv + torch.randn(uv.shape, generator=g, dtype=D) * 2.0
    lo, hi = _limits_tensor(body)
    w = Weights(0.5, 50.0, 1.0, 1 / 0.02, lo, hi)
    nb = _neighbours([np.arange(B // 2), np.arange(B - B // 2)])
    person = torch.as_tensor(np.repeat([0, 1], [B // 2, B - B // 2]))
    return ev, w, nb, person, (betas, root, theta, transl)


def test_gradient_of_the_linearisation_equals_autograd(body, skeleton):
    ev, w, nb, person, (betas, root, theta, transl) = _problem(body, skeleton, B=6)
    theta = theta * 2.5  # well outside the joint limits: every term is active
    B = theta.shape[0]
    pts = Points(
        torch.randn(B, 33, 3, dtype=D) * 0.1 + transl[:, None], torch.rand(B, 33, dtype=D), 0.05
    )
    X0, *_ = skeleton.forward(betas, root, theta, transl)
    up = torch.tensor([0.3, -0.2, 0.9], dtype=D)
    up = up / up.norm()
    clearance = torch.rand(33, generator=torch.Generator().manual_seed(5), dtype=D) * 0.1
    floor = Floor(up, float((X0 @ up).median()), clearance, 1e4)  # about half the markers below
    assert 0 < (floor.depth(X0) > 0).float().mean() < 1
    for evidence in (ev, [ev, pts], [ev, floor]):
        X, _, _, local, dX = skeleton.forward(betas, root, theta, transl, jacobian=True)
        H, g = linearise(X, dX, theta, local, evidence, nb, w)
        d = torch.zeros(B, 3, dtype=D, requires_grad=True)
        tr = transl.clone().requires_grad_(True)
        th = theta.clone().requires_grad_(True)
        be = betas.clone().requires_grad_(True)
        Xa, _, _, la = skeleton.forward(be, rodrigues(d) @ root, th, tr)
        cost(Xa, th, la, evidence, nb, w).sum().backward()
        auto = torch.cat([d.grad, tr.grad, th.grad.reshape(B, 69), be.grad], 1)
        np.testing.assert_allclose(2 * g, auto, rtol=1e-6, atol=1e-6 * auto.abs().max())
        assert torch.allclose(H, H.transpose(1, 2))
        assert torch.linalg.eigvalsh(H).min() > -1e-6 * H.abs().max()
    # the person's own marker offsets as unknowns too (their columns come last)
    off = torch.randn(B, 33, 3, dtype=D) * 0.02 + skeleton.offsets
    X, _, G, local, dX = skeleton.forward(betas, root, theta, transl, True, off)
    H, g = linearise(X, dX, theta, local, ev, nb, w, G[:, skeleton.frame])
    o = off.clone().requires_grad_(True)
    th = theta.clone().requires_grad_(True)
    Xa, _, _, la = skeleton.forward(betas, root, th, transl, offsets=o)
    cost(Xa, th, la, ev, nb, w).sum().backward()
    auto = torch.cat([th.grad.reshape(B, 69), o.grad.reshape(B, 99)], 1)
    mine = torch.cat([g[:, 6:75], g[:, 85:]], 1)
    np.testing.assert_allclose(2 * mine, auto, rtol=1e-6, atol=1e-6 * auto.abs().max())
    assert torch.allclose(H, H.transpose(1, 2))


def test_gradient_of_the_silhouette_term_equals_autograd(body, skeleton):
    """The coverage term's linearisation (distance and its gradient sampled from the fields)
    against autograd through the sampling, on a field whose bilinear interpolation is exact (a
    plane): the gradient channels are then the interpolant's true derivatives."""
    ev, w, nb, person, (betas, root, theta, transl) = _problem(body, skeleton, B=6)
    ev.K = ev.K + torch.tensor([[0, 0, 256.0], [0, 0, 256.0], [0, 0, 0]], dtype=D)
    B, C, s, crop = 6, 3, 32, 768  # every projection well inside the crop
    centres = (torch.arange(s, dtype=D) + 0.5) * crop / s
    plane = 0.3 * centres[None, :] + 0.2 * centres[:, None] + 5.0  # crop px, u along columns
    fields = torch.stack([plane, torch.full_like(plane, 0.3), torch.full_like(plane, 0.2)])
    weight = torch.rand(B, C, generator=torch.Generator().manual_seed(3), dtype=D)
    cov = Coverage(ev, fields.expand(B * C, 3, s, s), weight, torch.full((B,), 4.0, dtype=D), crop)
    X, _, _, local, dX = skeleton.forward(betas, root, theta, transl, jacobian=True)
    uv, _ = ev.project(X)
    assert uv.min() > crop / s and uv.max() < crop * (1 - 1 / s)  # inside the field's cells
    for evidence in (cov, [ev, cov]):
        H, g = linearise(X, dX, theta, local, evidence, nb, w)
        d = torch.zeros(B, 3, dtype=D, requires_grad=True)
        tr = transl.clone().requires_grad_(True)
        th = theta.clone().requires_grad_(True)
        Xa, _, _, la = skeleton.forward(betas, rodrigues(d) @ root, th, tr)
        cost(Xa, th, la, evidence, nb, w).sum().backward()
        auto = torch.cat([d.grad, tr.grad, th.grad.reshape(B, 69)], 1)
        np.testing.assert_allclose(2 * g[:, :75], auto, rtol=1e-6, atol=1e-6 * auto.abs().max())
        assert torch.linalg.eigvalsh(H).min() > -1e-6 * H.abs().max()


def test_the_silhouette_fields_are_sampled_at_pixel_centres(body, skeleton):
    """The fields pool the crop's pixels (integer centres, edges at -0.5): cell j's centre lies
    at crop pixel (j + 0.5) f - 0.5. A plane stored at those centres is read back exactly at
    every projection (the sampling was half a crop pixel off: the plane's 0.5 px x (0.3 + 0.2)
    gradient showed as 0.25 px of distance)."""
    ev, w, nb, person, (betas, root, theta, transl) = _problem(body, skeleton, B=6)
    ev.K = ev.K + torch.tensor([[0, 0, 256.0], [0, 0, 256.0], [0, 0, 0]], dtype=D)
    B, C, s, crop = 6, 3, 32, 768
    centres = (torch.arange(s, dtype=D) + 0.5) * crop / s - 0.5
    plane = 0.3 * centres[None, :] + 0.2 * centres[:, None] + 5.0
    fields = torch.stack([plane, torch.full_like(plane, 0.3), torch.full_like(plane, 0.2)])
    weight = torch.ones(B, C, dtype=D)
    cov = Coverage(ev, fields.expand(B * C, 3, s, s), weight, torch.full((B,), 4.0, dtype=D), crop)
    X, *_ = skeleton.forward(betas, root, theta, transl)
    dist, grad, uv, _ = cov.sample(X)
    assert uv.min() > crop / s and uv.max() < crop * (1 - 1 / s)
    want = (0.3 * uv[..., 0] + 0.2 * uv[..., 1] + 5.0) * ev.scale[..., None]
    np.testing.assert_allclose(dist, want, atol=1e-9)


def test_schur_step_equals_the_dense_solve(body, skeleton):
    """The step that eliminates the frames (Schur complement) solves the full system of all
    frames and people's betas at once (undamped); damped, its frame rows still hold."""
    ev, w, nb, person, (betas, root, theta, transl) = _problem(body, skeleton, B=5, seed=5)
    shared = betas[:2]  # one shape per person
    X, _, _, local, dX = skeleton.forward(shared[person], root, theta, transl, jacobian=True)
    H, g = linearise(X, dX, theta, local, ev, nb, w)
    wb, B, P, npp = 0.3, 5, 75, 2
    n = B * P + npp * 10
    A, b = torch.zeros(n, n, dtype=D), torch.zeros(n, dtype=D)
    for i in range(B):
        k = int(person[i])
        fi, pi = slice(P * i, P * i + P), slice(B * P + 10 * k, B * P + 10 * k + 10)
        A[fi, fi] += H[i, :P, :P]
        A[fi, pi] += H[i, :P, P:]
        A[pi, fi] += H[i, P:, :P]
        A[pi, pi] += H[i, P:, P:]
        b[fi] += g[i, :P]
        b[pi] += g[i, P:]
    for k in range(npp):
        pi = slice(B * P + 10 * k, B * P + 10 * k + 10)
        A[pi, pi] += wb * torch.eye(10, dtype=D)
        b[pi] += wb * shared[k]
    dp, db = schur_step(H, g, shared, person, torch.zeros(npp, dtype=D), wb)
    step = torch.cat([dp.reshape(-1), db.reshape(-1)])
    np.testing.assert_allclose(step, -torch.linalg.solve(A, b), rtol=1e-6, atol=1e-9)
    lam = torch.tensor([0.01, 0.1], dtype=D)
    dp, db = schur_step(H, g, shared, person, lam, wb)
    for i in range(B):
        fi = slice(P * i, P * i + P)
        A[fi, fi] += torch.diag(lam[person[i]] * torch.diagonal(H[i, :P, :P]))
    r = A[: B * P] @ torch.cat([dp.reshape(-1), db.reshape(-1)]) + b[: B * P]
    assert r.abs().max() < 1e-6 * b.abs().max()


def test_levenberg_marquardt_lowers_the_energy_monotonically(body, skeleton):
    ev, w, nb, person, (betas, root, theta, transl) = _problem(body, skeleton, B=4, seed=9)
    state = BodyState(root, transl + 0.05, torch.zeros_like(theta), torch.zeros_like(betas[:2]))

    def energy(s):
        X, _, _, local = skeleton.forward(s.betas[person], s.root, s.theta, s.transl)
        return cost(X, s.theta, local, ev, nb, w)

    def lin(s):
        X, _, _, local, dX = skeleton.forward(
            s.betas[person], s.root, s.theta, s.transl, jacobian=True
        )
        return linearise(X, dX, s.theta, local, ev, nb, w)

    totals = [float(energy(state).sum())]
    for _ in range(4):
        state = levenberg_marquardt(state, person, energy, lin, 2, 0.3)
        totals.append(float(energy(state).sum() + 0.3 * (state.betas**2).sum()))
    assert all(b <= a for a, b in zip(totals, totals[1:], strict=False)), totals
    assert totals[-1] < 0.5 * totals[0]

"""Numerical stability of LBS: extreme and near-degenerate poses on the synthetic SMPL-layout
body (with pose correctives) and on the open Anny default. Outputs and gradients (pose, shape,
translation) must stay finite; periodic and degenerate inputs must behave as documented."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.body import BodyModel, load_body_model
from gst.body.joint_limits import JOINT_LIMITS_DEG, euler_xyz_to_matrix
from gst.body.random_model import random_body_data
from gst.body.rotations import rot6d_to_matrix
from gst.body.skeleton import SMPL_JOINT_NAMES

_NAMES = SMPL_JOINT_NAMES[1:]
_LO = torch.tensor(
    [[r[0] for r in JOINT_LIMITS_DEG[n]] for n in _NAMES], dtype=torch.float64
).deg2rad()
_HI = torch.tensor(
    [[r[1] for r in JOINT_LIMITS_DEG[n]] for n in _NAMES], dtype=torch.float64
).deg2rad()


@pytest.fixture(scope="module")
def synthetic():
    return BodyModel(random_body_data(num_vertices=800, with_posedirs=True, seed=3))


@pytest.fixture(scope="module")
def anny():
    """The default body (built once per machine, then read from the cache in a fraction of a
    second)."""
    return load_body_model("anny")


def _limit_corner(bits: np.ndarray) -> torch.Tensor:
    """(1, 23, 3, 3): every joint angle at its lower (0) or upper (1) anatomical limit."""
    b = torch.as_tensor(bits, dtype=torch.float64).reshape(23, 3)
    return euler_xyz_to_matrix(_LO + b * (_HI - _LO))[None]


def _assert_finite_lbs(body: BodyModel, body_pose, global_orient, betas=None, transl=None):
    """Pose, backpropagate a loss touching every output, check everything is finite."""
    dtype = body.dtype
    pose = body_pose.to(dtype).clone().requires_grad_(True)
    orient = global_orient.to(dtype).clone().requires_grad_(True)
    b = pose.shape[0]
    betas = (
        (torch.zeros(b, body.num_betas) if betas is None else betas)
        .to(dtype)
        .clone()
        .requires_grad_(True)
    )
    transl = (
        (torch.zeros(b, 3) if transl is None else transl).to(dtype).clone().requires_grad_(True)
    )
    out = body(betas, pose, orient, transl, return_transforms=True)
    for name in ("vertices", "joints", "joint_transforms", "vertex_transforms"):
        assert torch.isfinite(getattr(out, name)).all(), f"{name} not finite"
    g = torch.Generator().manual_seed(0)
    loss = sum(
        (getattr(out, k) * torch.randn(getattr(out, k).shape, generator=g, dtype=dtype)).sum()
        for k in ("vertices", "joints", "vertex_transforms")
    )
    loss.backward()
    for name, t in (
        ("body_pose", pose),
        ("global_orient", orient),
        ("betas", betas),
        ("transl", transl),
    ):
        assert t.grad is not None and torch.isfinite(t.grad).all(), f"gradient of {name} not finite"
    return out


@pytest.mark.parametrize("which", ["synthetic", "anny"])
@pytest.mark.parametrize("corner", ["all_lower", "all_upper", "alternating"])
def test_every_joint_at_its_limits(request, which, corner):
    body = request.getfixturevalue(which)
    bits = {"all_lower": np.zeros(69), "all_upper": np.ones(69), "alternating": np.arange(69) % 2}[
        corner
    ]
    out = _assert_finite_lbs(body, _limit_corner(bits), torch.zeros(1, 3))
    # Bent to its limits, the body stays body-sized (no joint flies off): within 2.5 m of the
    # pelvis.
    assert (out.joints - out.joints[:, :1]).norm(dim=-1).max() < 2.5


@settings(max_examples=15, deadline=None)
@given(st.lists(st.integers(0, 1), min_size=69, max_size=69))
def test_random_limit_corners_synthetic(synthetic, bits):
    _assert_finite_lbs(synthetic, _limit_corner(np.array(bits)), torch.zeros(1, 3))


def _axis_angles(norm: float, b: int = 2, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    axes = torch.nn.functional.normalize(
        torch.randn(b, 24, 3, generator=g, dtype=torch.float64), dim=-1
    )
    return axes * norm


@pytest.mark.parametrize("which", ["synthetic", "anny"])
@pytest.mark.parametrize("norm", [0.0, 1e-12, math.pi - 1e-6, math.pi, 1e3, 1e6, 1e20])
def test_extreme_axis_angle_norms(request, which, norm):
    """Zero, half-turn and huge axis-angle norms on every joint at once (float32 model)."""
    body = request.getfixturevalue(which)
    aa = _axis_angles(norm)
    _assert_finite_lbs(body, aa[:, 1:], aa[:, 0])


def test_whole_turns_do_not_change_the_mesh(synthetic):
    """theta + 2 pi k poses the body exactly like theta (float64 model, k up to 1e5 turns)."""
    body64 = BodyModel(synthetic.data, dtype=torch.float64)
    aa = _axis_angles(1.0, b=1, seed=1) * torch.rand(1, 24, 1, dtype=torch.float64) * math.pi
    turns = torch.randint(-(10**5), 10**5, (1, 24, 1), generator=torch.Generator().manual_seed(2))
    wound = aa + aa / aa.norm(dim=-1, keepdim=True) * 2 * math.pi * turns.double()
    a = body64(None, aa[:, 1:], aa[:, 0])
    b = body64(None, wound[:, 1:], wound[:, 0])
    torch.testing.assert_close(b.vertices, a.vertices, atol=1e-8, rtol=0)


@pytest.mark.parametrize("which", ["synthetic", "anny"])
@pytest.mark.parametrize("six", ["zero", "collinear", "antiparallel", "tiny"])
def test_degenerate_6d_poses_through_lbs(request, which, six):
    """The network's 6D output goes through Gram-Schmidt into LBS; degenerate 6D gives a
    non-rotation but everything downstream, gradients included, stays finite."""
    body = request.getfixturevalue(which)
    base = torch.tensor([0.3, -1.0, 0.2])
    x = {
        "zero": torch.zeros(6),
        "collinear": torch.cat([base, 2 * base]),
        "antiparallel": torch.cat([base, -base]),
        "tiny": torch.tensor([1e-20, 0, 0, 0, 1e-20, 0]),
    }[six]
    six_d = x.expand(2, 24, 6).clone().requires_grad_(True)
    R = rot6d_to_matrix(six_d)
    out = body(torch.zeros(2, body.num_betas), R[:, 1:], R[:, 0], return_transforms=True)
    assert torch.isfinite(out.vertices).all() and torch.isfinite(out.vertex_transforms).all()
    (out.vertices.square().sum() + out.vertex_transforms.sum()).backward()
    assert torch.isfinite(six_d.grad).all()


@pytest.mark.parametrize("which", ["synthetic", "anny"])
def test_extreme_shapes_and_translations(request, which):
    """Shape coefficients far outside their range and translations of kilometres (float32)."""
    body = request.getfixturevalue(which)
    betas = torch.tensor(
        [[10.0] * body.num_betas, [-10.0] * body.num_betas, [1e3] * body.num_betas]
    )
    transl = torch.tensor([[0.0, 0.0, 0.0], [1e3, -1e3, 5e3], [0.0, 0.0, 1e-30]])
    pose = _limit_corner(np.ones(69)).expand(3, -1, -1, -1)
    _assert_finite_lbs(body, pose, torch.zeros(3, 3), betas, transl)


@pytest.mark.parametrize("b", [1, 256])
def test_batches_of_one_and_256(synthetic, b):
    """Batch items are independent: row 0 of a 256 batch equals the same pose alone."""
    g = torch.Generator().manual_seed(4)
    u = torch.rand(b, 23, 3, generator=g, dtype=torch.float64)
    pose = euler_xyz_to_matrix(_LO + u * (_HI - _LO)).float()
    orient = torch.randn(b, 3, generator=g)
    out = _assert_finite_lbs(synthetic, pose, orient)
    single = synthetic(None, pose[:1], orient[:1])
    torch.testing.assert_close(out.vertices[:1].detach(), single.vertices, atol=1e-5, rtol=0)


def test_non_finite_pose_is_refused_with_its_name(synthetic):
    pose = torch.zeros(2, 23, 3)
    pose[1, 4, 0] = float("nan")
    with pytest.raises(ValueError, match=r"body_pose contains NaN or Inf \(batch items \[1\]\)"):
        synthetic(None, pose, torch.zeros(2, 3))
    with pytest.raises(ValueError, match="global_orient contains NaN or Inf"):
        synthetic(None, torch.zeros(1, 23, 3), torch.tensor([[float("inf"), 0.0, 0.0]]))

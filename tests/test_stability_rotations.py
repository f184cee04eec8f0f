"""Numerical stability of the rotation conversions: round trips through every representation
we use (axis-angle, rotation matrix, 6D, wxyz quaternion) against scipy, and finite values and
gradients at the degenerate inputs: zero and half-turn angles, huge angle norms, zero and
(near-)collinear 6D pairs, zero and huge quaternions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion
from scipy.spatial.transform import Rotation

from gst.body.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_rot6d,
    rot6d_to_matrix,
)
from gst.render.projection import quats_to_rotmats

finite = st.floats(-10.0, 10.0, allow_nan=False, width=64)
unit_axis = (
    arrays(np.float64, (3,), elements=finite)
    .filter(lambda v: np.linalg.norm(v) > 1e-3)
    .map(lambda v: v / np.linalg.norm(v))
)
# Zero, tiny (Taylor branch), ordinary, and half-turn angles (where the axis sign flips).
angles = st.one_of(
    st.just(0.0),
    st.floats(0.0, 1e-6),
    st.floats(1e-6, np.pi),
    st.floats(np.pi - 1e-6, np.pi),
    st.just(np.pi),
)


def _wxyz_from_scipy(rot: Rotation) -> np.ndarray:
    x, y, z, w = rot.as_quat()
    return np.array([w, x, y, z])


def _same_quaternion(a: np.ndarray, b: np.ndarray, atol: float) -> bool:
    """q and -q are the same rotation."""
    return min(np.abs(a - b).max(), np.abs(a + b).max()) <= atol


@settings(max_examples=60, deadline=None)
@given(unit_axis, angles)
def test_round_trip_through_every_representation(axis, angle):
    """axis-angle -> matrix -> quaternion -> matrix -> 6D -> matrix -> axis-angle, each step
    compared with scipy's rotation (float64)."""
    ref = Rotation.from_rotvec(axis * angle)
    R = axis_angle_to_matrix(torch.tensor(axis * angle))
    np.testing.assert_allclose(R.numpy(), ref.as_matrix(), atol=1e-12)

    q = rotation_matrix_to_quaternion(R, eps=1e-12)  # what gst.model.assemble uses
    assert _same_quaternion(q.numpy(), _wxyz_from_scipy(ref), atol=1e-9)
    for to_matrix in (
        quaternion_to_rotation_matrix,
        quats_to_rotmats,
    ):  # kornia's, the rasteriser's
        np.testing.assert_allclose(to_matrix(q).numpy(), ref.as_matrix(), atol=1e-9)

    R6 = rot6d_to_matrix(matrix_to_rot6d(quats_to_rotmats(q)))
    np.testing.assert_allclose(R6.numpy(), ref.as_matrix(), atol=1e-9)

    back = matrix_to_axis_angle(R6)
    assert abs(float(back.norm()) - angle) < 1e-7
    np.testing.assert_allclose(
        Rotation.from_rotvec(back.numpy()).as_matrix(), ref.as_matrix(), atol=1e-7
    )


@settings(max_examples=50, deadline=None)
@given(unit_axis, angles)
def test_float32_round_trip_stays_close(axis, angle):
    """The network and the body model run in float32: errors stay at float32 rounding."""
    ref = Rotation.from_rotvec(axis * angle).as_matrix()
    R = axis_angle_to_matrix(torch.tensor(axis * angle, dtype=torch.float32))
    np.testing.assert_allclose(R.numpy(), ref, atol=2e-6)
    q = rotation_matrix_to_quaternion(R, eps=1e-12)
    np.testing.assert_allclose(quats_to_rotmats(q).numpy(), ref, atol=5e-6)
    back = matrix_to_axis_angle(rot6d_to_matrix(matrix_to_rot6d(R)))
    np.testing.assert_allclose(
        Rotation.from_rotvec(back.double().numpy()).as_matrix(), ref, atol=5e-5
    )


@settings(max_examples=60, deadline=None)
@given(unit_axis, st.floats(0.0, 2 * np.pi), st.integers(-(10**6), 10**6))
def test_axis_angle_is_two_pi_periodic_for_huge_norms(axis, angle, turns):
    """theta and theta + 2 pi k are the same rotation, for k up to a million turns."""
    total = angle + 2 * np.pi * turns
    R = axis_angle_to_matrix(torch.tensor(axis * total))
    ref = Rotation.from_rotvec(axis * angle).as_matrix()
    # 2 pi k carries a relative rounding error of 1e-16, i.e. up to ~1e-9 rad at a million turns.
    np.testing.assert_allclose(R.numpy(), ref, atol=1e-8)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    "norm", [0.0, 1e-30, 1e-8, math.pi - 1e-7, math.pi, 2 * math.pi, 1e3, 1e6, 1e19, 1e20, 1e30]
)
def test_axis_angle_extremes_give_rotations_and_finite_gradients(norm, dtype):
    """Above ~1.8e19 rad float32 used to overflow (theta^2) into NaN."""
    aa = (torch.tensor([0.3, -0.5, 0.8], dtype=dtype) / math.sqrt(0.98) * norm).requires_grad_(True)
    R = axis_angle_to_matrix(aa)
    assert torch.isfinite(R).all()
    eye = torch.eye(3, dtype=dtype)
    assert (R @ R.T - eye).abs().max() < (1e-5 if dtype == torch.float32 else 1e-12)
    assert torch.linalg.det(R).item() == pytest.approx(1.0, abs=1e-5)
    (R * torch.arange(9.0, dtype=dtype).view(3, 3)).sum().backward()
    assert torch.isfinite(aa.grad).all()


@settings(max_examples=50, deadline=None)
@given(
    unit_axis,
    st.one_of(st.floats(0.0, 1e-5), st.floats(np.pi - 1e-5, np.pi)),
    st.sampled_from([torch.float32, torch.float64]),
)
def test_matrix_to_axis_angle_and_quaternion_gradients_are_finite(axis, angle, dtype):
    """Near the identity and near a half turn (the two branch points of the inverse maps)."""
    R = torch.tensor(
        Rotation.from_rotvec(axis * angle).as_matrix(), dtype=dtype, requires_grad=True
    )
    w = torch.arange(1.0, 4.0, dtype=dtype)
    (matrix_to_axis_angle(R) * w).sum().backward()
    assert torch.isfinite(R.grad).all()
    R.grad = None
    (
        rotation_matrix_to_quaternion(R, eps=1e-12) * torch.arange(1.0, 5.0, dtype=dtype)
    ).sum().backward()
    assert torch.isfinite(R.grad).all()


def _near_collinear(a1: np.ndarray, factor: float, eps: float, direction: np.ndarray) -> np.ndarray:
    return np.concatenate([a1, factor * a1 + eps * direction])


@settings(max_examples=60, deadline=None)
@given(
    arrays(np.float64, (3,), elements=st.floats(-1e3, 1e3, allow_nan=False)),
    st.floats(-1e3, 1e3, allow_nan=False),
    st.sampled_from([0.0, 1e-30, 1e-12, 1e-7, 1e-4]),
    arrays(np.float64, (3,), elements=st.floats(-1, 1, allow_nan=False)),
    st.sampled_from([torch.float32, torch.float64]),
)
def test_near_collinear_and_zero_6d_are_finite_with_finite_gradients(
    a1, factor, eps, direction, dtype
):
    x = torch.tensor(_near_collinear(a1, factor, eps, direction), dtype=dtype, requires_grad=True)
    R = rot6d_to_matrix(x)
    assert torch.isfinite(R).all()
    (R * torch.arange(9.0, dtype=dtype).view(3, 3)).sum().backward()
    assert torch.isfinite(x.grad).all()
    # Whenever the two columns are clearly independent the result is a proper rotation. (Columns
    # shorter than the Gram-Schmidt floor, 1e-12, count as degenerate by design: that floor
    # bounds the gradient.)
    a2 = factor * a1 + eps * direction
    n1, n2, n12 = np.linalg.norm(a1), np.linalg.norm(a2), np.linalg.norm(np.cross(a1, a2))
    if n1 > 1e-6 and n12 / n1 > 1e-6 and n12 > 1e-3 * n1 * n2:
        Rd = R.detach().double()
        assert (Rd @ Rd.T - torch.eye(3, dtype=torch.float64)).abs().max() < 1e-4
        assert torch.linalg.det(Rd).item() == pytest.approx(1.0, abs=1e-4)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_degenerate_6d_batch_gradients(dtype):
    """A batch mixing zero, parallel, antiparallel and tiny 6D vectors (what an untrained or
    diverging pose head can emit): outputs and gradients finite, rows independent."""
    x = torch.tensor(
        [
            [0, 0, 0, 0, 0, 0],
            [1, 2, 3, 2, 4, 6],
            [1, 2, 3, -1, -2, -3],
            [1e-20, 0, 0, 0, 1e-20, 0],
            [0, 0, 0, 1, 0, 0],
            [1, 0, 0, 0, 0, 0],
            [1, 0, 0, 0, 1, 0],
        ],
        dtype=dtype,
        requires_grad=True,
    )
    R = rot6d_to_matrix(x)
    assert torch.isfinite(R).all()
    R.square().sum().backward()
    assert torch.isfinite(x.grad).all()
    torch.testing.assert_close(R[-1], torch.eye(3, dtype=dtype))  # a good row is unaffected


@pytest.mark.parametrize("scale", [0.0, 1e-30, 1e-6, 1.0, 1e12, 1e30])
def test_quaternion_to_matrix_extremes(scale):
    """The rasteriser normalises quaternions itself: zero means identity, any scale is the same
    rotation, gradients are finite."""
    q0 = torch.tensor([[0.3, -0.2, 0.9, 0.1]])
    q = (q0 * scale).requires_grad_(True)
    R = quats_to_rotmats(q)
    assert torch.isfinite(R).all()
    expected = (
        torch.eye(3)[None] if scale < 1e-20 else quats_to_rotmats(q0)
    )  # far below QUAT_EPS: identity
    torch.testing.assert_close(R, expected, atol=1e-5, rtol=0)
    (R * torch.arange(9.0).view(1, 3, 3)).sum().backward()
    assert torch.isfinite(q.grad).all()


@pytest.mark.parametrize("norm", [1e-14, 5e-13, 9e-13])
def test_a_quaternion_shorter_than_quat_eps_is_the_identity(norm):
    """As conventions.QUAT_EPS says (and the gsplat backend and the PLY writer do): it was a
    non-rotation (|q| = 5e-13 scaled two axes by 0.5) with gradients of 1e12."""
    q = torch.tensor([[0.0, norm, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    R = quats_to_rotmats(q)
    torch.testing.assert_close(R[0], torch.eye(3, dtype=torch.float64), atol=1e-12, rtol=0)
    R.sum().backward()
    assert q.grad.abs().max() == 0

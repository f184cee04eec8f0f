"""Rotation helpers against scipy's Rotation and numpy's QR (independent references)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from gst.body.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_rot6d,
    rot6d_to_matrix,
)

finite = st.floats(-10.0, 10.0, allow_nan=False, width=64)
vec3 = arrays(np.float64, (3,), elements=finite)
unit_axis = vec3.filter(lambda v: np.linalg.norm(v) > 1e-3).map(lambda v: v / np.linalg.norm(v))
# Angles spanning tiny (Taylor branch), ordinary and near-half-turn rotations.
angles = st.one_of(st.floats(0.0, 1e-3), st.floats(1e-3, np.pi), st.floats(np.pi - 1e-4, np.pi))


@settings(max_examples=200, deadline=None)
@given(unit_axis, angles)
def test_axis_angle_to_matrix_matches_scipy(axis, angle):
    rotvec = axis * angle
    ours = axis_angle_to_matrix(torch.tensor(rotvec)).numpy()
    ref = Rotation.from_rotvec(rotvec).as_matrix()
    np.testing.assert_allclose(ours, ref, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(unit_axis, angles)
def test_matrix_to_axis_angle_inverts(axis, angle):
    R = torch.tensor(Rotation.from_rotvec(axis * angle).as_matrix())
    aa = matrix_to_axis_angle(R)
    # Near a half turn the axis sign is arbitrary; compare the rotation and the angle.
    assert abs(float(aa.norm()) - angle) < 1e-7
    np.testing.assert_allclose(axis_angle_to_matrix(aa).numpy(), R.numpy(), atol=1e-7)
    if 1e-6 < angle < np.pi - 1e-3:
        np.testing.assert_allclose(aa.numpy(), axis * angle, atol=1e-7)


@settings(max_examples=200, deadline=None)
@given(vec3, vec3)
def test_rot6d_is_gram_schmidt_of_columns(a1, a2):
    """HMR2's convention: the 6 numbers are columns 0 and 1 before orthonormalisation, i.e. the
    Q factor of QR([a1 a2]) with a positive diagonal."""
    m = np.stack([a1, a2], axis=1)
    if np.linalg.svd(m, compute_uv=False)[-1] < 1e-3 * max(1.0, np.abs(m).max()):
        return  # (near) degenerate pair: no unique rotation
    R = rot6d_to_matrix(torch.tensor(np.concatenate([a1, a2]))).numpy()
    q, r = np.linalg.qr(m)
    q = q * np.sign(np.diag(r))
    np.testing.assert_allclose(R[:, :2], q, atol=1e-9)
    np.testing.assert_allclose(R[:, 2], np.cross(q[:, 0], q[:, 1]), atol=1e-9)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)


@settings(max_examples=100, deadline=None)
@given(unit_axis, angles)
def test_rot6d_round_trip(axis, angle):
    R = torch.tensor(Rotation.from_rotvec(axis * angle).as_matrix())
    six = matrix_to_rot6d(R)
    np.testing.assert_array_equal(six.numpy(), np.concatenate([R[:, 0].numpy(), R[:, 1].numpy()]))
    np.testing.assert_allclose(rot6d_to_matrix(six).numpy(), R.numpy(), atol=1e-12)


def test_batched_shapes_and_float32():
    x = torch.randn(4, 5, 6)
    assert rot6d_to_matrix(x).shape == (4, 5, 3, 3)
    assert rot6d_to_matrix(x).dtype == torch.float32
    assert matrix_to_rot6d(torch.eye(3).expand(2, 3, 3)).shape == (2, 6)
    assert axis_angle_to_matrix(torch.zeros(2, 7, 3)).shape == (2, 7, 3, 3)
    assert matrix_to_axis_angle(torch.eye(3).expand(2, 7, 3, 3)).shape == (2, 7, 3)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 1.0, np.pi - 1e-6])
def test_gradients_are_finite(angle):
    aa = torch.tensor([[0.3, -0.5, 0.8]], dtype=torch.float64)
    aa = (aa / aa.norm() * angle).requires_grad_(True)
    R = axis_angle_to_matrix(aa)
    (R * torch.randn(3, 3, dtype=torch.float64)).sum().backward()
    assert torch.isfinite(aa.grad).all()
    back = matrix_to_axis_angle(R.detach().requires_grad_(True))
    assert torch.isfinite(back).all()
    six = torch.tensor([[1.0, 0.0, 0.0, 1.0, 1e-12, 0.0]], requires_grad=True)
    rot6d_to_matrix(six).sum().backward()
    assert torch.isfinite(six.grad).all()


def test_degenerate_6d_is_finite():
    assert torch.isfinite(rot6d_to_matrix(torch.zeros(6))).all()
    assert torch.isfinite(rot6d_to_matrix(torch.tensor([1.0, 0, 0, 2.0, 0, 0]))).all()


@pytest.mark.parametrize(
    "fn, shape",
    [
        (rot6d_to_matrix, (3, 5)),
        (matrix_to_rot6d, (3, 4)),
        (axis_angle_to_matrix, (2, 4)),
        (matrix_to_axis_angle, (3,)),
    ],
)
def test_wrong_shapes_raise(fn, shape):
    with pytest.raises(ValueError, match="must have shape"):
        fn(torch.zeros(shape))

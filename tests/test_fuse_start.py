"""The fit's start (gst.fuse.start) on inputs the body model is not needed for: a person one
camera sees whose landmarks' pixels are partly not numbers."""

from __future__ import annotations

import numpy as np

from calibration.camera import look_at_rotation
from gst.fuse.observations import PersonObservations
from gst.fuse.start import rigid_start


def _one_camera_person(T: int = 3) -> PersonObservations:
    """A person 5 m in front of one camera, 33 landmarks spread over 1.7 m of height."""
    rng = np.random.default_rng(0)
    pos, target = np.array([5.0, 0.0, 1.5]), np.array([0.0, 0.0, 1.0])
    R = look_at_rotation(pos, target)
    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    X = target + np.c_[rng.normal(0, 0.2, (33, 2)), np.linspace(-0.9, 0.8, 33)]
    q = (K @ (X @ R.T - R @ pos).T).T
    uv = q[:, :2] / q[:, 2:]
    return PersonObservations(
        7, np.arange(T), np.broadcast_to(uv, (T, 1, 33, 2)).copy(), np.ones((T, 1, 33)),
        np.broadcast_to(K, (T, 1, 3, 3)).copy(),
        np.broadcast_to(np.c_[R, -R @ pos], (T, 1, 3, 4)).copy(), np.ones((T, 1)),
        np.zeros((T, 1), np.int64),
    )  # fmt: skip


def test_single_view_start_with_unread_hips_is_finite():
    """The one view's hips have NaN pixels (confidence kept): the start stands at the readable
    landmarks instead (was: every frame's start NaN, then numpy's 'attempt to get argmin of an
    empty sequence', naming no person)."""
    p = _one_camera_person()
    p.uv[:, :, [23, 24]] = np.nan
    rest = np.random.default_rng(1).normal(0, 0.3, (33, 3))
    R, c, _ = rigid_start(p, None, rest, np.zeros(3), 0.005)
    assert np.isfinite(R).all() and np.isfinite(c).all()
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    assert np.linalg.norm(c[:, :2], axis=1).max() < 1.0  # near the person, not at the camera


def test_landmarks_without_pixels_are_not_readable():
    """Confidence on NaN pixels is no reading: such a person is left out by the fuse stage's
    readable test (was: readable, then a failed start)."""
    p = _one_camera_person()
    assert p.readable
    p.uv[:] = np.nan
    assert not p.readable


def test_single_view_start_straight_below_an_overhead_camera_is_a_rotation():
    """A camera 6 m up looking straight down, the person's hips on its optical axis: the
    horizontal direction towards the camera is zero, and the start's 'rotation' had a zero
    column (det 0)."""
    T, K = 2, np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    R = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # looks down -Z, image x along +X
    pos = np.array([0.0, 0.0, 6.0])
    uv = np.c_[np.full(33, 320.0), np.linspace(150, 330, 33)]
    uv[23], uv[24] = (310.0, 240.0), (330.0, 240.0)  # hips about the principal point
    p = PersonObservations(
        3, np.arange(T), np.broadcast_to(uv, (T, 1, 33, 2)).copy(), np.ones((T, 1, 33)),
        np.broadcast_to(K, (T, 1, 3, 3)).copy(),
        np.broadcast_to(np.c_[R, -R @ pos], (T, 1, 3, 4)).copy(), np.ones((T, 1)),
        np.zeros((T, 1), np.int64),
    )  # fmt: skip
    rest = np.random.default_rng(1).normal(0, 0.3, (33, 3))
    Rs, c, _ = rigid_start(p, None, rest, np.zeros(3), 0.005)
    assert np.isfinite(Rs).all() and np.isfinite(c).all()
    np.testing.assert_allclose(np.linalg.det(Rs), 1.0, atol=1e-9)
    np.testing.assert_allclose(
        Rs @ Rs.transpose(0, 2, 1), np.broadcast_to(np.eye(3), Rs.shape), atol=1e-9
    )

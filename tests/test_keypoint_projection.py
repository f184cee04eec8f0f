"""Projection of skeleton points into a camera (gst.data.keypoints.geometry.project): the lens
model is only trusted near the image, so points far outside it are not projected."""

from __future__ import annotations

import numpy as np
from crowd_people import rig
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.data.keypoints.geometry import FIELD_MARGIN, project

RIG = rig("dome", 7)


def _world(cam, pixel, depth):
    """World point seen at undistorted pinhole `pixel` (2,) and `depth` metres by `cam`."""
    ray = np.linalg.solve(cam.K, np.array([pixel[0], pixel[1], 1.0]))
    return cam.R.T @ (ray * depth - cam.t)


@settings(max_examples=60, deadline=None)
@given(
    st.integers(0, len(RIG.cameras) - 1),
    st.floats(0.0, 1.0),
    st.floats(0.0, 1.0),
    st.floats(1.0, 12.0),
)
def test_points_in_the_image_project_as_the_camera_does(c, fx, fy, depth):
    cam = RIG.cameras[c]
    X = _world(cam, (fx * cam.width, fy * cam.height), depth)[None]
    uv, front = project(cam, X)
    assert front.all()
    np.testing.assert_allclose(uv, cam.project(X), atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(
    st.integers(0, len(RIG.cameras) - 1),
    st.sampled_from([-1.0, 1.0]),
    st.floats(FIELD_MARGIN + 0.05, 50.0),
    st.floats(0.0, 1.0),
    st.floats(0.05, 12.0),
)
def test_points_far_beside_the_image_are_not_projected(c, side, beyond, along, depth):
    """A point in front of the camera but far outside its field of view (beside the camera,
    as a wrong skeleton's limb can be) gets no pixel: the distortion polynomial would put it
    anywhere, and a crop built around it would be millions of pixels wide."""
    cam = RIG.cameras[c]
    u = cam.width * (1 + beyond) if side > 0 else -cam.width * beyond
    X = _world(cam, (u, along * cam.height), depth)[None]
    uv, front = project(cam, X)
    assert front.all() and np.isnan(uv).all()


def test_points_behind_the_camera_and_nan_give_nan():
    cam = RIG.cameras[0]
    behind = _world(cam, (cam.width / 2, cam.height / 2), -2.0)
    X = np.stack([behind, np.full(3, np.nan), _world(cam, (10.0, 10.0), 3.0)])
    uv, front = project(cam, X)
    assert front.tolist() == [False, False, True]
    assert np.isnan(uv[:2]).all() and np.isfinite(uv[2]).all()


def test_a_crop_ignores_landmarks_far_outside_the_image():
    """The extraction's crop covers the person's landmarks as well as their mask, but only as
    far as the field the lens model holds: a landmark a million pixels away must not make the
    crop a million pixels wide (it did, on the five-person crowd scenes)."""
    from gst.data.extract.crops import crop_person

    cam = RIG.cameras[0]
    frame = np.zeros((cam.height, cam.width, 3), np.uint8)
    mask = np.zeros((cam.height, cam.width), bool)
    mask[300:350, 20:40] = True  # a person in the lower left corner
    sane = crop_person(frame, mask, cam, 64, 1.0, np.array([15.0, 280.0, 45.0, 355.0]))
    wild = crop_person(frame, mask, cam, 64, 1.0, np.array([-5.9e6, 134.0, 338.0, 1.7e6]))
    side = (1 + 2 * FIELD_MARGIN) * max(cam.width, cam.height) * 1.25  # the crop's enlargement
    assert sane[4][2] < 100 and wild[4][2] < side


def test_a_distortion_polynomial_folds_far_points_back_into_the_image():
    """Why the field check exists: with barrel distortion (k1 < 0) a point beside the camera,
    twice the focal length off-axis, lands back inside the image on the other side. Camera.
    in_field says it is not in the field; geometry.project and the fuse overlay skip it."""
    from calibration import Camera

    K = np.array([[500.0, 0, 240], [0, 500.0, 180], [0, 0, 1]])
    cam = Camera.create("wide", K, np.array([-0.3, 0, 0, 0, 0]), np.eye(3), np.zeros(3), 480, 360)
    beside = np.array([[2.0, 0.0, 1.0]])  # normalised x = 2: pinhole u = 1240 on a 480 px image
    u, v = cam.project(beside)[0]
    assert 0 <= u < 480 and 0 <= v < 360  # folded back: drawn at u = 40
    assert not cam.in_field(beside).any()
    assert np.isnan(project(cam, beside)[0]).all()
    near = np.array([[0.2, 0.1, 1.0]])
    assert cam.in_field(near).all()
    np.testing.assert_allclose(project(cam, near)[0], cam.project(near))

"""A single-view person read as standing (gst.data.keypoints.standing): the guess lies on every
landmark's own ray, puts the ankles where they are, and the body within its own depth."""

import numpy as np
import pytest
from crowd_people import person, rig
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.data.keypoints.instances import PersonInstance
from gst.data.keypoints.standing import ANKLES, AnkleHeight, standing_skeleton

RIG = rig("dome", 5, seed=2)
UP = np.array([0.0, 0.0, 1.0])


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(-1.0, 1.0),
    y=st.floats(-1.0, 1.0),
    heading=st.floats(-np.pi, np.pi),
    cam=st.integers(0, len(RIG) - 1),
)
def test_the_guess_stands_on_the_ankles_rays_and_within_the_bodys_depth(x, y, heading, cam):
    camera = RIG[cam]
    truth = person(x, y, heading)
    uv = camera.project(truth)
    inst = PersonInstance.create(np.c_[uv, np.ones(len(uv))])
    ankle_height = float(truth[list(ANKLES)].mean(axis=0) @ UP)
    guess = standing_skeleton(camera, inst, UP, ankle_height, 0.3)
    assert guess is not None and np.isfinite(guess).all()
    # every landmark on its own ray: it projects back onto its pixel (OpenCV's projection)
    np.testing.assert_allclose(camera.project(guess), uv, atol=1e-6)
    # the ankles where they are (to the few mm between the mean pixel's ray and the mean's),
    # the rest within the body's own depth
    np.testing.assert_allclose(
        guess[list(ANKLES)].mean(axis=0), truth[list(ANKLES)].mean(axis=0), atol=0.03
    )
    # A landmark off the upright plane moves along its own ray, by more the steeper the camera
    # looks down; measured in depth (along the camera's horizontal direction to the person) it
    # stays within the body's half-depth around the ankles.
    ankles = truth[list(ANKLES)].mean(axis=0)
    towards = (ankles - camera.center) - ((ankles - camera.center) @ UP) * UP
    towards /= np.linalg.norm(towards)
    assert np.abs((guess - truth) @ towards).max() < 0.35


def test_no_guess_without_ankles_or_above_the_horizon():
    camera = RIG[0]
    truth = person(0.0, 0.0)
    lm = np.c_[camera.project(truth), np.ones(33)]
    hidden = lm.copy()
    hidden[list(ANKLES), 2] = 0.0
    assert standing_skeleton(camera, PersonInstance.create(hidden), UP, 0.08, 0.3) is None
    # ankles at a height above the camera: their ray never comes up to it in front
    above = float(camera.center @ UP) + 1.0
    assert standing_skeleton(camera, PersonInstance.create(lm), UP, above, 0.3) is None


def test_ankle_height_waits_for_four_ankles_and_takes_the_median():
    h = AnkleHeight(UP)
    assert h.value is None
    h.add(person(0, 0))
    assert h.value is None  # two ankles
    h.add(person(1, 0))
    assert h.value == pytest.approx(0.08)
    nan = np.full((33, 3), np.nan)
    h.add(nan)  # nothing seen: nothing added
    assert h.value == pytest.approx(0.08)


def test_no_guess_straight_below_a_camera():
    """A camera looking straight down at someone's ankles: no upright plane through them faces
    it, and the guess was a skeleton of NaN only (not None), which `CrowdTracker` then looked
    for in every camera as a person standing apart."""
    from calibration.camera import Camera

    R = np.diag([1.0, -1.0, -1.0])  # looking down the world's -z
    K = [[400, 0, 240], [0, 400, 180], [0, 0, 1]]
    top = Camera.create("top", K, [], R, -R @ [0, 0, 5.0], 480, 360)
    lm = np.c_[top.project(person(0.0, 0.0)), np.ones(33)]
    lm[list(ANKLES), :2] = [[240.0, 175.0], [240.0, 185.0]]  # their mean: the principal point
    assert standing_skeleton(top, PersonInstance.create(lm), UP, 0.08, 0.3) is None

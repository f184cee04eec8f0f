"""The floor under the fitted bodies (gst.fuse.floor, the fit's Floor term)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.body import load_body_model
from gst.body.kinematics import MarkerSkeleton
from gst.body.markers import MarkerModel
from gst.fuse.fit import fit_people
from gst.fuse.floor import (
    FLOOR_SEARCH_M,
    FOOT_MARKERS,
    contact_height,
    floor_clearance,
    stands_on,
    world_floor,
)
from gst.fuse.triangulate import triangulate_person
from tests.fuse_fixtures import make_capture, observations

UP = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def capture_and_body():
    body = load_body_model("anny")
    return make_capture(body, n_people=2, n_frames=6, n_cams=4, seed=1), body


def _feet(markers: MarkerModel) -> np.ndarray:
    return np.array([any(n.endswith(f) for f in FOOT_MARKERS) for n in markers.names])


@settings(max_examples=25, deadline=None)
@given(
    height=st.floats(-3.0, 3.0),
    lift=st.lists(st.floats(0.0, 0.3), min_size=1, max_size=20),
    tilt=st.floats(0.0, 1.0),
)
def test_contact_height_is_the_median_lowest_foot_along_up(height, lift, tilt):
    up = np.array([0.0, np.sin(tilt), np.cos(tilt)])
    side = np.cross(up, [1.0, 0.0, 0.0])
    pts = np.full((len(lift), 33, 3), np.nan)
    for t, d in enumerate(lift):
        # the lower foot at `height + d` along up, the other 0.2 m higher, sideways anywhere
        pts[t, [29, 31]] = (height + d) * up + side * t
        pts[t, [30, 32]] = (height + d + 0.2) * up
    assert contact_height([pts, None], up) == pytest.approx(height + np.median(lift), abs=1e-9)
    floor, h = world_floor([pts], up)
    assert (floor == 0.0) == (abs(h) <= FLOOR_SEARCH_M)
    assert floor is None or floor == 0.0


def test_no_feet_no_floor():
    pts = np.full((4, 33, 3), np.nan)
    pts[:, 0] = 1.0  # a nose, no feet
    assert world_floor([pts, None], UP) == (None, pytest.approx(float("nan"), nan_ok=True))
    assert world_floor([], UP)[0] is None


def test_a_world_centred_on_a_camera_has_no_floor_at_zero(capture_and_body):
    """Feet triangulated 2 m below the origin (a world whose origin is a camera) are no floor at
    height 0; the same feet in the capture's z-up world are."""
    feet = capture_and_body[0].markers.reshape(-1, 33, 3)
    assert world_floor([feet], UP)[0] == 0.0
    floor, h = world_floor([feet - [0, 0, 2.0]], UP)
    assert floor is None and h < -1.5


def test_fit_keeps_the_feet_above_the_floor(capture_and_body):
    """Landmarks that put every foot 6 cm too low (the views' feet bias): without a floor the
    fitted foot markers sink below their rest height above the ground; with it they stay within
    the tolerance. A floor nobody comes near changes nothing."""
    capture, body = capture_and_body
    markers = MarkerModel.load()
    feet = _feet(markers)
    sunk = capture.markers.copy()
    sunk[..., feet, 2] -= 0.06
    people = observations(dataclasses.replace(capture, markers=sunk), noise_px=0.5, seed=4)
    tris = [triangulate_person(p) for p in people]
    # the ground under the true feet: the lowest true foot marker less its rest clearance
    rest = _rest_markers(body, markers)
    clearance = floor_clearance(body, markers, rest, 0.0)
    ground = float((capture.markers[..., 2] - clearance).min())

    def depth(fits, tolerance):
        X = np.stack([f.markers for f in fits])
        allowed = ground + np.maximum(clearance - tolerance, 0) * feet
        return float((allowed - X[..., 2]).max())

    free = fit_people(body, markers, people, tris, fps=30.0)
    held = fit_people(body, markers, people, tris, fps=30.0, floor=(UP, ground))
    assert depth(free, 0.01) > 0.03  # sunk by several cm
    assert depth(held, 0.01) < 0.005
    far = fit_people(body, markers, people, tris, fps=30.0, floor=(UP, ground - 1.0))
    for a, b in zip(free, far, strict=True):
        np.testing.assert_allclose(a.joints, b.joints, atol=1e-6)


def test_someone_on_lower_ground_keeps_their_legs(capture_and_body):
    """The lab's two people stand on a force plate at height 0, its bystander on the room's
    floor 0.18 m below it: the floor held her feet up and her fitted shank shrank from 0.35 to
    0.19 m. A person whose own soles stand far from the floor is fitted without it; the others
    are held as before."""
    capture, body = capture_and_body
    markers = MarkerModel.load()
    lower = capture.markers.copy()
    lower[1, ..., 2] -= 0.18  # the second person stands on ground 18 cm lower
    people = observations(dataclasses.replace(capture, markers=lower), noise_px=0.5, seed=4)
    tris = [triangulate_person(p) for p in people]
    rest = _rest_markers(body, markers)
    clearance = floor_clearance(body, markers, rest, 0.0)
    ground = float((capture.markers[0, ..., 2] - clearance).min())  # under the first person
    assert stands_on(tris[0].points, UP, ground) and not stands_on(tris[1].points, UP, ground)
    free = fit_people(body, markers, people, tris, fps=30.0)
    held = fit_people(body, markers, people, tris, fps=30.0, floor=(UP, ground))
    np.testing.assert_allclose(held[1].joints, free[1].joints, atol=1e-6)  # no floor for her
    # ... and the fit of each is its own: the first person's, fitted alone, is the same (to
    # 20 um: batched float32 kernels round differently with one person than with two, 6 um
    # measured with torch 2.13; a floor wrongly dropped or kept moves the feet by cm)
    alone = fit_people(body, markers, people[:1], tris[:1], fps=30.0, floor=(UP, ground))
    np.testing.assert_allclose(held[0].joints, alone[0].joints, atol=2e-5)
    assert stands_on(None, UP, ground)  # no feet triangulated: the floor, as before


def _rest_markers(body, markers) -> np.ndarray:
    sk = MarkerSkeleton(body, markers, 10, torch.float64)
    zeros = torch.zeros
    X, *_ = sk.forward(
        zeros(1, 10, dtype=torch.float64), torch.eye(3, dtype=torch.float64)[None],
        zeros(1, 23, 3, dtype=torch.float64), zeros(1, 3, dtype=torch.float64),
    )  # fmt: skip
    return X[0].numpy()

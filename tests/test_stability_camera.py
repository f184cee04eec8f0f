"""Camera round trips as hypothesis properties (the fixed-rig versions are in
test_calib_camera.py / test_calib_formats.py): rig files written and read back for random
cameras (tiny, ordinary and half-turn rotations, every distortion length, skew), unprojected
rays against world points, and a world-frame change undone by its inverse."""

from __future__ import annotations

import tempfile
from pathlib import Path

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.camera import Camera, Rig
from calibration.formats import read_rig, write_rig
from tests.test_calib_formats import assert_same_rig

finite = dict(allow_nan=False, allow_infinity=False)
DIST_SCALES = np.array(
    [0.2, 0.05, 0.002, 0.002, 0.01, 0.05, 0.01, 0.005, 0.002, 0.001, 0.002, 0.001, 0.01, 0.01]
)


@st.composite
def rotations(draw) -> np.ndarray:
    axis = np.array(draw(st.lists(st.floats(-1, 1, **finite), min_size=3, max_size=3)))
    if np.linalg.norm(axis) < 1e-3:
        axis = np.array([0.0, 0.0, 1.0])
    angle = draw(
        st.one_of(
            st.just(0.0), st.floats(0, 1e-5), st.floats(0, np.pi), st.floats(np.pi - 1e-5, np.pi)
        )
    )
    R, _ = cv2.Rodrigues(axis / np.linalg.norm(axis) * angle)
    return R


@st.composite
def cameras(draw, name: str, dist_lengths=(0, 4, 5, 8, 12, 14), skew: bool = True) -> Camera:
    R = draw(rotations())
    t = np.array(draw(st.lists(st.floats(-20, 20, **finite), min_size=3, max_size=3)))
    w, h = draw(st.integers(16, 4096)), draw(st.integers(16, 4096))
    fx, fy = draw(st.floats(50, 8000, **finite)), draw(st.floats(50, 8000, **finite))
    s = draw(st.floats(-20, 20, **finite)) if skew else 0.0
    K = [
        [fx, s, draw(st.floats(0, w, **finite))],
        [0, fy, draw(st.floats(0, h, **finite))],
        [0, 0, 1],
    ]
    n = draw(st.sampled_from(dist_lengths))
    dist = (
        np.array(draw(st.lists(st.floats(-1, 1, **finite), min_size=n, max_size=n)))
        * DIST_SCALES[:n]
    )
    return Camera.create(name, K, dist, R, t, w, h, {"serial": name.upper()})


@st.composite
def rigs(draw, **kw) -> Rig:
    n = draw(st.integers(1, 3))
    return Rig(tuple(draw(cameras(f"cam{i}", **kw)) for i in range(n)), up=(0.0, 0.0, 1.0))


@settings(max_examples=30, deadline=None)
@given(rigs())
def test_rig_json_round_trip_is_bit_exact(rig):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "rig.json"
        write_rig(rig, path, "rig")
        back = read_rig(path, "rig")
    assert back.names == rig.names and back.up == rig.up
    for a, b in zip(rig, back, strict=True):
        assert (a.width, a.height) == (b.width, b.height) and b.meta == a.meta
        for field in ("K", "R", "t", "dist"):
            assert np.array_equal(getattr(a, field), getattr(b, field)), field


@settings(max_examples=20, deadline=None)
@given(rigs(dist_lengths=(5,), skew=False), st.sampled_from(["panoptic", "colmap", "pose2sim"]))
def test_other_formats_round_trip(rig, fmt):
    """Formats that store OpenCV's five-term model (COLMAP: FULL_OPENCV) without skew."""
    suffix = {"panoptic": ".json", "colmap": "", "pose2sim": ".toml"}[fmt]
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"rig{suffix}"
        write_rig(rig, path, fmt)
        back = read_rig(path, fmt)
    assert_same_rig(rig, back, atol=1e-7)


@settings(max_examples=40, deadline=None)
@given(cameras("c"), st.integers(0, 2**32 - 1))
def test_unprojected_rays_point_at_the_world_points(cam, seed):
    """Points in front of the camera inside its field of view: the unit ray unproject() returns
    for their pixel is the direction from the camera centre to the point."""
    rng = np.random.default_rng(seed)
    # Normalised coordinates within +-0.5 keep every drawn distortion monotonic (invertible).
    xy = rng.uniform(-0.5, 0.5, (8, 2)) * np.array([cam.width / cam.fx, cam.height / cam.fy]).clip(
        max=1.0
    )
    z = rng.uniform(0.2, 50.0, 8)
    pts = (np.c_[xy * z[:, None], z] - cam.t) @ cam.R  # camera -> world
    rays = cam.unproject(cam.project(pts))
    expected = pts - cam.center
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(rays, expected, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(cam.to_camera(pts), np.c_[xy * z[:, None], z], atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(
    rigs(),
    rotations(),
    st.lists(st.floats(-100, 100, **finite), min_size=3, max_size=3),
    st.floats(1e-3, 1e3, **finite),
)
def test_world_frame_change_and_its_inverse(rig, Rw, tw, scale):
    tw = np.array(tw)
    moved = rig.transformed(Rw, tw, scale)
    back = moved.transformed(Rw.T, -Rw.T @ tw / scale, 1.0 / scale)
    for a, b in zip(rig, back, strict=True):
        np.testing.assert_allclose(b.R, a.R, atol=1e-9)
        np.testing.assert_allclose(b.t, a.t, atol=1e-9 * max(1.0, np.abs(a.t).max() * 1e3))
        np.testing.assert_allclose(b.center, a.center, atol=1e-6)
    np.testing.assert_allclose(back.up, rig.up, atol=1e-12)

"""Crop geometry: the stored K_crop (with the camera's R, t) must describe every crop pixel."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration import Camera
from gst.data.association import project_fast
from gst.data.crop import (
    CropBox,
    crop_camera,
    crop_intrinsics,
    extract_crop,
    hmr_crop_box,
    undistorted_box,
)


def _camera(dist, skew=0.0, w=640, h=480, f=520.0) -> Camera:
    R = cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))[0]
    return Camera.create(
        "c",
        [[f, skew, w / 2 - 3.2], [0, f * 1.01, h / 2 + 2.1], [0, 0, 1]],
        dist,
        R,
        [0.1, -0.2, 4.0],
        w,
        h,
    )


def test_crop_intrinsics_formula_and_pixel_centres():
    K = np.array([[500.0, 0.0, 320.0], [0, 510.0, 240.0], [0, 0, 1]])
    box = CropBox(100.0, 50.0, 200.0)
    Kc = crop_intrinsics(K, box, 100)
    s = 0.5
    assert np.allclose(
        Kc, [[250, 0, (320 - 100) * s - 0.5], [0, 255, (240 - 50) * s - 0.5], [0, 0, 1]]
    )
    # A crop of side S mapped to S pixels is a pure shift: full pixel (u, v) -> (u - x0, v - y0)
    # when the box edge sits on a pixel edge (x0 = u_edge - 0.5).
    Kid = crop_intrinsics(K, CropBox(99.5, 49.5, 64.0), 64)
    assert np.allclose(Kid[:2, 2], K[:2, 2] - [99.5 + 0.5, 49.5 + 0.5])


def test_identity_crop_reproduces_pixels_exactly():
    cam = _camera([])
    img = np.random.default_rng(0).integers(0, 255, (cam.height, cam.width, 3), dtype=np.uint8)
    crop = extract_crop(img, cam, CropBox(99.5, 49.5, 64.0), 64)  # edges on pixel edges, scale 1
    assert np.array_equal(crop, img[50:114, 100:164])


def test_hmr_crop_box_is_square_centred_and_scaled():
    b = hmr_crop_box((10.0, 20.0, 50.0, 120.0), 1.2)
    assert b.side == pytest.approx(120.0)
    assert b.x0 + b.side / 2 == pytest.approx(30.0)
    assert b.y0 + b.side / 2 == pytest.approx(70.0)
    with pytest.raises(ValueError, match="x1 > x0"):
        hmr_crop_box((5, 5, 5, 10))


dist_st = st.one_of(
    st.just([]),
    st.tuples(
        st.floats(-0.25, 0.1),
        st.floats(-0.05, 0.05),
        st.floats(-0.002, 0.002),
        st.floats(-0.002, 0.002),
        st.floats(-0.01, 0.01),
    ).map(list),
)


@settings(max_examples=40, deadline=None)
@given(
    dist=dist_st,
    cx=st.floats(150, 490),
    cy=st.floats(120, 360),
    side=st.floats(40, 400),
    size=st.sampled_from([64, 128, 256]),
    skew=st.sampled_from([0.0, 30.0]),
)
def test_full_camera_and_crop_camera_agree(dist, cx, cy, side, size, skew):
    """A 3D point projected with the full (distorted) camera and with the crop camera lands on
    the same image content: drawn as a dot in the full frame, it is found in the crop where the
    crop camera projects it. With skew too: OpenCV's lens maps ignore K[0, 1], and crops of a
    skewed camera were cut several pixels beside their K_crop."""
    cam = _camera(dist, skew)
    box = CropBox(cx - side / 2, cy - side / 2, side)
    ccam = crop_camera(cam, box, size)
    # A world point whose crop projection lies well inside the crop.
    rng = np.random.default_rng(int(cx * 1000) % 2**31)
    j, i = rng.uniform(0.25, 0.75, 2) * size
    ray = ccam.unproject(np.array([[j, i]]))[0]
    X = ccam.center + 3.5 * ray
    uv_full = cam.project(X)[0]
    uv_crop = ccam.project(X)[0]
    assert np.allclose(uv_crop, [j, i], atol=1e-6)
    # Content: a Gaussian dot of radius ~3 crop pixels at the full-image projection.
    sigma = max(1.5, 3.0 * side / size)
    yy, xx = np.mgrid[0 : cam.height, 0 : cam.width]
    dot = np.exp(-((xx - uv_full[0]) ** 2 + (yy - uv_full[1]) ** 2) / (2 * sigma**2)).astype(
        np.float32
    )
    crop = extract_crop(dot, cam, box, size)
    # Sub-pixel peak: centroid of the dot's upper part (symmetric, so unbiased).
    w = np.clip(crop - 0.3 * crop.max(), 0, None)
    ys, xs = np.mgrid[0:size, 0:size]
    peak = np.array([(xs * w).sum() / w.sum(), (ys * w).sum() / w.sum()])
    assert np.linalg.norm(peak - uv_crop) < 0.35, (peak, uv_crop)


def test_crop_is_undistorted_straight_lines_stay_straight():
    """A straight 3D line is curved in the distorted frame but straight in the crop."""
    cam = _camera([-0.3, 0.08, 0, 0, 0])
    box = CropBox(20.0, 20.0, 440.0)
    size = 220
    ccam = crop_camera(cam, box, size)
    P0 = ccam.unproject(np.array([[20.0, 30.0]]), 3.0)[0]
    P1 = ccam.unproject(np.array([[200.0, 190.0]]), 3.0)[0]
    pts = P0 + np.linspace(0, 1, 400)[:, None] * (P1 - P0)
    img = np.zeros((cam.height, cam.width), np.float32)
    for u, v in cam.project(pts):
        cv2.circle(
            img, (int(round(u * 16)), int(round(v * 16))), 2 * 16, 1.0, -1, cv2.LINE_AA, shift=4
        )
    crop = extract_crop(img, cam, box, size)
    ys, xs = np.nonzero(crop > 0.5)
    a, b = np.polyfit(xs, ys, 1)
    assert np.abs(ys - (a * xs + b)).max() < 2.0
    expect = np.polyfit([20.0, 200.0], [30.0, 190.0], 1)
    assert abs(a - expect[0]) < 0.02


def test_undistorted_box_contains_undistorted_points():
    cam = _camera([-0.2, 0.03, 0.001, 0.0, 0.0])
    pts = np.array([[5.0, 5.0], [600.0, 20.0], [320.0, 470.0]])
    box = undistorted_box(cam, pts)
    und = cam.undistort_points(pts) @ cam.K[:2, :2].T + cam.K[:2, 2]
    assert np.all(und >= box[:2]) and np.all(und <= box[2:])
    with pytest.raises(ValueError, match="empty"):
        undistorted_box(cam, np.zeros((0, 2)))


def test_undistorted_box_leaves_out_pixels_the_lens_cannot_invert():
    """A barrel lens (k1 -0.1 at f 1000 on 1920 x 1080) is invertible out to about 258 px left
    of the frame; a landmark box reaching -800 px widened the person's box from 80 to 880 px
    (the iteration's answer there lies on no ray). It is left out; nothing else can be boxed."""
    cam = Camera.create(
        "c", [[1000.0, 0, 959.5], [0, 1000.0, 539.5], [0, 0, 1]], [-0.1, 0, 0, 0, 0],
        np.eye(3), np.zeros(3), 1920, 1080,
    )  # fmt: skip
    person = np.array([[40.0, 200.0], [200.0, 200.0], [40.0, 600.0], [200.0, 600.0]])
    alone = undistorted_box(cam, person)
    assert np.isnan(cam.undistort_points(np.array([[-800.5, 400.0]]), exact_only=True)).all()
    np.testing.assert_allclose(undistorted_box(cam, np.r_[person, [[-800.5, 400.0]]]), alone)
    with pytest.raises(ValueError, match="camera 'c'.*inverted"):
        undistorted_box(cam, np.array([[-800.5, 400.0], [-900.0, 500.0]]))


@settings(max_examples=30, deadline=None)
@given(
    dist=st.one_of(dist_st, st.tuples(*[st.floats(-0.05, 0.05)] * 8).map(list)),
    skew=st.sampled_from([0.0, 5.0, 30.0]),  # H36M's cameras have skew; OpenCV leaves it out
)
def test_fast_projection_matches_opencv(dist, skew):
    cam = _camera(dist, skew=skew)
    pts = np.random.default_rng(1).normal(size=(500, 3)) * [1.5, 1.2, 0.8]
    pts = (
        cam.unproject(
            np.random.default_rng(2).uniform([0, 0], [cam.width, cam.height], (500, 2)), 3.0
        )
        + pts * 0.1
    )
    uv, ok = project_fast(cam, pts)
    ref = cam.project(pts)
    assert ok.mean() > 0.5
    assert np.abs(uv[ok] - ref[ok]).max() < 1e-6


def test_the_grid_maps_agree_with_the_exact_ones_for_a_skewed_lens():
    from gst.data.crop import crop_maps

    cam = _camera([-0.2, 0.05, 0.001, -0.002, 0.01], skew=30.0)
    box = CropBox(180.0, 120.0, 260.0)
    exact = crop_maps(cam, box, 128)
    grid = crop_maps(cam, box, 128, grid_step=8)
    for a, b in zip(exact, grid, strict=True):
        assert np.abs(a - b).max() < 0.05


def test_crop_of_a_strongly_distorted_camera_is_zero_beyond_the_lens_fold():
    # k1 = -0.4 alone: the distorted radius r (1 - 0.4 r^2) peaks at r = 0.91 and falls after,
    # so rays beyond it project back into the image. A person at the right edge gets a crop
    # box reaching past that radius; its pixels there showed a mirrored copy of the frame
    # (and of the mask) instead of nothing.
    from gst.data.extract.crops import crop_person

    w, h = 640, 480
    cam = Camera.create(
        "c", [[500, 0, 320], [0, 500, 240], [0, 0, 1]], [-0.4, 0, 0, 0], np.eye(3), [0, 0, 0], w, h
    )
    frame = np.full((h, w, 3), 200, np.uint8)
    mask = np.zeros((h, w), bool)
    mask[150:330, 560:620] = True
    S = 128
    image, crop_mask, Kc, _, _ = crop_person(frame, mask, cam, S, 1.2)
    # each crop pixel's ray, and whether the lens model gives that ray back from its pixel
    v, u = np.mgrid[0:S, 0:S].astype(np.float64)
    rays = np.stack([(u - Kc[0, 2]) / Kc[0, 0], (v - Kc[1, 2]) / Kc[1, 1]], -1).reshape(-1, 2)
    back = cam.undistort_points(cam.project_normalised(rays))
    beyond = (np.linalg.norm(back - rays, axis=1) > 1e-3).reshape(S, S)
    assert beyond.sum() > 1000  # the case is exercised
    assert not image[beyond].any()
    assert not crop_mask[beyond].any()
    # the rays within the lens field are untouched (all of the frame is 200 there)
    inner = ~beyond & (np.hypot(*rays.T) < 0.85).reshape(S, S)
    assert inner.sum() > 1000 and (image[inner] == 200).all()

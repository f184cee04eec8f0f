"""Camera model: torch projection against cv2.projectPoints, skew, rig transforms, validation."""

import cv2
import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from calibration.camera import (
    Camera,
    CameraError,
    Rig,
    fit_rig_to_frames,
    look_at_rotation,
    project_points_torch,
)

finite = dict(allow_nan=False, allow_infinity=False)


@st.composite
def camera_and_points(draw, dist_len=None):
    rvec = np.array(draw(st.lists(st.floats(-np.pi, np.pi, **finite), min_size=3, max_size=3)))
    t = np.array(draw(st.lists(st.floats(-2, 2, **finite), min_size=3, max_size=3)))
    fx, fy = draw(st.floats(200, 3000, **finite)), draw(st.floats(200, 3000, **finite))
    cx, cy = draw(st.floats(100, 1000, **finite)), draw(st.floats(100, 1000, **finite))
    n = dist_len if dist_len is not None else draw(st.sampled_from([0, 4, 5, 8, 12]))
    scales = np.array(
        [0.2, 0.05, 0.002, 0.002, 0.01, 0.05, 0.01, 0.005, 0.002, 0.001, 0.002, 0.001]
    )[:n]
    dist = np.array(draw(st.lists(st.floats(-1, 1, **finite), min_size=n, max_size=n))) * scales
    # Points in front of the camera inside a moderate field of view.
    m = draw(st.integers(1, 20))
    xy = np.array(
        draw(st.lists(st.floats(-0.6, 0.6, **finite), min_size=2 * m, max_size=2 * m))
    ).reshape(m, 2)
    z = np.array(draw(st.lists(st.floats(0.5, 10, **finite), min_size=m, max_size=m)))
    pts_cam = np.c_[xy * z[:, None], z]
    R = cv2.Rodrigues(rvec)[0]
    pts_world = (pts_cam - t) @ R  # R^T (X - t)
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return K, dist, R, t, pts_world


@settings(max_examples=60, deadline=None)
@given(camera_and_points())
@example(
    (
        np.array([[200.0, 0, 100], [0, 200, 100], [0, 0, 1]]),
        np.array([]),
        cv2.Rodrigues(np.array([0.0, 1e-5, 0.0]))[0],
        np.zeros(3),
        np.array([[-1e-5, 0.0, 1.0]]),
    )
)
def test_torch_projection_matches_opencv(data):
    K, dist, R, t, pts = data
    # scipy's rotation vector is exact for tiny angles, where cv2.Rodrigues(matrix) rounds to 0.
    rvec = Rotation.from_matrix(R).as_rotvec()
    ref, _ = cv2.projectPoints(pts, rvec, t, K, dist if dist.size else None)
    T = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    out = project_points_torch(T(pts), T(K), T(R), T(t), T(dist) if dist.size else None)
    np.testing.assert_allclose(out.numpy(), ref.reshape(-1, 2), rtol=0, atol=1e-6)


def test_torch_projection_batched_and_differentiable():
    rng = np.random.default_rng(0)
    B, N = 3, 7
    K = torch.tensor([[[800.0, 0, 320], [0, 780, 240], [0, 0, 1]]] * B, dtype=torch.float64)
    R = torch.tensor(np.stack([cv2.Rodrigues(rng.normal(size=3) * 0.2)[0] for _ in range(B)]))
    t = torch.tensor(rng.normal(size=(B, 3)) * 0.1 + [0, 0, 4])
    dist = torch.tensor(rng.normal(size=(B, 5)) * [0.1, 0.02, 1e-3, 1e-3, 1e-3])
    pts = torch.tensor(rng.normal(size=(B, N, 3)) * 0.5, requires_grad=True)
    out = project_points_torch(pts, K, R, t, dist)
    assert out.shape == (B, N, 2)
    for b in range(B):  # each batch element equals its own OpenCV projection
        ref, _ = cv2.projectPoints(
            pts[b].detach().numpy(),
            cv2.Rodrigues(R[b].numpy())[0],
            t[b].numpy(),
            K[b].numpy(),
            dist[b].numpy(),
        )
        np.testing.assert_allclose(out[b].detach().numpy(), ref.reshape(-1, 2), atol=1e-8)
    # Gradients w.r.t. points and distortion agree with finite differences.
    assert torch.autograd.gradcheck(
        lambda p, d: project_points_torch(p, K, R, t, d), (pts, dist.clone().requires_grad_(True))
    )
    # Shared camera broadcast over a batch of point sets.
    out2 = project_points_torch(pts, K[0], R[0], t[0], dist[0])
    assert out2.shape == (B, N, 2)


def test_torch_projection_rejects_tilted_model():
    with pytest.raises(CameraError, match="14"):
        project_points_torch(
            torch.zeros(1, 3), torch.eye(3), torch.eye(3), torch.ones(3), torch.zeros(14)
        )


@settings(max_examples=40, deadline=None)
@given(camera_and_points(dist_len=5), st.floats(-40, 40, **finite))
def test_skew_is_honoured_by_project_and_undistort(data, skew):
    K, dist, R, t, pts = data
    K = K.copy()
    K[0, 1] = skew
    cam = Camera.create("c", K, dist, R, t, 1280, 960)
    uv = cam.project(pts)
    # Independent reference: OpenCV's distortion on normalised points, then the full K with skew.
    ref, _ = cv2.projectPoints(pts, cam.rvec, t, np.eye(3), dist)
    ref_h = np.c_[ref.reshape(-1, 2), np.ones(len(pts))] @ K.T
    np.testing.assert_allclose(uv, ref_h[:, :2], atol=1e-6)
    depth = cam.to_camera(pts)[:, 2]
    np.testing.assert_allclose(cam.unproject(uv, depth), pts, atol=1e-6)
    T = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    np.testing.assert_allclose(
        project_points_torch(T(pts), T(K), T(R), T(t), T(dist)).numpy(), uv, atol=1e-6
    )


def test_rig_transformed_keeps_projections_and_stacked_arrays():
    rng = np.random.default_rng(1)
    cams = []
    for i in range(3):
        pos = rng.normal(size=3) * 3 + [0, 0, 2]
        R = look_at_rotation(pos, [0, 0, 1])
        cams.append(
            Camera.create(
                f"c{i}",
                [[700, 0, 320], [0, 700, 240], [0, 0, 1]],
                [0.1, -0.02, 0, 0, 0],
                R,
                -R @ pos,
                640,
                480,
            )
        )
    rig = Rig(tuple(cams))
    Rw = cv2.Rodrigues(np.array([0.3, -0.2, 0.5]))[0]
    tw, s = np.array([1.0, -2.0, 0.5]), 1.7
    new = rig.transformed(Rw, tw, s)
    X = rng.normal(size=(10, 3))
    for a, b in zip(rig, new, strict=True):
        np.testing.assert_allclose(b.project(s * X @ Rw.T + tw), a.project(X), atol=1e-9)
        np.testing.assert_allclose(b.center, s * Rw @ a.center + tw, atol=1e-9)
    np.testing.assert_allclose(new.up, Rw @ np.array([0, 0, 1.0]), atol=1e-12)
    arrays = rig.stacked()
    assert (
        arrays.K.shape == (3, 3, 3)
        and arrays.dist.shape == (3, 5)
        and arrays.size.tolist()[0] == [640, 480]
    )


def test_look_at_points_camera_at_target_with_image_up():
    R = look_at_rotation([3, 0, 2], [0, 0, 1])
    cam = Camera.create("c", np.eye(3), None, R, -R @ np.array([3, 0, 2.0]), 10, 10)
    d = np.array([0, 0, 1.0]) - cam.center
    np.testing.assert_allclose(cam.optical_axis, d / np.linalg.norm(d), atol=1e-12)
    assert R[1] @ [0, 0, 1] < 0  # image y (down) points against world up


@pytest.mark.parametrize(
    "field,value,match",
    [
        ("K", np.full((3, 3), np.nan), "NaN"),
        ("R", np.diag([1.0, 1.0, 1.1]), "orthonormal"),
        ("R", np.diag([1.0, 1.0, -1.0]), "reflection"),
        ("t", np.zeros(4), "shape"),
        ("dist", np.zeros(6), "distortion has 6 terms"),
    ],
)
def test_camera_validation_names_camera_and_field(field, value, match):
    fields = dict(K=np.eye(3), dist=None, R=np.eye(3), t=np.zeros(3), width=10, height=10)
    fields[field] = value
    with pytest.raises(CameraError, match=match) as info:
        Camera.create("cam-x", **fields)
    assert "cam-x" in str(info.value)


def test_tiny_rotation_is_not_rounded_to_identity():
    # cv2.Rodrigues returns a zero vector below ~1e-5 rad; projection must not depend on it.
    R = np.array([[1.0, 0.0, 1e-5], [0.0, 1.0, 0.0], [-1e-5, 0.0, 1.0]])
    R, _ = np.linalg.qr(R)
    R *= np.sign(np.diag(R))[None]
    cam = Camera.create(
        "c", [[200, 0, 100], [0, 200, 100], [0, 0, 1]], np.zeros(5), R, np.zeros(3), 1280, 960
    )
    pts = np.array([[-1e-5, 0.0, 1.0]])
    np.testing.assert_allclose(
        cam.unproject(cam.project(pts), cam.to_camera(pts)[:, 2]), pts, atol=1e-9
    )


@settings(max_examples=40, deadline=None)
@given(
    k1=st.floats(-0.35, 0.1),
    k2=st.floats(-0.05, 0.1),
    u=st.floats(-600, 2500),
    v=st.floats(-600, 1700),
)
def test_exact_only_undistortion_keeps_what_projects_back_and_drops_the_rest(k1, k2, u, v):
    """`exact_only`: a pixel whose undistorted point projects back onto it (OpenCV's own
    projection, the reference) keeps that point; one whose point does not (outside the frame,
    beyond where a barrel lens inverts: 245 px off at k1 = -0.1) is NaN, not a wrong ray."""
    cam = Camera.create(
        "c", [[1000, 0, 959.5], [0, 1000, 539.5], [0, 0, 1]], [k1, k2, 0, 0, 0], np.eye(3),
        np.zeros(3), 1920, 1080,
    )  # fmt: skip
    px = np.array([[u, v]])
    plain = cam.undistort_points(px)
    exact = cam.undistort_points(px, exact_only=True)
    back = cv2.projectPoints(np.c_[plain, np.ones(1)], np.zeros(3), np.zeros(3), cam.K, cam.dist)[
        0
    ].reshape(-1, 2)
    miss = float(np.linalg.norm(back - px))
    if miss <= 0.4:
        np.testing.assert_array_equal(exact, plain)
    elif miss > 0.6:
        assert np.isnan(exact).all()


def test_exact_only_undistortion_examples():
    cam = Camera.create(
        "c", [[1000, 0, 959.5], [0, 1000, 539.5], [0, 0, 1]], [-0.1, 0, 0, 0, 0], np.eye(3),
        np.zeros(3), 1920, 1080,
    )  # fmt: skip
    px = np.array([[959.5, 1079.0], [1900, 1250], [2100, 1300], [np.nan, 3.0]])
    exact = cam.undistort_points(px, exact_only=True)
    assert np.isfinite(exact[:2]).all() and np.isnan(exact[2:]).all()
    np.testing.assert_array_equal(exact[:2], cam.undistort_points(px[:2]))
    pinhole = Camera.create(
        "p", cam.K, [], np.eye(3), np.zeros(3), 1920, 1080
    )  # no lens: every finite pixel inverts
    assert np.isfinite(pinhole.undistort_points(px[:3], exact_only=True)).all()


def test_undistortion_converges_for_wide_strong_lenses():
    """Every pixel of a 90 degree camera with a strong sampled lens, undistorted and projected
    again, lands on itself (OpenCV's iteration stopped at 50 steps, 0.6 px short: the synthetic
    renderer's rays missed their pixels)."""
    from synth.rigs import make_rig

    uu, vv = np.meshgrid(np.arange(160.0), np.arange(120.0))
    pix = np.stack([uu.ravel(), vv.ravel()], -1)
    for seed in range(3):
        for cam in make_rig(
            "dome", 4, 160, 120, fov_deg=90, distortion="strong", seed=seed
        ).cameras:
            xy = cam.undistort_points(pix)
            back = cv2.projectPoints(
                np.c_[xy, np.ones(len(xy))], np.zeros(3), np.zeros(3), cam.K, cam.dist
            )[0].reshape(-1, 2)
            assert np.abs(back - pix).max() < 1e-6, (seed, cam.name)


def test_undistortion_runs_on_opencv_4_too(monkeypatch):
    """pyproject allows OpenCV >= 4.10, but the iteration's criteria were passed the OpenCV 5
    way (a 7th argument of undistortPoints): with OpenCV 4 every undistortion (extraction,
    fusion, tracking on a calibrated camera) failed with "takes at most 6 arguments". OpenCV 4's
    API is stood in for here: undistortPoints without criteria, and undistortPointsIter."""
    from synth.rigs import make_rig

    cam = make_rig("dome", 1, 160, 120, fov_deg=90, distortion="strong", seed=0).cameras[0]
    pix = np.array([[5.0, 7.0], [80.0, 60.0], [150.0, 110.0]])
    want = cam.undistort_points(pix)
    real = cv2.undistortPoints

    def undistort_points_v4(src, K, dist, dst=None, R=None, P=None):  # 6 arguments at most
        return real(src, K, dist, dst, R, P)

    def undistort_points_iter_v4(src, K, dist, R, P, criteria):
        return real(src, K, dist, None, R, P, criteria)

    monkeypatch.setattr(cv2, "undistortPoints", undistort_points_v4)
    monkeypatch.setattr(cv2, "undistortPointsIter", undistort_points_iter_v4, raising=False)
    np.testing.assert_allclose(cam.undistort_points(pix), want, atol=1e-12)


def test_rig_fitted_to_its_videos_frame_sizes():
    """Encoder padding (8 rows) is fitted and noted, a camera without a video is left as it
    is, and a frame size that is not padding names the camera."""
    from types import SimpleNamespace

    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    rig = Rig(
        tuple(Camera(n, K, np.zeros(5), np.eye(3), np.zeros(3), 640, 480) for n in ("a", "b"))
    )
    fitted, notes = fit_rig_to_frames(
        rig, {"a": SimpleNamespace(width=640, height=472, path="a.mp4")}
    )
    assert (fitted["a"].width, fitted["a"].height) == (640, 472)
    assert (fitted["b"].width, fitted["b"].height) == (640, 480)
    assert len(notes) == 1 and "camera 'a'" in notes[0] and "8 rows" in notes[0]
    np.testing.assert_array_equal(fitted["a"].K, K)
    with pytest.raises(CameraError, match=r"camera 'b' \(b.mp4\).*600x480"):
        fit_rig_to_frames(rig, {"b": SimpleNamespace(width=600, height=480, path="b.mp4")})


def test_a_video_turned_against_its_calibration_is_said_to_be_turned():
    """Frames 1920x1088 against a 1088x1920 calibration were told to fix the size in the file;
    a rig "fixed" that way (K and R unturned) then passed every check. Now the error says the
    video is turned, and the rig checks warn of a principal point far from the centre."""
    from types import SimpleNamespace

    from calibration.checks import lens_warnings

    K = np.array([[1400.0, 0, 533.0], [0, 1400, 948.0], [0, 0, 1]])
    rig = Rig((Camera("cam01", K, np.zeros(5), np.eye(3), np.zeros(3), 1088, 1920),))
    frames = {"cam01": SimpleNamespace(width=1920, height=1088, path="cam01.mp4")}
    with pytest.raises(CameraError, match=r"'cam01' \(cam01.mp4\).*turned by 90 degrees"):
        fit_rig_to_frames(rig, frames)
    assert lens_warnings(rig) == []
    edited = Rig((Camera("cam01", K, np.zeros(5), np.eye(3), np.zeros(3), 1920, 1088),))
    (warning,) = lens_warnings(edited)
    assert "camera 'cam01': principal point (533, 948)" in warning and "87%" in warning


@pytest.mark.parametrize("width", [1920.7, True, float("nan"), "1920"])
def test_a_side_that_is_not_a_whole_number_of_pixels_is_refused(width):
    """Camera.create took int() of each side: 1920.7 became 1920 and True a 1-pixel-wide
    camera, silently (the file readers check this, library callers were not)."""
    args = ("c", np.eye(3) * [100, 100, 1] + [[0, 0, 50], [0, 0, 40], [0, 0, 0]], [], np.eye(3))
    with pytest.raises(CameraError, match=r"camera 'c': width is .*whole number of pixels"):
        Camera.create(*args, np.zeros(3), width, 80)
    assert Camera.create(*args, np.zeros(3), np.float64(100.0), np.int64(80)).width == 100

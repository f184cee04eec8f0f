"""Mesh renderer: rays agree with OpenCV projection, masks and depth agree with independent
references (trimesh's pure-numpy intersector, OpenCV's rasteriser, exact surface distance), and
the rendered board is detected by OpenCV's ChArUco detector at the ground-truth corners."""

import cv2
import numpy as np
import pytest
from synth_fixtures import CapsuleBody

from synth.animate import pose_person
from synth.appearance import BodyAtlas, sample_outfit, team_kits
from synth.board import BoardPose, ChArUcoSpec, visible_corners
from synth.imaging import CameraResponse, develop, encode_srgb, linear_to_srgb, tonemap
from synth.motions import generate_motion
from synth.render import (
    PosedPerson,
    RayCaster,
    RenderOptions,
    ViewRenderer,
    floor_shadow_maps,
    vertex_normals,
)
from synth.rigs import look_at, make_rig
from synth.stage import stage_for_rig

BODY = CapsuleBody()
COARSE_BODY = CapsuleBody(max_edge=0.12)  # fewer triangles for the slow reference rasteriser
STAGE = stage_for_rig("dome", seed=0)


def _person(frame=10, heading=0.3, motion="kick", body=BODY):
    clip = generate_motion(
        motion, 20, 30.0, np.random.default_rng(1), start=(0.1, -0.2), heading=heading
    )
    tr = pose_person(body, np.zeros(10), clip, 1)
    faces = body.faces.astype(np.int32)
    atlas = BodyAtlas.build(tr.rest_vertices, tr.rest_joints, body.part_labels, body.part_names)
    outfit = sample_outfit(np.random.default_rng(0), team_kits(1, np.random.default_rng(0))[0], 0)
    v = tr.vertices[frame]
    return PosedPerson(1, v, vertex_normals(v, faces), faces, atlas, outfit), tr


def _camera(width=160, height=120, dist=(-0.25, 0.08, 0.001, -0.001, 0.0), distance=3.0):
    K = np.array([[0.9 * width, 0, width / 2 + 1.3], [0, 0.9 * width, height / 2 - 0.7], [0, 0, 1]])
    centre = np.array([distance * 0.8, -distance * 0.6, 1.4])
    return look_at("cam", centre, [0.1, -0.2, 0.9], K, np.asarray(dist), width, height)


def test_pixel_rays_reproject_to_their_pixels_with_distortion():
    cam = _camera(320, 240)
    r = ViewRenderer(cam, STAGE, RenderOptions(background_samples=1))
    rng = np.random.default_rng(0)
    pix = rng.integers(0, cam.width * cam.height, 500)
    pts = r.origin + r.dirs_from_xy(r.xy[pix]).astype(np.float64) * rng.uniform(1, 6, (500, 1))
    uv = cam.project(pts)
    rows, cols = np.divmod(pix, cam.width)
    assert np.abs(uv - np.c_[cols, rows]).max() < 2e-3
    # Sub-pixel sample directions (interpolated between undistorted corners) are accurate too.
    sub = r.subpixel_xy(pix, 3)
    pts = r.origin + r.dirs_from_xy(sub).astype(np.float64) * 3.0
    off = (np.arange(3) + 0.5) / 3 - 0.5
    fx, fy = np.meshgrid(off, off)
    expected = np.repeat(np.c_[cols, rows], 9, 0) + np.tile(
        np.c_[fx.ravel(), fy.ravel()], (len(pix), 1)
    )
    assert np.abs(cam.project(pts) - expected).max() < 0.02


def _cross2(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _rasterise(cam, vertices, faces):
    """Independent reference: z-buffer rasteriser sampling pixel centres (pinhole camera).
    Returns a coverage mask and camera-z depth (inf where empty)."""
    pc = cam.to_camera(vertices.astype(np.float64))
    uv = pc[:, :2] / pc[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    depth = np.full((cam.height, cam.width), np.inf)
    for f in faces:
        p, z = uv[f], pc[f, 2]
        x0, y0 = np.maximum(np.floor(p.min(0)).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(p.max(0)).astype(int), [cam.width - 1, cam.height - 1])
        if x1 < x0 or y1 < y0:
            continue
        gx, gy = np.meshgrid(np.arange(x0, x1 + 1), np.arange(y0, y1 + 1))
        q = np.stack([gx.ravel(), gy.ravel()], -1).astype(np.float64)
        e = np.stack(
            [_cross2(p[(i + 2) % 3] - p[(i + 1) % 3], q - p[(i + 1) % 3]) for i in range(3)], -1
        )
        area = e.sum(1)
        inside = (np.all(e >= 0, 1) | np.all(e <= 0, 1)) & (np.abs(area) > 1e-12)
        if not inside.any():
            continue
        w = e[inside] / area[inside, None]
        zq = 1.0 / (w / z).sum(1)  # perspective-correct depth
        rows, cols = gy.ravel()[inside], gx.ravel()[inside]
        depth[rows, cols] = np.minimum(depth[rows, cols], zq)
    return np.isfinite(depth), depth


@pytest.mark.parametrize("backend", ["embree", "trimesh"])
def test_mask_and_depth_match_an_independent_rasteriser(backend):
    person, _ = _person(body=COARSE_BODY)
    cam = _camera(160, 120, dist=())
    r = ViewRenderer(
        cam,
        STAGE,
        RenderOptions(antialias=1, background_samples=1, shadow_samples=1, backend=backend),
    )
    layers = r.render_people(
        [person], RayCaster([(person.vertices, person.faces)], backend), shadows=[]
    )
    ref_mask, ref_depth = _rasterise(cam, person.vertices, person.faces)
    mine = layers.mask > 0
    assert ref_mask.sum() > 300
    iou = (mine & ref_mask).sum() / (mine | ref_mask).sum()
    assert iou > 0.995, f"mask IoU with the reference rasteriser {iou:.4f}"
    both = mine & ref_mask
    assert np.abs(layers.depth[both] - ref_depth[both]).max() < 2e-3


def test_room_depth_is_exact_and_people_cast_shadows():
    person, _ = _person(heading=0.0)
    rig = make_rig("dome", n_cameras=3, width=160, height=120, seed=2)
    for cam in rig.cameras:
        r = ViewRenderer(cam, STAGE, RenderOptions(background_samples=1))
        floor = r.bg_floor.reshape(cam.height, cam.width)
        rows, cols = np.nonzero(floor)
        pts = cam.unproject(
            np.c_[cols, rows].astype(np.float64),
            r.bg_depth.reshape(cam.height, cam.width)[rows, cols],
        )
        assert np.abs(pts[:, 2]).max() < 1e-3
    caster = RayCaster([(person.vertices, person.faces)])
    (sm,) = floor_shadow_maps([person], caster, STAGE, 4)
    assert sm.factor.min() < 0.6 and sm.factor.max() == pytest.approx(1.0)
    # The darkest shadow lies near the person, on the side away from the light.
    iy, ix = np.unravel_index(sm.factor.argmin(), sm.factor.shape)
    p = np.array([sm.origin[0] + ix * sm.cell, sm.origin[1] + iy * sm.cell])
    assert np.linalg.norm(p - person.vertices[:, :2].mean(0)) < 1.5


def test_board_is_detected_at_its_ground_truth_corners():
    spec = ChArUcoSpec()
    cam = _camera(640, 480, dist=(-0.12, 0.03, 0.0005, -0.0003, 0.0), distance=2.6)
    # Board 2 m in front of the camera, facing it, slightly rotated.
    front = -cam.optical_axis
    centre = cam.center + 2.0 * cam.optical_axis
    z = -front
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    a = np.deg2rad(12)
    x, y = np.cos(a) * x + np.sin(a) * y, -np.sin(a) * x + np.cos(a) * y
    R = np.stack([x, y, z], -1)
    pose = BoardPose(R=R, t=centre - R @ np.array([spec.size[0] / 2, spec.size[1] / 2, 0]))
    r = ViewRenderer(cam, STAGE, RenderOptions(antialias=3))
    layers = r.render_board(spec, pose, spec.texture())
    image = develop(
        layers.radiance, CameraResponse(blur_sigma=0.4, noise_sigma=1.0), np.random.default_rng(0)
    )
    cc, ci, _, _ = cv2.aruco.CharucoDetector(spec.cv_board).detectBoard(
        cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    )
    ids, uv = visible_corners(spec, pose, cam)
    assert len(ids) == len(spec.corners)
    assert ci is not None and len(ci) >= 0.9 * len(ids)
    gt = dict(zip(ids.tolist(), uv, strict=True))
    err = np.array(
        [np.linalg.norm(c - gt[i]) for c, i in zip(cc.reshape(-1, 2), ci.ravel(), strict=True)]
    )
    assert np.median(err) < 0.15 and err.max() < 0.5, f"corner errors {err.round(3)}"
    assert layers.mask.sum() > 1000
    # Seen from behind, the board shows no pattern.
    back = BoardPose(
        R=R @ np.diag([-1.0, 1.0, -1.0]), t=pose.t + R @ np.array([spec.size[0], 0, 0])
    )
    assert len(visible_corners(spec, back, cam)[0]) == 0
    behind = develop(
        r.render_board(spec, back, spec.texture()).radiance,
        CameraResponse(),
        np.random.default_rng(0),
    )
    assert (
        cv2.aruco.CharucoDetector(spec.cv_board).detectBoard(
            cv2.cvtColor(behind, cv2.COLOR_BGR2GRAY)
        )[1]
        is None
    )


def test_develop_noise_level_and_encoding():
    flat = np.full((200, 200, 3), 0.2, np.float32)
    ideal = linear_to_srgb(tonemap(np.float64(0.2))) * 255
    clean = develop(flat, CameraResponse(vignetting=0.0), np.random.default_rng(0))
    assert np.abs(clean.astype(float) - ideal).max() <= 0.51
    noisy = develop(flat, CameraResponse(vignetting=0.0, noise_sigma=4.0), np.random.default_rng(0))
    expected_std = 4.0 * np.sqrt(0.35 + 0.65 * ideal / 128)
    assert noisy.astype(float).std() == pytest.approx(expected_std, rel=0.1)
    again = develop(flat, CameraResponse(vignetting=0.0, noise_sigma=4.0), np.random.default_rng(0))
    assert np.array_equal(noisy, again)
    x = np.linspace(0, 4, 10001)
    assert np.abs(encode_srgb(x.astype(np.float32)) - linear_to_srgb(tonemap(x)) * 255).max() < 0.05


def test_render_options_are_validated():
    with pytest.raises(ValueError, match="antialias"):
        RenderOptions(antialias=0)
    with pytest.raises(ValueError, match="backend"):
        RenderOptions(backend="optix")
    with pytest.raises(ValueError, match="outside the stage"):
        ViewRenderer(
            look_at(
                "far",
                [50.0, 0, 1],
                [0, 0, 1],
                np.eye(3) * [100, 100, 1] + [[0, 0, 32], [0, 0, 24], [0, 0, 0]],
                np.zeros(5),
                64,
                48,
            ),
            STAGE,
        )


def test_sample_image_takes_more_points_than_one_remap_call_holds(monkeypatch):
    """sample_image reshaped the points into rows of 1024 for one cv2.remap call, which refuses
    32767 rows or more: beyond 33.5 M points (the floor pixels of a camera beyond 8K, which the
    spec allows up to 8190 x 8190) the floor shadows failed an OpenCV assertion. Shown here
    with rows of 2 points."""
    from synth import sampling

    monkeypatch.setattr(sampling, "_BLOCK", 2)
    image = (np.arange(12, dtype=np.float32).reshape(3, 4) * 1.5).copy()
    rng = np.random.default_rng(0)
    n = 2 * 33_000 + 1
    x, y = rng.uniform(0, 3, n), rng.uniform(0, 2, n)
    got = sampling.sample_image(image, x, y)
    # the image is linear in x and y (1.5 x + 6 y), so bilinear sampling is exact
    np.testing.assert_allclose(got, 1.5 * x + 6.0 * y, atol=1e-2)

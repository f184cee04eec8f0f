"""Synthetic rigs: every camera looks at the capture volume, settings are honoured."""

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from synth.projection import field_radius, project_in_view
from synth.rigs import H36M_CAMERA_IDS, RIG_KINDS, make_rig, sample_distortion
from synth.stage import stage_for_rig
from synth.world import SMPL_TO_WORLD, facing_direction, heading_rotation


def _volume_points(rig, n_ring=16):
    """Points on the capture volume: its centre column and its rim at 0.1 m and 1.8 m."""
    c = np.asarray(rig.meta["volume_center"])
    r = 0.7 * rig.meta["volume_radius"]
    a = np.linspace(0, 2 * np.pi, n_ring, endpoint=False)
    rim = [
        np.c_[c[0] + r * np.cos(a), c[1] + r * np.sin(a), np.full(n_ring, z)] for z in (0.1, 1.8)
    ]
    return np.concatenate([np.array([[c[0], c[1], z] for z in (0.1, 0.9, 1.8)])] + rim)


@settings(max_examples=25, deadline=None)
@example(kind="hall", n=11, seed=64, width=64, aspect=0.5625, fov=30.0, distortion="mild")
@given(
    kind=st.sampled_from(sorted(RIG_KINDS)),
    n=st.integers(1, 32),
    seed=st.integers(0, 10_000),
    width=st.integers(64, 1920),
    aspect=st.sampled_from([0.5625, 0.75, 1.0]),
    fov=st.floats(30, 80),
    distortion=st.sampled_from([None, "mild", "strong"]),
)
def test_every_camera_looks_at_the_volume(kind, n, seed, width, aspect, fov, distortion):
    height = max(16, int(width * aspect))
    rig = make_rig(
        kind, n_cameras=n, width=width, height=height, fov_deg=fov, distortion=distortion, seed=seed
    )
    assert len(rig) == n and len(set(rig.names)) == n
    c = np.asarray(rig.meta["volume_center"])
    stage = stage_for_rig(kind, seed)
    for cam in rig.cameras:
        assert stage.contains(cam.center[None])[0], f"{cam.name} outside the room"
        # The optical axis passes through the volume, near its centre.
        to_c = c - cam.center
        miss = np.linalg.norm(to_c - np.dot(to_c, cam.optical_axis) * cam.optical_axis)
        assert np.dot(to_c, cam.optical_axis) > 0 and miss < 0.3 * rig.meta["volume_radius"]
        uv, inside = project_in_view(cam, c[None], field_radius(cam))
        assert inside[0], f"{cam.name} does not see the volume centre"
        # within a fifth of the image of its centre, or as far as the aim's allowed miss (0.3
        # radii) reaches at this depth: a narrow lens (30 degrees, 64 px) turned an allowed 0.63
        # m miss into 12.9 px, past 0.2 x 64 (a draw the derandomized CI never made)
        depth = float(np.dot(to_c, cam.optical_axis))
        reach = 1.1 * 0.3 * rig.meta["volume_radius"] / depth
        assert abs(uv[0, 0] - width / 2) < max(0.2 * width, reach * cam.K[0, 0])
        assert abs(uv[0, 1] - height / 2) < max(0.2 * height, reach * cam.K[1, 1])


@pytest.mark.parametrize("kind", sorted(RIG_KINDS))
def test_default_lenses_frame_the_whole_volume(kind):
    rig = make_rig(kind, distortion="mild", seed=1)
    pts = _volume_points(rig)
    for cam in rig.cameras:
        _, inside = project_in_view(cam, pts, field_radius(cam))
        assert inside[:3].all(), f"{cam.name} does not see the volume's centre column"
        assert inside.mean() >= 0.8, f"{cam.name} sees only {inside.mean():.0%} of the volume rim"


def test_rig_settings_are_honoured():
    rig = make_rig("hall", n_cameras=8, width=1280, height=720, focal_mm=35.0, fps=60.0, seed=3)
    assert rig.meta["fps"] == 60.0 and rig.meta["kind"] == "hall"
    assert rig.up == (0.0, 0.0, 1.0)
    for cam in rig.cameras:
        assert cam.width == 1280 and cam.height == 720
        assert cam.fx == pytest.approx(35.0 / 36.0 * 1280)
        assert cam.center[2] == pytest.approx(3.0, abs=0.11)  # hall cameras ~3 m up
        assert not np.any(cam.dist)
    dome = make_rig("dome", n_cameras=5, width=640, height=480, fov_deg=60.0)
    assert dome.cameras[0].fx == pytest.approx(320 / np.tan(np.deg2rad(30)))
    h36m = make_rig("h36m")
    assert h36m.names == list(H36M_CAMERA_IDS)
    assert (h36m.cameras[0].width, h36m.cameras[0].height) == (1000, 1002)


def test_rig_is_deterministic_from_seed():
    a = make_rig("dome", n_cameras=6, distortion="mild", seed=7)
    b = make_rig("dome", n_cameras=6, distortion="mild", seed=7)
    c = make_rig("dome", n_cameras=6, distortion="mild", seed=8)
    assert all(
        np.array_equal(x.R, y.R) and np.array_equal(x.dist, y.dist)
        for x, y in zip(a, b, strict=True)
    )
    assert not all(np.array_equal(x.dist, y.dist) for x, y in zip(a, c, strict=True))


def test_distortion_specs():
    rng = np.random.default_rng(0)
    mild = sample_distortion("mild", 10, rng)
    assert mild.shape == (10, 5) and np.all(mild[:, 0] < 0)
    assert np.array_equal(sample_distortion([0.1, 0.01, 0, 0], 2, rng), [[0.1, 0.01, 0, 0, 0]] * 2)
    with pytest.raises(ValueError, match="distortion 'wavy'"):
        sample_distortion("wavy", 1, rng)
    with pytest.raises(ValueError, match="4 or 5"):
        sample_distortion([0.1, 0.2], 1, rng)
    with pytest.raises(ValueError, match="folds over"):
        make_rig("dome", n_cameras=1, distortion=[-0.9, 0.0, 0.0, 0.0, 0.0])


def test_a_barrel_lens_that_cannot_reach_the_image_corners_is_refused():
    """k1 = -0.3 at a 65 degree field: the lens's largest distorted radius (0.70) is short of
    the corners' (0.80), so corner pixels would cast rays the lens never sends there. The slope
    was checked only up to the corners' distorted radius, not up to the undistorted radius that
    reaches them, and this lens was accepted."""
    with pytest.raises(ValueError, match="folds over"):
        make_rig("dome", 1, 480, 360, fov_deg=65.2, distortion=[-0.3, 0, 0, 0])
    k1, k2 = -0.3, 0.0  # its largest distorted radius, where the slope 1 + 3 k1 r^2 is 0
    r = np.sqrt(-1 / (3 * k1))
    assert r * (1 + k1 * r**2 + k2 * r**4) < 0.75
    make_rig("dome", 1, 480, 360, fov_deg=65.2, distortion=[-0.1, 0, 0, 0])  # a mild one is fine


def test_bad_rig_arguments_name_the_problem():
    with pytest.raises(ValueError, match="unknown rig kind 'arena'"):
        make_rig("arena")
    with pytest.raises(ValueError, match="n_cameras"):
        make_rig("dome", n_cameras=0)
    with pytest.raises(ValueError, match="not both"):
        make_rig("dome", focal_mm=20, fov_deg=60)
    with pytest.raises(ValueError, match="fps"):
        make_rig("dome", fps=-1)


@pytest.mark.parametrize("focal_mm", [1.0, 1e-6, 500.0, float("inf"), float("nan")])
def test_a_focal_length_is_held_to_the_field_of_view_fov_deg_allows(focal_mm):
    """fov_deg is refused outside [5, 150] degrees, but focal_mm took any positive number:
    1 mm on the 36 mm sensor made a 174 degree pinhole, 1e-6 mm a focal length of 2e-6 px and
    an infinite one a camera matrix of inf (refused only by the Camera, naming no focal_mm)."""
    with pytest.raises(ValueError, match="focal_mm .* degree field of view"):
        make_rig("dome", n_cameras=1, width=64, height=48, focal_mm=focal_mm)
    make_rig("dome", n_cameras=1, width=64, height=48, focal_mm=35.0)  # 54 degrees
    if not np.isfinite(focal_mm):
        from pydantic import ValidationError

        from synth.spec import preset

        with pytest.raises(ValidationError, match="rig.focal_mm"):
            preset("demo", rig__focal_mm=focal_mm)


@settings(max_examples=30, deadline=None)
@given(heading=st.floats(-10, 10))
def test_heading_convention(heading):
    R = heading_rotation(heading)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
    # SMPL facing (+z) goes to the heading direction, SMPL up (+y) to world up.
    assert np.allclose(R @ [0, 0, 1], facing_direction(heading), atol=1e-12)
    assert np.allclose(R @ [0, 1, 0], [0, 0, 1], atol=1e-12)


def test_smpl_to_world_is_the_documented_axis_swap():
    x, y, z = 0.3, 1.2, -0.7
    assert np.allclose(SMPL_TO_WORLD @ [x, y, z], [x, -z, y])

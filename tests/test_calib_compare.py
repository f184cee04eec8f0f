"""compare_rigs recovers zero error for a rig expressed in another world frame."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from calibration import Camera, Rig
from calibration.compare import compare_rigs


def ring_rig(n=6, radius=4.0, height=2.5):
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        c = np.array([radius * np.cos(a), radius * np.sin(a), height])
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        cams.append(
            Camera.create(
                f"c{i}", [[800, 0, 320], [0, 810, 240], [0, 0, 1]], [], R, -R @ c, 640, 480
            )
        )
    return Rig(tuple(cams))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.floats(-5, 5), st.floats(-5, 5))
def test_rig_in_another_world_frame_compares_equal(seed, tx, ty):
    ref = ring_rig()
    Q = Rotation.random(random_state=seed).as_matrix()  # world_new = Q world_ref + d
    d = np.array([tx, ty, 1.0])
    moved = Rig(tuple(c.replace(R=c.R @ Q.T, t=c.t - c.R @ Q.T @ d) for c in ref))
    cmp = compare_rigs(moved, ref)
    assert np.max(cmp.center_error_m) < 1e-9
    assert np.max(cmp.rotation_error_deg) < 1e-5
    assert np.max(cmp.focal_rel_error) == 0


def test_perturbed_camera_is_reported():
    ref = ring_rig()
    cams = list(ref.cameras)
    R = Rotation.from_euler("y", 1.0, degrees=True).as_matrix() @ cams[2].R
    cams[2] = cams[2].replace(
        R=R, K=np.diag([808.0, 810.0, 1.0]) + np.array([[0, 0, 320], [0, 0, 240], [0, 0, 0]])
    )
    cmp = compare_rigs(Rig(tuple(cams)), ref)
    assert np.argmax(cmp.focal_rel_error) == 2 and abs(cmp.focal_rel_error[2] - 0.01) < 1e-12
    assert cmp.rotation_error_deg[2] > 0.3

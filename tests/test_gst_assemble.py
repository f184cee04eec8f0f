"""Posing Gaussians: offsets and rotations follow the skinning, camera-to-world is exact."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from kornia.geometry.conversions import quaternion_to_rotation_matrix
from scipy.spatial.transform import Rotation

from calibration import Camera
from gst.body import BodyModel
from gst.body.random_model import random_body_data
from gst.body.rotations import matrix_to_rot6d
from gst.model.assemble import assemble, camera_translation, to_world
from gst.model.network import GaussianParams, GSTOutput


@pytest.fixture(scope="module")
def body():
    return BodyModel(random_body_data(num_vertices=500, with_posedirs=False), dtype=torch.float64)


def output(rotmats, offsets, quats, cam=(0.9, 0.1, -0.2)):
    b, v = offsets.shape[:2]
    g = GaussianParams(
        colors=torch.rand(b, v, 3, dtype=torch.float64),
        quats=quats,
        opacities=torch.full((b, v), 0.5, dtype=torch.float64),
        scales=torch.full((b, v, 3), 0.01, dtype=torch.float64),
        offsets=offsets,
    )
    return GSTOutput(
        matrix_to_rot6d(rotmats),
        rotmats,
        torch.zeros(b, 10, dtype=torch.float64),
        torch.tensor([cam], dtype=torch.float64).expand(b, 3),
        g,
    )


def K(f=500.0, c=128.0):
    return torch.tensor([[[f, 0, c], [0, f, c], [0, 0, 1]]], dtype=torch.float64)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000))
def test_rigid_pose_moves_offsets_and_rotations_with_the_body(body, seed):
    rot = torch.tensor(Rotation.random(random_state=seed).as_matrix())
    rotmats = torch.eye(3, dtype=torch.float64).repeat(1, 24, 1, 1)
    rotmats[0, 0] = rot  # only a global rotation: every vertex transform is this rotation
    gen = torch.Generator().manual_seed(seed)
    offsets = 0.02 * torch.randn(1, 500, 3, generator=gen, dtype=torch.float64)
    quats = torch.nn.functional.normalize(
        torch.randn(1, 500, 4, generator=gen, dtype=torch.float64), dim=-1
    )
    pred = assemble(output(rotmats, offsets, quats), body, K(), 256)
    g = pred.gaussians_cam
    torch.testing.assert_close(g.means - pred.vertices_cam, offsets @ rot.T)
    expected_rot = rot @ quaternion_to_rotation_matrix(quats)
    torch.testing.assert_close(
        quaternion_to_rotation_matrix(g.quats), expected_rot, atol=1e-9, rtol=0
    )


def test_camera_translation_uses_crop_focal():
    t = camera_translation(torch.tensor([[0.5, 0.1, 0.2]], dtype=torch.float64), K(f=800.0), 256)
    torch.testing.assert_close(
        t, torch.tensor([[0.1, 0.2, 2 * 800 / (256 * 0.5)]], dtype=torch.float64)
    )


def test_world_transform_matches_camera(body):
    cam = Camera.create(
        "c",
        [[500, 0, 128], [0, 500, 128], [0, 0, 1]],
        [],
        Rotation.from_euler("xyz", [10, -30, 5], degrees=True).as_matrix(),
        [0.3, -0.2, 4.0],
        256,
        256,
    )
    pts_world = np.random.default_rng(0).normal(size=(7, 3))
    pts_cam = torch.tensor(cam.to_camera(pts_world))[None]
    back = to_world(pts_cam, torch.tensor(cam.R)[None], torch.tensor(cam.t)[None])
    np.testing.assert_allclose(back[0].numpy(), pts_world, atol=1e-12)


def test_pose_only_output_has_no_gaussians_and_the_same_body(body):
    """A network output without Gaussians (the pose-only path) assembles into the same body as
    the full output, with no splat."""
    rotmats = torch.eye(3, dtype=torch.float64).repeat(2, 24, 1, 1)
    rotmats[:, 18] = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    offsets = 0.01 * torch.randn(2, 500, 3, dtype=torch.float64)
    quats = torch.nn.functional.normalize(torch.randn(2, 500, 4, dtype=torch.float64), dim=-1)
    full = assemble(output(rotmats, offsets, quats), body, K().expand(2, 3, 3), 256)
    pose_only_out = output(rotmats, offsets, quats)
    pose_only_out.gaussians = None
    pose_only = assemble(pose_only_out, body, K().expand(2, 3, 3), 256)
    assert full.gaussians_cam is not None and pose_only.gaussians_cam is None
    assert torch.equal(pose_only.joints_cam, full.joints_cam)
    assert torch.equal(pose_only.transl_cam, full.transl_cam)


def test_half_an_extrinsic_is_refused(body):
    """`R_in` without `t_in` gave no world coordinates and no word."""
    rotmats = torch.eye(3).expand(1, 24, 3, 3).clone()
    offsets, quats = torch.zeros(1, 10, 3), torch.tensor([[1.0, 0, 0, 0]]).expand(1, 10, 4)
    with pytest.raises(ValueError, match="need the input camera's R and t together, got only R"):
        assemble(output(rotmats, offsets, quats), body, K(), 256, R_in=torch.eye(3)[None])

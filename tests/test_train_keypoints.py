"""Detected-joint reprojection term: exact projections cost nothing, errors are measured in image
widths and weighted by confidence; the BlazePose-to-body joint mapping."""

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.train.keypoints import BODY_FROM_BLAZEPOSE, keypoint_term, keypoints_from_landmarks


def _views(b: int, m: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    viewmats = torch.eye(4).repeat(b, m, 1, 1)
    angles = torch.rand(b, m, generator=g) * 0.6 - 0.3
    c, s = torch.cos(angles), torch.sin(angles)
    viewmats[..., 0, 0], viewmats[..., 0, 2], viewmats[..., 2, 0], viewmats[..., 2, 2] = c, s, -s, c
    viewmats[..., 2, 3] = 4.0
    K = torch.tensor([[60.0, 0, 31.5], [0, 60.0, 31.5], [0, 0, 1]]).repeat(b, m, 1, 1)
    return viewmats, K


def _project(joints, viewmats, K):
    cam = torch.einsum("bmij,bnj->bmni", viewmats[..., :3, :3], joints) + viewmats[..., None, :3, 3]
    uv = torch.einsum("bmij,bmnj->bmni", K, cam / cam[..., 2:])[..., :2]
    return uv


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.5, 3.0))
def test_exact_detections_cost_nothing_and_shifts_cost_their_size(seed, shift_px):
    g = torch.Generator().manual_seed(seed)
    joints = torch.rand(2, 24, 3, generator=g) - 0.5
    viewmats, K = _views(2, 3, seed)
    uv = _project(joints, viewmats, K)
    conf = torch.rand(2, 3, 24, generator=g) + 0.1
    kp = torch.cat([uv, conf[..., None]], -1)
    assert keypoint_term(joints, viewmats, K, kp, 64).item() < 1e-5
    shifted = kp.clone()
    shifted[..., 0] += shift_px
    assert abs(keypoint_term(joints, viewmats, K, shifted, 64).item() - shift_px / 64) < 1e-4


def test_zero_confidence_joints_are_ignored_and_gradients_flow():
    joints = (torch.rand(1, 24, 3) - 0.5).requires_grad_()
    viewmats, K = _views(1, 2)
    kp = torch.cat([_project(joints.detach(), viewmats, K), torch.zeros(1, 2, 24, 1)], -1)
    kp[..., 5, 2] = 1.0
    kp[..., 5, 0] += 6.4  # only joint 5 is detected, 0.1 image widths off
    kp[..., 7, 0] += 50.0  # wrong but confidence 0: ignored
    loss = keypoint_term(joints, viewmats, K, kp, 64)
    assert abs(loss.item() - 0.1) < 1e-4
    loss.backward()
    assert joints.grad[0, 5].abs().sum() > 0 and joints.grad[0, 7].abs().sum() == 0


def test_landmark_mapping():
    lm = np.zeros((33, 3), np.float32)
    lm[:, 0] = np.arange(33)
    lm[:, 1] = 100 + np.arange(33)
    lm[:, 2] = 0.9
    lm[24, 2] = 0.3
    lm[:, 2] *= 0.8  # confidence = visibility x presence (0.8)
    out = keypoints_from_landmarks(lm[None])[0].numpy()
    assert out.shape == (24, 3)
    assert np.allclose(out[0, :2], [23.5, 123.5]) and np.isclose(
        out[0, 2], 0.8 * 0.3
    )  # pelvis: mid-hips
    assert np.allclose(out[16, :2], [11, 111]) and np.isclose(out[16, 2], 0.72)  # left shoulder
    unmapped = [j for j in range(24) if j not in BODY_FROM_BLAZEPOSE]
    assert np.all(out[unmapped] == 0)


def test_keypoint_points_are_the_landmarks_virtual_markers():
    """The keypoint term compared the landmarks with the body model's joints, which they are
    not (a review measured the landmarks' pelvis 25 mm low, hips 39 mm narrow, shoulders
    20-30 mm high against the joints); it compares them with the virtual markers of
    gst.body.markers, checked here against MarkerModel.positions in another frame."""
    from scipy.spatial.transform import Rotation

    from gst.body import load_body_model
    from gst.body.markers import MarkerModel
    from gst.model.assemble import to_world
    from gst.train.keypoints import BODY_FROM_BLAZEPOSE, marker_keypoints

    body, markers = load_body_model("anny"), MarkerModel.load()
    g = torch.Generator().manual_seed(0)
    B = 3
    pose = 0.3 * torch.randn(B, 23, 3, generator=g)
    rot = torch.as_tensor(Rotation.random(B, random_state=1).as_matrix(), dtype=torch.float32)
    from kornia.geometry.conversions import axis_angle_to_rotation_matrix

    out = body(
        0.5 * torch.randn(B, body.num_betas, generator=g),
        axis_angle_to_rotation_matrix(pose.reshape(-1, 3)).reshape(B, 23, 3, 3),
        rot,
        torch.tensor([[0.1, -0.2, 3.0]]).expand(B, 3),
        vertex_ids=markers.vertex_ids,
        return_transforms=True,
    )
    R_in = torch.as_tensor(Rotation.random(B, random_state=2).as_matrix(), dtype=torch.float32)
    t_in = torch.randn(B, 3, generator=g)
    got = marker_keypoints(
        to_world(out.joints, R_in, t_in), out.joint_transforms[..., :3, :3], R_in, markers
    )
    ref = to_world(markers.positions(out), R_in, t_in)
    for j, src in BODY_FROM_BLAZEPOSE.items():
        torch.testing.assert_close(got[:, j], ref[:, list(src)].mean(1), atol=1e-5, rtol=0)
    other = [j for j in range(24) if j not in BODY_FROM_BLAZEPOSE]
    torch.testing.assert_close(got[:, other], to_world(out.joints, R_in, t_in)[:, other])
    # and they are not the joints: the hips' markers lie centimetres from the hip joints
    assert float((got[:, 1] - to_world(out.joints, R_in, t_in)[:, 1]).norm(dim=-1).min()) > 0.01


def test_the_training_task_carries_the_markers_when_the_keypoint_term_is_on():
    from gst.body import load_body_model
    from gst.model.presets import get_preset
    from gst.train.losses import LossWeights
    from gst.train.recipe import make_task

    body, cfg = load_body_model("anny"), get_preset("tiny")
    assert make_task(body, [0], cfg, 128, LossWeights(keypoints=10.0)).markers is not None
    assert make_task(body, [0], cfg, 128, LossWeights(keypoints=0.0)).markers is None
    off = make_task(body, [0], cfg, 128, LossWeights(keypoints=10.0), keypoint_markers=False)
    assert off.markers is None


def test_the_projections_stay_float32_under_bf16_autocast():
    """Under bf16 autocast (train.amp) the keypoint term's and the 2D terms' projections ran in
    bf16: exact detections of a body 5 m from the world origin cost 0.18 px at 64 px."""
    from gst.train.steps import project

    g = torch.Generator().manual_seed(0)
    joints = torch.randn(4, 24, 3, generator=g) * 0.3 + torch.tensor([4.0, 3.0, 1.0])
    viewmats, K = _views(4, 3)
    viewmats[..., :3, 3] = torch.tensor([-4.0, -3.0, 4.0])  # the person ~4 m in front
    uv = _project(joints, viewmats, K)
    kp = torch.cat([uv, torch.ones(4, 3, 24, 1)], -1)
    cam = joints @ viewmats[:, 0, :3, :3].transpose(1, 2) + viewmats[:, 0, None, :3, 3]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        term = keypoint_term(joints, viewmats, K, kp, 64)
        px = project(cam, K[:, 0])
    assert term.dtype == torch.float32 and term.item() * 64 < 1e-3
    assert px.dtype == torch.float32
    torch.testing.assert_close(px, uv[:, 0], atol=1e-3, rtol=0)

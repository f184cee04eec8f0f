"""Appearance on the rig's body (gst.train.teacher_render): the network's Gaussians posed on
another body, and targets from synthetic truth."""

from __future__ import annotations

import pytest
import torch

from gst.model.presets import get_preset
from gst.train.distill_targets import DistillTargets
from gst.train.losses import LossWeights
from gst.train.recipe import build_network, make_task
from gst.train.steps import predict
from gst.train.teacher_render import teacher_posed_gaussians, truth_targets


@pytest.fixture(scope="module")
def scene(one_sample):
    """The shared one-person scene (tests/conftest.py (4 cameras, 2 frames) and a tiny network's
    prediction on every crop."""
    crops, _, body = one_sample
    net, ids, _ = build_network(get_preset("tiny"), body, seed=0)
    task = make_task(body, ids, net.cfg, 128, LossWeights(lpips=0.0))
    with torch.no_grad():
        pred = predict(net, task, crops.images, crops.K, crops.R, crops.t, with_gaussians=True)
    return crops, body, task, pred


def _own_body(pred, R) -> DistillTargets:
    """Targets that describe the prediction's own body (global orientation camera -> world)."""
    n = len(pred.betas)
    return DistillTargets(
        joints_world=pred.joints_world.clone(),
        joint_weight=torch.ones(n, 24),
        global_orient=R.transpose(1, 2) @ pred.rotmats[:, 0],
        body_pose=pred.rotmats[:, 1:].clone(),
        betas=pred.betas.clone(),
        weight=torch.ones(n),
    )


def test_gaussians_posed_on_their_own_body_are_where_the_prediction_put_them(scene):
    crops, body, task, pred = scene
    g = teacher_posed_gaussians(pred, _own_body(pred, crops.R), body, task.vertex_ids)
    own = pred.gaussians_world
    torch.testing.assert_close(g.means, own.means, atol=2e-5, rtol=0)
    # quaternions up to sign
    dots = (g.quats * own.quats).sum(-1).abs()
    assert float(dots.min()) > 1 - 1e-5
    for name in ("scales", "opacities", "colors", "offsets"):
        assert torch.equal(getattr(g, name), getattr(own, name))


def test_the_teacher_decides_where_and_rows_without_one_keep_their_own(scene):
    crops, body, task, pred = scene
    t = _own_body(pred, crops.R)
    shift = torch.tensor([0.3, -0.2, 0.1])
    t.joints_world = t.joints_world + shift  # the teacher's body stands elsewhere
    t.weight[0] = 0.0  # no target for row 0
    g = teacher_posed_gaussians(pred, t, body, task.vertex_ids)
    own = pred.gaussians_world
    assert torch.equal(g.means[0], own.means[0]) and torch.equal(g.quats[0], own.quats[0])
    torch.testing.assert_close(g.means[1:], own.means[1:] + shift, atol=2e-5, rtol=0)
    # the teacher's pose, not the prediction's: another elbow angle moves the forearm's splats
    t.body_pose[:, 17] = torch.linalg.matrix_exp(
        torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    )
    bent = teacher_posed_gaussians(pred, t, body, task.vertex_ids)
    moved = (bent.means[1:] - g.means[1:]).norm(dim=-1)
    assert float(moved.max()) > 0.05 and float(moved.median()) < 1e-6


def test_truth_targets_pose_the_true_body(scene):
    crops, body, _, _ = scene
    t = truth_targets(crops)
    assert bool((t.weight == 1).all())
    nb = body.num_betas
    posed = body(t.betas[:, :nb], t.body_pose, t.global_orient, torch.zeros(len(t), 3))
    joints = posed.joints - posed.joints[:, :1] + t.joints_world[:, :1]
    torch.testing.assert_close(joints, t.joints_world, atol=2e-3, rtol=0)


def test_prediction_without_gaussians_is_refused(scene):
    crops, body, task, pred = scene
    from dataclasses import replace

    with pytest.raises(ValueError, match="no Gaussians"):
        teacher_posed_gaussians(
            replace(pred, gaussians_world=None), _own_body(pred, crops.R), body, task.vertex_ids
        )


def test_multiview_terms_render_on_the_teacher_when_asked(scene):
    """With `appearance_on_teacher` the image terms are those of the Gaussians posed on the
    batch's targets: on the true body the rendered silhouette meets the masks, with the body
    1 m away it misses them; without the switch the targets change nothing."""
    from dataclasses import replace

    from gst.train.steps import multiview_image_terms
    from gst.train.views import sample_multiview

    crops, body, task, pred = scene
    net, ids, _ = build_network(get_preset("tiny"), body, seed=0)
    weights = LossWeights(lpips=0.0, distill_joints=0.0, distill_root=0.0, distill_params=0.0)
    parts = {}
    for shift in (0.0, 1.0):
        targets = truth_targets(crops)
        targets.joints_world = targets.joints_world + torch.tensor([shift, shift, 0.0])
        shifted = replace(crops, distill=targets)
        b = sample_multiview(shifted, shifted.groups(), torch.Generator().manual_seed(0), 2, 2, 32)
        for on in (False, True):
            t = make_task(body, ids, net.cfg, 128, weights, appearance_on_teacher=on)
            with torch.no_grad():
                parts[shift, on] = multiview_image_terms(net, b, t)[3]
    assert float(parts[0.0, True]["alpha"]) < 0.7 * float(parts[1.0, True]["alpha"])
    assert float(parts[0.0, False]["alpha"]) == float(parts[1.0, False]["alpha"])

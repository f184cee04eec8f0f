"""Frames held out in time and held-out cameras never enter a training batch (distillation
targets included), nor the checkpoint choice; a landmark network gets its inputs' landmarks."""

from __future__ import annotations

import torch

import gst.train.recipe as recipe
from gst.body import BodyModel
from gst.body.random_model import random_body_data
from gst.model.checkpoint import load_checkpoint
from gst.model.presets import get_preset
from gst.train.distill_targets import DistillTargets
from gst.train.evaluation import novel_view_pairs
from gst.train.losses import LossWeights
from gst.train.recipe import FitOptions, build_network, fit_gst, make_task
from gst.train.trainer import TrainConfig
from tests.test_train_recipe import crop_set


def test_heldout_frames_and_cameras_never_reach_a_batch(tmp_path, monkeypatch):
    body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
    cfg = get_preset("tiny", vertex_preset="full", landmark_tokens=True, num_landmarks=33)
    net, ids, groups = build_network(cfg, body)
    crops = crop_set(n_frames=8, n_cams=3)
    n = len(crops)
    crops.landmarks = torch.cat([torch.rand(n, 33, 2) * 64, torch.rand(n, 33, 1)], -1)
    crops.distill = DistillTargets.empty(n)
    crops.distill.weight[:] = 1.0  # a target everywhere: the sampler alone must keep them out
    crops.distill.joints_world = crops.truth["joints_world"].clone()
    seen = []
    real = recipe.sample_multiview

    def spy(*args, **kwargs):
        batch = real(*args, **kwargs)
        seen.append(batch)
        return batch

    monkeypatch.setattr(recipe, "sample_multiview", spy)
    task = make_task(body, ids, cfg, crops.crop_size, LossWeights(lpips=0.0))
    fit_gst(
        net, task, crops,
        TrainConfig(steps=6, batch_size=4, warmup_steps=1, val_every=3, log_every=1),
        tmp_path,
        FitOptions(mode="multiview", num_targets=2, render_size=16, heldout_cameras=("c2",),
                   first_heldout_frame=6, landmark_dropout=0.5, scene="s"),
        body_spec="random", vertex_ids=ids, group_index=groups,
    )  # fmt: skip
    assert len(seen) == 6
    for b in seen:
        rows = torch.cat([b.input_index, b.target_index.flatten()])
        assert (crops.frame[rows] < 6).all() and (crops.camera[rows] != 2).all()
        assert b.input_landmarks is not None and b.distill is not None
        assert torch.equal(b.distill.joints_world, crops.distill.joints_world[b.input_index])
    dropped = torch.cat([torch.isnan(b.input_landmarks).all(-1).all(-1) for b in seen])
    assert 0 < dropped.float().mean() < 1  # landmark dropout hides some inputs' landmarks
    extra = load_checkpoint(tmp_path / "best.pt").extra
    assert extra["first_heldout_frame"] == 6 and extra["heldout_cameras"] == ["c2"]
    assert extra["trained_on"] == {"scene": "s", "cameras": ["c0", "c1"], "frames": [0, 5],
                                   "crops": 12, "crop_store": "extract"}  # fmt: skip
    # the checkpoint is chosen on held-out-camera views of training frames only
    pairs = novel_view_pairs(crops, {2}, frames=(0, 6))
    assert len(pairs.inputs) and (crops.frame[pairs.targets] < 6).all()


def test_every_heldout_camera_is_a_novel_view_target():
    """With cameras 2 and 3 held out, training's novel-view pairs scored camera 2 only (the
    first held-out view of every group); with one held-out camera the pairs are as before."""
    crops = crop_set(n_frames=10, n_cams=4)
    pairs = novel_view_pairs(crops, {2, 3}, max_pairs=64)
    counts = torch.bincount(crops.camera[pairs.targets], minlength=4).tolist()
    assert counts[0] == counts[1] == 0 and counts[2] > 0 and counts[3] > 0, counts
    one = novel_view_pairs(crops, {2}, max_pairs=64)
    assert set(crops.camera[one.targets].tolist()) == {2}
    assert set(crops.camera[one.inputs].tolist()) <= {0, 1, 3}


def test_groups_never_mix_frames_whatever_the_person_ids():
    """Person id -1 (a person the association left unnamed) in frame 1 had the key of the
    highest id in frame 0: one 'multi-view' group rendered one frame's person into another
    frame's views (and a held-out frame's crop could join a training frame's group)."""
    from gst.train.views import CropSet

    n = 4
    crops = CropSet(
        images=torch.zeros(n, 8, 8, 3, dtype=torch.uint8),
        masks=torch.zeros(n, 8, 8),
        K=torch.eye(3).repeat(n, 1, 1),
        R=torch.eye(3).repeat(n, 1, 1),
        t=torch.zeros(n, 3),
        camera=torch.tensor([0, 1, 0, 1]),
        frame=torch.tensor([0, 0, 1, 1]),
        person=torch.tensor([0, 0, -1, 0]),
        camera_names=["c0", "c1"],
    )
    for g in crops.groups(min_views=1):
        assert len(set(crops.frame[g].tolist())) == 1, g
        assert len(set(crops.person[g].tolist())) == 1, g
    assert sorted(len(g) for g in crops.groups(min_views=1)) == [1, 1, 2]

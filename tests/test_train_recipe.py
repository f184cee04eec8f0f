"""fit_gst in every mode on a small random crop set: runs, checkpoints, finite numbers."""

from __future__ import annotations

import math

import pytest
import torch

from gst.body import BodyModel
from gst.body.random_model import random_body_data
from gst.model.checkpoint import load_checkpoint, network_from_checkpoint
from gst.model.presets import get_preset
from gst.train.losses import LossWeights
from gst.train.recipe import FitOptions, build_network, fit_gst, make_task
from gst.train.trainer import TrainConfig
from gst.train.views import CropSet


def crop_set(n_frames=4, n_cams=3, size=64) -> CropSet:
    gen = torch.Generator().manual_seed(0)
    n = n_frames * n_cams
    cam = torch.arange(n) % n_cams
    angle = 2 * math.pi * cam.float() / n_cams
    R = torch.zeros(n, 3, 3)  # cameras on a ring 3 m from the origin, looking at it
    R[:, 0, 0], R[:, 0, 2] = torch.cos(angle), -torch.sin(angle)
    R[:, 1, 1] = 1
    R[:, 2, 0], R[:, 2, 2] = torch.sin(angle), torch.cos(angle)
    t = torch.tensor([0.0, 0.0, 3.0]).expand(n, 3)
    K = torch.tensor([[120.0, 0, size / 2], [0, 120.0, size / 2], [0, 0, 1]]).expand(n, 3, 3)
    joints_world = 0.3 * torch.randn(n_frames, 24, 3, generator=gen)[torch.arange(n) // n_cams]
    joints_cam = joints_world @ R.transpose(1, 2) + t[:, None]
    uv = joints_cam[..., :2] / joints_cam[..., 2:] * 120 + size / 2
    truth = {
        "joints_world": joints_world,
        "joints_cam": joints_cam,
        "joints2d": uv,
        "visible": torch.ones(n, 24),
        "rotmats_cam": torch.eye(3).expand(n, 24, 3, 3).clone(),
        "betas": torch.zeros(n, 10),
    }
    return CropSet(
        images=torch.randint(0, 255, (n, size, size, 3), generator=gen, dtype=torch.uint8),
        masks=(torch.rand(n, size, size, generator=gen) > 0.5).float(),
        K=K.clone(),
        R=R,
        t=t.clone(),
        camera=cam,
        frame=torch.arange(n) // n_cams,
        person=torch.zeros(n, dtype=torch.long),
        camera_names=[f"c{i}" for i in range(n_cams)],
        truth=truth,
    )


def small_fit(
    tmp_path, mode="multiview", heldout=("c2",), *, steps=2, device="cpu", rehearse=False
):
    """fit_gst on `crop_set()` with the tiny preset: (network, body, summary). `rehearse`: the
    open body, landmark tokens and the landmark prior rehearsed beside each step."""
    torch.manual_seed(0)
    if rehearse:
        from gst.body import load_body_model
        from gst.lift.rehearsal import PriorRehearsal

        body = load_body_model("anny")
        cfg = get_preset("tiny", landmark_tokens=True)
    else:
        body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
        cfg = get_preset("tiny", vertex_preset="full")
    net, ids, groups = build_network(cfg, body)
    crops = crop_set()
    task = make_task(body, ids, cfg, crops.crop_size, LossWeights(lpips=0.0))
    summary = fit_gst(
        net,
        task,
        crops,
        TrainConfig(
            steps=steps, batch_size=2, warmup_steps=1, val_every=steps, log_every=1, device=device
        ),
        tmp_path,
        FitOptions(mode=mode, num_targets=2, render_size=16, heldout_cameras=heldout),
        body_spec="anny" if rehearse else "random",
        vertex_ids=ids,
        group_index=groups,
        rehearsal=PriorRehearsal(body, net, batch_size=2) if rehearse else None,
    )
    return net, body, summary


@pytest.mark.parametrize(
    "mode, heldout", [("multiview", ("c2",)), ("pretrain", ()), ("3d", ()), ("2d", ())]
)
def test_fit_gst_modes(tmp_path, mode, heldout):
    _, _, summary = small_fit(tmp_path, mode, heldout)
    assert summary.steps == 2 and summary.bad_steps == 0
    assert all(math.isfinite(v) for v in summary.after.values())
    if heldout:
        assert {"psnr", "ssim", "silhouette_iou"} <= set(summary.after)
        import csv

        vals = [
            float(r["val_silhouette_iou"])
            for r in csv.DictReader(open(tmp_path / "log.csv"))
            if r.get("val_silhouette_iou")
        ]
        assert vals  # the held-out cameras' scores are watched in log.csv
    assert "mpjpe_mm" in summary.after
    reloaded = network_from_checkpoint(load_checkpoint(tmp_path / "best.pt"))
    assert reloaded.num_query_tokens == 5 * 26 + 1
    # the kept model is the last step's: never chosen on held-out cameras (their novel-view
    # scores would be a validation result) nor on the scene's truth (its 3D labels)
    assert summary.best is None
    last = network_from_checkpoint(load_checkpoint(tmp_path / "last.pt")).state_dict()
    for k, v in reloaded.state_dict().items():
        assert torch.equal(v, last[k]), k


def test_heldout_camera_must_exist(tmp_path):
    body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
    cfg = get_preset("tiny", vertex_preset="full")
    net, ids, groups = build_network(cfg, body)
    crops = crop_set()
    task = make_task(body, ids, cfg, crops.crop_size, LossWeights(lpips=0.0))
    with pytest.raises(ValueError, match="held-out cameras"):
        fit_gst(
            net,
            task,
            crops,
            TrainConfig(steps=1),
            tmp_path,
            FitOptions(heldout_cameras=("nope",)),
            body_spec="random",
            vertex_ids=ids,
            group_index=groups,
        )


def test_augmented_3d_fit_validates_on_the_unseen_crops(tmp_path):
    """With val_crops, the reported MPJPE is on them: a validation set whose truth is shifted by a
    constant per-joint offset reports a different error than the training crops."""
    from gst.train.augment import CropJitter

    body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
    cfg = get_preset("tiny", vertex_preset="full")
    crops, val = crop_set(), crop_set(n_frames=2)
    val.truth["joints_world"] = (
        val.truth["joints_world"] + 0.5 * torch.linspace(0, 1, 24)[None, :, None]
    )

    def fit(val_crops, out):
        net, ids, groups = build_network(cfg, body)
        task = make_task(body, ids, cfg, crops.crop_size, LossWeights(lpips=0.0))
        return fit_gst(
            net,
            task,
            crops,
            TrainConfig(steps=2, batch_size=2, warmup_steps=1, val_every=2),
            out,
            FitOptions(mode="3d", augment=CropJitter()),
            body_spec="random",
            vertex_ids=ids,
            group_index=groups,
            val_crops=val_crops,
        )

    own, unseen = fit(None, tmp_path / "a"), fit(val, tmp_path / "b")
    assert unseen.bad_steps == 0 and math.isfinite(unseen.after["mpjpe_mm"])
    assert abs(unseen.after["mpjpe_mm"] - own.after["mpjpe_mm"]) > 50


def test_multiview_fit_uses_anchors_when_the_crops_have_them(tmp_path):
    """With only the anchor term on, training pulls each body's centre towards its anchor."""
    import csv

    from gst.train.steps import predict

    body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
    cfg = get_preset("tiny", vertex_preset="full")
    net, ids, groups = build_network(cfg, body)
    crops = crop_set()
    only_anchor = LossWeights(
        mse=0.0, lpips=0.0, alpha=0.0, tightness=0.0, anchor=1.0, keypoints=0.0
    )
    task = make_task(body, ids, cfg, crops.crop_size, only_anchor)

    def centres() -> torch.Tensor:
        with torch.no_grad():
            g = predict(net.eval(), task, crops.images, crops.K, crops.R, crops.t).gaussians_world
        return g.means.mean(1)

    before = centres()
    # Half a metre to each input camera's right: one shift of the predicted body that every
    # view can make (the crops are noise, so the network cannot tell the cameras apart).
    right = crops.R.transpose(1, 2) @ torch.tensor([0.5, 0.0, 0.0])
    crops.anchors = before + right
    fit_gst(
        net.train(),
        task,
        crops,
        TrainConfig(steps=20, batch_size=4, lr=2e-3, warmup_steps=1, val_every=20, log_every=1),
        tmp_path,
        FitOptions(mode="multiview", num_targets=2, render_size=16),
        body_spec="random",
        vertex_ids=ids,
        group_index=groups,
    )
    rows = list(csv.DictReader(open(tmp_path / "log.csv")))
    assert all(math.isfinite(float(r["anchor"])) for r in rows)
    dist_before = (before - crops.anchors).norm(dim=1)
    dist_after = (centres() - crops.anchors).norm(dim=1)
    assert float(dist_after.max()) < 0.8 * float(dist_before.min()), (dist_before, dist_after)


def test_after_scores_the_model_the_caller_keeps(tmp_path):
    """The image pretraining keeps best.pt (chosen on the unseen world), but its summary's
    `after` scored the last step's model; `after_from="best"` scores, and returns, best.pt's."""
    body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
    cfg = get_preset("tiny", vertex_preset="full")
    crops, val = crop_set(), crop_set(n_frames=2)
    torch.manual_seed(0)
    net, ids, groups = build_network(cfg, body)
    task = make_task(body, ids, cfg, crops.crop_size, LossWeights(lpips=0.0))
    summary = fit_gst(
        net,
        task,
        crops,
        # a rate high enough that the validation error moves from one validation to the next
        TrainConfig(steps=6, batch_size=2, lr=3e-3, warmup_steps=1, val_every=1),
        tmp_path,
        FitOptions(mode="3d"),
        body_spec="random",
        vertex_ids=ids,
        group_index=groups,
        val_crops=val,
        after_from="best",
    )
    assert summary.after["mpjpe_mm"] == pytest.approx(summary.best, rel=1e-5)
    best = load_checkpoint(tmp_path / "best.pt").model
    for k, v in net.state_dict().items():
        assert torch.equal(v, best[k]), k
    with pytest.raises(ValueError, match="after_from"):
        fit_gst(
            net, task, crops, TrainConfig(steps=1), tmp_path / "x", FitOptions(),
            body_spec="random", vertex_ids=ids, group_index=groups, after_from="first",
        )  # fmt: skip


def test_supervised_batches_carry_the_scenes_up(tmp_path, monkeypatch):
    """The 2d/3d baselines gave a gravity-aware network the up of a z-up world whatever the
    scene's rig said (validation and tracking read the rig's): a y-up rig trained on a wrong up."""
    import gst.train.recipe as recipe
    from gst.model.landmarks import camera_up

    body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
    cfg = get_preset("tiny", vertex_preset="full")
    net, ids, groups = build_network(cfg, body)
    crops = crop_set(n_frames=2, n_cams=2)
    task = make_task(body, ids, cfg, crops.crop_size, LossWeights(lpips=0.0), world_up=(0, 1, 0))
    seen = []
    real = recipe.supervised_step

    def spy(m, b, t):
        seen.append(b)
        return real(m, b, t)

    monkeypatch.setattr(recipe, "supervised_step", spy)
    fit_gst(
        net, task, crops, TrainConfig(steps=1, batch_size=2, warmup_steps=1, val_every=1),
        tmp_path, FitOptions(mode="3d"), body_spec="random", vertex_ids=ids, group_index=groups,
    )  # fmt: skip
    assert seen
    for b in seen:
        rows = [
            int(torch.nonzero((crops.images == img).all(-1).all(-1).all(-1))[0]) for img in b.images
        ]
        torch.testing.assert_close(b.up, camera_up(crops.R[rows], (0.0, 1.0, 0.0)))

"""pretrain: supervised pretraining on synthetic people, our stand-in for HMR2's 3D-labelled start.

It renders its own synthetic world (a different rig, other people, outfits and motions than any
target scene), cuts crops with exact truth, and trains the network with 3D joint and parameter
supervision plus the multi-view image terms (so the Gaussian head starts sane). Writes
`models/pretrain.pt` (a GST checkpoint) and `reports/pretrain/`.
"""

from __future__ import annotations

import json
import shutil
from typing import Literal

import torch

from gst.body import load_body_model
from gst.metrics.lpips import load_lpips
from gst.model.presets import PRESETS, get_preset
from gst.train.losses import LossWeights
from gst.train.recipe import FitOptions, build_network, fit_gst, make_task
from gst.train.synthetic_crops import crops_from_synth_scene
from gst.train.trainer import TrainConfig
from pipeline.stage import Stage, StageContext, StageParams
from synth.scene import preset, render_scene


class Params(StageParams):
    preset: Literal[tuple(PRESETS)] = "tiny"  # type: ignore[valid-type]
    body_model: str = "anny"  # or a path to your SMPL file (docs/body_model.md)
    world_seed: int = 1000  # the pretraining world differs from every scene by construction
    world_rig: Literal["dome", "h36m", "hall"] = "dome"  # its own seed: other camera positions
    world_frames: int = 60
    world_people: int = 3
    crop_size: int = 256
    mode: Literal["3d", "pretrain"] = "3d"  # "pretrain" also trains the Gaussian head by rendering (slower)
    steps: int = 1000
    batch_size: int = 8
    lr: float = 5e-4
    num_targets: int = 3
    render_size: int = 64
    losses: LossWeights = LossWeights()
    threads: int | None = None  # torch CPU threads (default: torch's choice)


def run(ctx: StageContext) -> None:
    p = ctx.params
    if p.threads:
        torch.set_num_threads(p.threads)
    world = ctx.staging / "world"
    if not (world / "scene.json").is_file():
        spec = preset("demo", seed=p.world_seed, n_frames=p.world_frames, n_people=p.world_people,
                      motions=None, rig={"kind": p.world_rig, "n_cameras": 8, "width": 480, "height": 360},
                      board={"n_frames": 1}).model_copy(update={"name": "pretrain"})
        summary = render_scene(spec, world)
        ctx.log.info("pretraining world: %d frames x %d cameras in %.0f s", summary.n_frames, len(summary.cameras),
                     summary.seconds)
    crops = crops_from_synth_scene(world, crop_size=p.crop_size, progress=ctx.progress)
    ctx.log.info("pretraining crops: %d", len(crops))
    body = load_body_model(p.body_model)
    cfg = get_preset(p.preset)
    net, ids, groups = build_network(cfg, body)
    lpips = load_lpips() if p.losses.lpips > 0 and p.mode == "pretrain" else None
    task = make_task(body, ids, cfg, crops.crop_size, p.losses, lpips)
    train_cfg = TrainConfig(steps=p.steps, batch_size=p.batch_size, lr=p.lr, warmup_steps=min(30, p.steps // 10),
                            val_every=max(1, p.steps // 4), ckpt_every=25, log_every=5)
    out = ctx.out("models/pretrain_run")
    summary = fit_gst(net, task, crops, train_cfg, out, FitOptions(mode=p.mode, num_targets=p.num_targets,
                      render_size=p.render_size), body_spec=p.body_model, vertex_ids=ids, group_index=groups,
                      progress=ctx.progress)
    shutil.copyfile(out / "last.pt", ctx.out("models/pretrain.pt"))
    reports = ctx.out("reports/pretrain")
    reports.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(out / "log.csv", reports / "log.csv")
    (reports / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
    ctx.log.info("pretrain: MPJPE on its own world %.1f -> %.1f mm", summary["before"].get("mpjpe_mm", float("nan")),
                 summary["after"].get("mpjpe_mm", float("nan")))
    shutil.rmtree(out)
    shutil.rmtree(world)


STAGE = Stage(name="pretrain", run=run, params_model=Params, resumable=True,
              outputs=lambda ctx: ["models/pretrain.pt", "reports/pretrain"],
              help="supervised pretraining on a separate synthetic world (stand-in for HMR2 weights)")

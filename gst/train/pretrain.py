"""Pretraining on synthetic people, our stand-in for HMR2's 3D-labelled start.

Mode `lift` (the default; docs/landmark_prior.md): a network with landmark tokens first learns
to lift BlazePose landmarks to a body without rendering a single image (`gst.lift.pretrain`:
simulated detections of sampled bodies, fresh every step), then a short rendered phase trains
the image path and the Gaussian head to work with the landmark tokens, on crops of a few
rendered worlds with the landmarks BlazePose finds in them (3D terms plus the multi-view image
terms). The image cross-attention starts silent (zero output), so the rendered phase starts
from the lifting path's pose exactly.

Modes `3d` / `pretrain` (the image-only network): it renders its own corpus of small synthetic
worlds, each with its own seed, rig (dome or H36M style, field of view drawn per world), person,
outfit and motions (every third world holds independent random poses), cuts crops with exact
truth, and trains the network with 3D joint and parameter supervision (optionally on jittered
crops, `gst.train.augment`), then briefly adds the multi-view image terms so the Gaussian head
learns to render (`gaussian_steps`). One more world is rendered and never trained on: pose
validation, the reported MPJPE and the choice of the kept checkpoint use it, so the number says
how the model does on people and cameras it has not seen. Writes `models/pretrain.pt` (a GST
checkpoint) and `reports/pretrain/`.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import torch
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    model_validator,
)

from gst.body import load_body_model
from gst.device import check_device_name
from gst.metrics.lpips import load_lpips
from gst.model.checkpoint import keep_model, load_checkpoint, network_from_checkpoint
from gst.model.inference import check_same_body
from gst.model.presets import PRESETS, get_preset
from gst.model.refine import DEFAULT_ROUNDS
from gst.param_types import NAMES_FILE
from gst.records import Record
from gst.train.augment import CropJitter
from gst.train.losses import LossWeights
from gst.train.recipe import FitOptions, FitSummary, build_network, fit_gst, make_task
from gst.train.synthetic_crops import crops_from_synth_scene
from gst.train.trainer import TrainConfig
from gst.train.views import CropSet, concat_crop_sets
from synth.scene import SceneSpec, preset, render_scene

log = logging.getLogger("gst.train")


def _track(progress, items, description: str):
    items = list(items)
    return items if progress is None else progress(items, description=description, total=len(items))


# the lift mode's crops: the pipeline's crop size, so BlazePose sees what it sees in extraction
LIFT_CROP_SIZE = 256


class PretrainConfig(BaseModel):
    """Settings of the supervised pretraining (the `pretrain` stage's parameters)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    # network size: tiny (CPU) to huge (the paper's, for GPUs; gst.model.presets)
    preset: Literal[tuple(PRESETS)] = "tiny"  # type: ignore[valid-type]
    # "anny", or a path to your SMPL file (docs/body_model.md)
    body_model: str = Field("anny", json_schema_extra=NAMES_FILE)
    # The world settings are bounded here as the scene spec bounds them, so that a bad value is
    # named as the pretrain setting (it was a ZeroDivisionError for world_rigs: [], numpy's
    # "expected non-negative integer" for a negative seed, SceneSpec's n_people / rig.fps /
    # rig.fov_deg for the others; static_every < 0 was taken as 0).

    # world k has seed world_seed + k (the validation world: world_seed + worlds);
    world_seed: NonNegativeInt = (
        1000  # the pretraining worlds differ from every scene by construction
    )
    worlds: PositiveInt = 12  # worlds trained on; one more (unseen) validates
    world_rigs: Annotated[list[Literal["dome", "h36m", "hall"]], Field(min_length=1)] = [
        "dome",
        "h36m",
    ]  # cycled over the worlds
    # cameras of each pretraining world (at least 2 where a multi-view phase runs: modes lift
    # and pretrain, and 3d with gaussian_steps)
    world_cameras: Annotated[int, Field(ge=1, le=256)] = 6
    world_frames: PositiveInt = 40  # per world
    world_fps: Annotated[float, Field(gt=0, le=1000)] = (
        10.0  # motions sampled at this rate: fewer near-duplicate poses per frame rendered
    )
    world_people: Annotated[int, Field(ge=1, le=255)] = (
        1  # one person per crop: with 3, crowded crops stalled learning (docs/training.md)
    )
    # horizontal field of view (deg), drawn per world (the scene spec's rig takes 5-150)
    world_fov_deg: tuple[
        Annotated[float, Field(gt=5, lt=150)], Annotated[float, Field(gt=5, lt=150)]
    ] = (40.0, 75.0)
    static_every: NonNegativeInt = (
        3  # every Nth world holds independent random poses instead of motions (0: none)
    )
    # modes 3d and pretrain, at least the network's input height (the tiny preset's input is
    # 128x96; larger presets need 256, which they take when crop_size is left out); mode lift
    # cuts 256 px crops, the pipeline's, and refuses another value
    crop_size: PositiveInt = 128
    # mode 3d: box (zoom/shift) and colour jitter of the supervised crops (docs/training.md)
    augment: bool = False
    # lift: landmark tokens, render-free lifting then a short rendered phase (module doc);
    # 3d / pretrain: the image-only network on rendered worlds ("pretrain" also renders)
    mode: Literal["lift", "3d", "pretrain"] = "lift"
    # lift mode: the landmark set (all 33, or the 12 limb landmarks), per-landmark tokens (off:
    # the lift tokens alone, as accurate at half the cost; docs/landmark_prior.md), the
    # render-free phase's steps, batch and rate, the rendered phase's rate for everything but
    # the Gaussian head (`gaussian_lr`), and the share of its samples trained without landmarks
    landmarks: Literal["all", "limbs"] = "all"
    landmark_point_tokens: bool = False  # lift mode: one token per landmark too
    # rounds of reprojection feedback after the SMPL head (gst.model.refine; 0: none)
    landmark_refine: NonNegativeInt = DEFAULT_ROUNDS
    lift_steps: PositiveInt = 1000  # steps of the render-free lifting phase
    lift_batch_size: PositiveInt = 64  # simulated samples per lifting step
    lift_lr: PositiveFloat = 1e-3  # lifting phase learning rate
    lift_body_lr: PositiveFloat = 1e-4  # rendered phase rate of all but the Gaussian head
    landmark_dropout: float = 0.1  # share of rendered-phase samples without landmarks
    # Then this many steps of mode "pretrain" from the kept 3d checkpoint: the Gaussian head learns
    # to render bodies whose pose is right. Without it the multi-view stage starts from an untrained
    # head and the demo's held-out renders come out as faint dots (docs/training.md).
    gaussian_steps: NonNegativeInt = 800
    # that phase's rate, of the whole network (mode "pretrain" trains every weight; its 3D
    # terms hold the pose while the Gaussian head, starting untrained, learns the most)
    gaussian_lr: PositiveFloat = 2e-4
    # lift mode: the rendered phase renders the Gaussians posed on each crop's true body (the
    # worlds' exact truth) instead of on the network's pose (gst.train.teacher_render), so that
    # the pose error does not teach them to shrink and fade (docs/training.md "Appearance on
    # the rig's body")
    appearance_on_truth: bool = True
    # steps of the rendered modes ("3d", "pretrain"); refused in mode lift, whose rendered phase
    # runs gaussian_steps
    steps: PositiveInt = 1000
    batch_size: PositiveInt = 8  # crops per step of the rendered modes
    # learning rate of the rendered modes ("3d", "pretrain"); refused in mode lift, whose
    # rendered phase takes gaussian_lr and lift_body_lr
    lr: PositiveFloat = 5e-4
    num_targets: PositiveInt = 3  # cameras each crop's Gaussians are rendered into per step
    render_size: PositiveInt = 64  # side (px) of those renders
    losses: LossWeights = LossWeights()  # loss weights (docs/training.md)
    threads: PositiveInt | None = None  # torch CPU threads (default: torch's choice)
    # where the rendered phases train (gst.device; auto: the GPU when PyTorch sees one). The
    # render-free lift phase and the world renders stay on the CPU.
    device: Annotated[str, AfterValidator(check_device_name)] = "auto"
    amp: bool = False  # bf16 autocast in the rendered phases (GPUs; docs/gpu.md)
    # An existing GST checkpoint to use as is instead of pretraining (e.g. another scene's
    # models/pretrain.pt: one pretraining serves every scene). Its content is part of the
    # fingerprint.
    reuse: Path | None = None

    @model_validator(mode="after")
    def _augment_where_it_acts(self):
        # the jitter acts on the 3d mode's supervised crops only: with mode pretrain or lift it
        # was accepted and did nothing
        if self.augment and self.mode != "3d":
            raise ValueError(
                f"augment jitters the supervised crops of mode '3d'; mode '{self.mode}' samples "
                "none (set augment: false, or mode: 3d)"
            )
        given = "crop_size" in self.model_fields_set  # the default (128) is the image modes'
        if self.mode == "lift" and given and self.crop_size != LIFT_CROP_SIZE:
            # accepted and ignored: the lift mode cuts its crops at the pipeline's crop size
            raise ValueError(
                f"crop_size ({self.crop_size}) sets the crops of modes '3d' and 'pretrain'; mode "
                "'lift' cuts 256 px crops, the pipeline's, so that BlazePose reads them as in "
                "extraction (leave crop_size out, or set mode: 3d)"
            )
        for name, instead in (("steps", "gaussian_steps"), ("lr", "gaussian_lr")):
            if self.mode == "lift" and name in self.model_fields_set:
                # accepted and ignored: mode lift's rendered phase runs gaussian_steps at
                # gaussian_lr (the Gaussian head) and lift_body_lr (the image path)
                raise ValueError(
                    f"{name} ({getattr(self, name)}) sets the run of modes '3d' and 'pretrain'; "
                    f"mode 'lift' does not use it: its rendered phase takes {instead} (leave "
                    f"{name} out, or set mode: 3d)"
                )
        side = get_preset(self.preset).image_size[0]  # the network's input is side x (3/4 side)
        if self.mode in ("3d", "pretrain") and self.crop_size < side and not given:
            self.crop_size = side  # the default follows the preset (128: tiny's input)
        if self.mode in ("3d", "pretrain") and self.crop_size < side:
            # accepted, the crops were upsampled to the network's input (huge: 128 px crops
            # blown up 2x), training a network on blurred images it never meets in the pipeline
            raise ValueError(
                f"crop_size ({self.crop_size}) is smaller than the '{self.preset}' "
                f"network's input ({side} px high): its crops would be upsampled; set crop_size "
                f"to at least {side}"
            )
        multiview = self.mode in ("lift", "pretrain") or self.gaussian_steps > 0
        if multiview and self.world_cameras < 2 and self.reuse is None:
            # accepted, it failed with "no training samples" after the renders (and in mode
            # lift the lifting and BlazePose on every crop): those phases sample a person seen
            # by two cameras
            raise ValueError(
                f"world_cameras ({self.world_cameras}) must be at least 2 in mode '{self.mode}'"
                + (" with gaussian_steps" if self.mode == "3d" else "")
                + ": its multi-view phase trains on people seen by two cameras"
            )
        if self.mode == "lift" and self.gaussian_steps == 0 and self.reuse is None:
            # accepted, it crashed on a missing last.pt after the lifting, the world renders and
            # the landmark model on every crop
            raise ValueError(
                "gaussian_steps: 0 leaves mode 'lift' without its rendered phase, which trains "
                "the Gaussian head and gives the kept model; use at least 1 (0 skips the Gaussian "
                "phase in mode '3d')"
            )
        return self


def world_specs(p: PretrainConfig) -> list[dict]:
    """Scene specs of the corpus: `p.worlds` training worlds, then the validation world."""
    specs = []
    for k in range(p.worlds + 1):
        seed = p.world_seed + k
        rng = np.random.default_rng(np.random.SeedSequence([seed, 0x9E7]))
        # independent random poses in every `static_every`-th training world; the validation
        # world plays motions, as the scenes the model is for do
        static = p.static_every > 0 and k < p.worlds and k % p.static_every == p.static_every - 1
        spec = preset(
            "demo",
            seed=seed,
            n_frames=p.world_frames,
            n_people=p.world_people,
            motions=[["random_static"]] * p.world_people if static else None,
            rig={
                "kind": p.world_rigs[k % len(p.world_rigs)],
                "n_cameras": p.world_cameras,
                "width": 480,
                "height": 360,
                "fps": p.world_fps,
                "fov_deg": float(rng.uniform(*p.world_fov_deg)),
            },
            board={"n_frames": 1},
        )
        specs.append(
            spec.model_copy(
                update={"name": "pretrain_val" if k == p.worlds else f"pretrain_{k:02d}"}
            ).model_dump(mode="json")
        )
    return specs


def render_world(item: tuple[dict, str]) -> str:
    """Render one corpus world (skipped when that world, finished, is there: the stage
    resumes)."""
    spec, out = item
    done = Path(out) / "scene.json"
    # Kept only if it is this spec: a folder of the same name from other settings (a work
    # folder reused with another `worlds`) was kept, and its old 'pretrain_val' could be a
    # training world of the new corpus.
    try:
        same = done.is_file() and json.loads(done.read_text()).get("spec") == spec
    except (OSError, ValueError, AttributeError):
        same = False
    if not same:
        render_scene(SceneSpec.model_validate(spec), Path(out))
    return out


@dataclass(frozen=True)
class ReusedCheckpoint(Record):
    """The pretrain summary when `pretrain.reuse` copies an existing checkpoint."""

    reused: str


@dataclass(frozen=True)
class CorpusSummary(Record):
    """The summary's `corpus` entry: the worlds trained on, the validation world, crop counts."""

    worlds: list[str]
    validation_world: str
    train_crops: int
    validation_crops: int


@dataclass(frozen=True)
class ImagePretrainSummary:
    """What `pretrain_images` returns (and writes as summary.json): the corpus run, the
    Gaussian-head run when mode `3d` has `gaussian_steps`, and the corpus."""

    fit: FitSummary
    corpus: CorpusSummary
    gaussians: FitSummary | None = None

    @property
    def kept(self) -> FitSummary:
        """The run whose model is kept: the Gaussian-head run when there is one."""
        return self.fit if self.gaussians is None else self.gaussians

    def to_dict(self) -> dict:
        """summary.json: the corpus run's fields, then `gaussians` (when run) and `corpus`."""
        out = self.fit.to_dict()
        if self.gaussians is not None:
            out["gaussians"] = self.gaussians.to_dict()
        out["corpus"] = self.corpus.to_dict()
        return out


def reuse_checkpoint(p: PretrainConfig, checkpoint: Path, reports: Path) -> ReusedCheckpoint:
    ckpt = load_checkpoint(p.reuse)  # weights_only: a GST checkpoint or a clear error
    # compared by content where the specs differ: the same file at another path is that body
    check_same_body(
        ckpt,
        p.body_model,
        lambda: load_body_model(p.body_model),
        f"pretrain.reuse={p.reuse}",
        "pretrain.body_model",
    )
    preset = ckpt.config.get("name") if isinstance(ckpt.config, dict) else None
    if preset is not None and preset != p.preset:
        # training builds the network the file holds, whatever pretrain.preset says
        log.warning(
            "pretrain.reuse=%s holds a '%s' network; pretrain.preset '%s' is not used",
            p.reuse, preset, p.preset,
        )  # fmt: skip
    # the network it holds, built before the copy: weights that do not fit it, or that are not
    # finite, are refused naming the user's file, not models/pretrain.pt in the train stage
    network_from_checkpoint(ckpt, p.reuse)
    shutil.copyfile(p.reuse, checkpoint)
    reports.mkdir(parents=True, exist_ok=True)
    summary = ReusedCheckpoint(reused=str(p.reuse))
    (reports / "summary.json").write_text(json.dumps(summary.to_dict(), indent=2))
    log.info("pretrain: reusing %s", p.reuse)
    return summary


def render_corpus(p: PretrainConfig, work: Path, map_fn=None, progress=None) -> list[str]:
    """Render every world of the corpus (the validation world last); returns their folders."""
    specs = world_specs(p)
    items = [(spec, str(work / "worlds" / spec["name"])) for spec in specs]
    if map_fn is not None:
        return map_fn(render_world, items, description="pretraining worlds")
    return [render_world(x) for x in _track(progress, items, "pretraining worlds")]


def corpus_crops(
    p: PretrainConfig, dirs: list[str], crop_size: int, progress=None
) -> tuple[CropSet, CropSet]:
    """The training worlds' crops (one CropSet) and the validation world's."""
    sets = [
        crops_from_synth_scene(d, crop_size=crop_size)
        for d in _track(progress, dirs, "synthetic crops")
    ]
    crops = concat_crop_sets(sets[:-1], [Path(d).name for d in dirs[:-1]])
    log.info(
        "pretraining corpus: %d worlds, %d crops (%d groups); validation world: %d crops",
        p.worlds,
        len(crops),
        len(crops.groups(min_views=1)),
        len(sets[-1]),
    )
    return crops, sets[-1]


def corpus_summary(specs: list[dict], crops: CropSet, val: CropSet) -> CorpusSummary:
    """The summary's `corpus` entry: the worlds trained on, the validation world, crop counts."""
    return CorpusSummary(
        worlds=[s["name"] for s in specs[:-1]],
        validation_world=specs[-1]["name"],
        train_crops=len(crops),
        validation_crops=len(val),
    )


def pretrain_images(
    p: PretrainConfig,
    work: Path,
    checkpoint: Path,
    reports: Path,
    *,
    map_fn=None,
    progress=None,
) -> ImagePretrainSummary:
    """Modes `3d` / `pretrain` (the image-only network; mode `lift` is `gst.lift.recipe`):
    render the corpus into `work/worlds` (finished worlds are kept: a rerun resumes), train,
    write the kept model to `checkpoint` and the logs and summary to `reports`; returns the
    summary (MPJPE before/after on the unseen validation world, corpus sizes). `map_fn` fans
    the world renders out (an executor's map); `progress` wraps loops with a progress bar."""
    if p.mode not in ("3d", "pretrain"):
        raise ValueError(f"pretrain_images trains modes 3d / pretrain, not '{p.mode}'")
    if p.threads:
        torch.set_num_threads(p.threads)
    specs = world_specs(p)
    dirs = render_corpus(p, work, map_fn, progress)
    crops, val = corpus_crops(p, dirs, p.crop_size, progress)
    body = load_body_model(p.body_model)
    cfg = get_preset(p.preset)
    net, ids, groups = build_network(cfg, body)
    lpips = load_lpips() if p.losses.lpips > 0 and p.mode == "pretrain" else None
    task = make_task(body, ids, cfg, crops.crop_size, p.losses, lpips)
    train_cfg = TrainConfig.for_stage(p.steps, p.batch_size, p.lr, p.device, p.amp, validations=10)

    def fit(
        task, train_cfg: TrainConfig, run_dir: Path, options: FitOptions, after_from: str
    ) -> FitSummary:
        """One fit_gst run on the corpus (pose validation on the unseen world); its `after`
        scores the model the recipe keeps from it (`after_from`)."""
        run_dir.mkdir(parents=True, exist_ok=True)
        return fit_gst(
            net,
            task,
            crops,
            train_cfg,
            run_dir,
            options,
            body_spec=p.body_model,
            vertex_ids=ids,
            group_index=groups,
            progress=progress,
            val_crops=val,
            after_from=after_from,
        )

    out = work / "models" / "pretrain_run"
    first = fit(
        task,
        train_cfg,
        out,
        FitOptions(
            mode=p.mode,
            num_targets=p.num_targets,
            render_size=p.render_size,
            augment=CropJitter() if p.augment else None,
            val_pose_crops=256,
        ),
        after_from="best",
    )
    # best.pt: the lowest MPJPE on the unseen world (early stopping against memorising the
    # corpus); the trainer always writes it (the last model when nothing was validated)
    kept = out / "best.pt"
    reports.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(out / "log.csv", reports / "log.csv")
    gaussians = None
    if p.mode == "3d" and p.gaussian_steps > 0:
        net.load_state_dict(load_checkpoint(kept).model)
        task = make_task(
            body, ids, cfg, crops.crop_size, p.losses, load_lpips() if p.losses.lpips > 0 else None
        )
        gauss_out = work / "models" / "pretrain_gaussians"
        gcfg = TrainConfig(
            steps=p.gaussian_steps,
            batch_size=p.batch_size,
            lr=p.gaussian_lr,
            warmup_steps=min(20, p.gaussian_steps // 10),
            val_every=p.gaussian_steps,
            ckpt_every=25,
            log_every=5,
            device=p.device,
            amp=p.amp,
        )
        gaussians = fit(
            task,
            gcfg,
            gauss_out,
            FitOptions(
                mode="pretrain",
                num_targets=p.num_targets,
                render_size=p.render_size,
                val_pose_crops=256,
            ),
            after_from="last",
        )
        # the 3D terms keep the pose; the head keeps learning to the end
        kept = gauss_out / "last.pt"
        shutil.copyfile(gauss_out / "log.csv", reports / "log_gaussians.csv")
    keep_model(kept, checkpoint)
    summary = ImagePretrainSummary(first, corpus_summary(specs, crops, val), gaussians)
    (reports / "summary.json").write_text(json.dumps(summary.to_dict(), indent=2, default=float))
    log.info(
        "pretrain: MPJPE on the unseen validation world %.1f -> %.1f mm (the kept model)",
        summary.fit.before.get("mpjpe_mm", float("nan")),
        summary.kept.after.get("mpjpe_mm", float("nan")),
    )
    shutil.rmtree(out)
    shutil.rmtree(work / "models" / "pretrain_gaussians", ignore_errors=True)
    shutil.rmtree(work / "worlds")
    return summary

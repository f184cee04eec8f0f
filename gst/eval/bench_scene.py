"""Run time against error for model variants, in one run, on a scene's crops with truth.

Sweeps backbone preset, input size and Gaussian count; every variant is trained with the same
short budget on the training split (earlier frames, training cameras), timed pose-only and full
(median of repeats), and scored on the test split (later frames; PSNR in held-out cameras).
The pretrained checkpoint is benchmarked as it is, for reference. Writes `reports/bench/`
(table.md, table.csv, pareto.png; docs/evaluate.md).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    model_validator,
)

from gst.body import load_body_model
from gst.eval.bench import Variant, run_bench, write_bench_table, write_pareto_plot
from gst.eval.split import FinetuneConfig, check_unseen, frame_split
from gst.metrics.image import SSIM_WINDOW
from gst.model.checkpoint import load_checkpoint, network_from_checkpoint
from gst.train.keypoints import store_landmarks
from gst.train.losses import LossWeights
from gst.train.scene_truth import attach_scene_truth
from gst.train.views import load_cropset

log = logging.getLogger("gst.eval")


class VariantParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    preset: Literal["tiny", "small", "base", "huge"] = "tiny"
    image_size: tuple[int, int] | None = None
    vertex_preset: Literal["1723", "3445", "6890", "full"] | None = None
    # landmark tokens: 0 = the paper's image-only network, 33 or 12 BlazePose landmarks
    landmarks: Literal[0, 12, 33] = 0
    landmark_point_tokens: bool = False  # a token per landmark besides the lift tokens
    # rounds of reprojection feedback after the SMPL head (gst.model.refine; needs landmarks)
    landmark_refine: NonNegativeInt = 0

    @model_validator(mode="after")
    def _landmark_options_need_landmarks(self):
        # without landmarks the network has neither: the row was the base network again,
        # trained, timed and plotted as if it differed
        if not self.landmarks and (self.landmark_refine or self.landmark_point_tokens):
            raise ValueError(
                f"variant {self.name!r}: landmark_refine and landmark_point_tokens need "
                "landmarks (12 or 33)"
            )
        return self


_DEFAULT_VARIANTS = [
    VariantParams(name="tiny-128x96-1723"),
    VariantParams(name="tiny-128x96-1723-lm33", landmarks=33),
    VariantParams(name="tiny-128x96-1723-lm33-points", landmarks=33, landmark_point_tokens=True),
    VariantParams(name="tiny-128x96-1723-lm33-refine2", landmarks=33, landmark_refine=2),
    VariantParams(name="tiny-128x96-1723-lm12", landmarks=12),
    VariantParams(name="tiny-256x192-1723", image_size=(256, 192)),
    VariantParams(name="tiny-128x96-6890", vertex_preset="6890"),
    VariantParams(name="small-128x96-3445", preset="small", image_size=(128, 96)),
]  # small at 256x192 (the preset's own size) and base train too slowly for the 20-minute CPU budget


class BenchSettings(BaseModel):
    """Settings of the run-time-against-error sweep (the `bench` stage's parameters)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    variants: list[VariantParams] = _DEFAULT_VARIANTS  # the rows (docs/evaluate.md)
    include_pretrained: bool = True  # also time and score models/pretrain.pt as it is
    include_trained: bool = True  # and models/gst.pt (the train stage's model) when it exists
    landmarks: bool = True  # feed crops' landmarks to landmark variants (store's, else BlazePose)
    steps: PositiveInt = 40  # equal training budget of every variant
    batch_size: PositiveInt = 8  # training crops per step
    lr: PositiveFloat = 5e-4  # training learning rate
    mode: Literal["pretrain", "3d"] = (
        "pretrain"  # 3D supervision + image terms (Gaussians learn too)
    )
    test_fraction: float = Field(0.25, gt=0, lt=1)  # last share of the frames, held out
    # default: the trained model's (train's setting), else the rig's last camera
    heldout_cameras: list[str] | None = None
    repeats: PositiveInt = 5  # timed runs per row (the median is reported)
    timing_batch: PositiveInt = 8  # crops per timed call (ms per crop)
    render_size: int = Field(64, ge=SSIM_WINDOW)  # side (px) of the renders (SSIM's window)
    max_groups: PositiveInt | None = 16  # cap on test (frame, person) groups (None: all)
    threads: PositiveInt | None = None  # torch CPU threads (default: torch's choice)


def _check_training_samples(crops, split, mode: str) -> None:
    """Refuse a split that leaves no training sample, before the landmarks are read and the
    first variant is built (fit_gst then failed naming no held-out camera: the split's rows
    were already taken out); `pretrain` samples need a (frame, person) seen by >= 2 training
    cameras."""
    need = 2 if mode == "pretrain" else 1
    train = torch.zeros(len(crops), dtype=torch.bool)
    train[split.train_rows] = True
    if not any(int(train[g].sum()) >= need for g in crops.groups(min_views=need)):
        raise ValueError(
            f"bench: no training sample: no (frame, person) with truth seen by >= {need} "
            f"training camera(s) in frames < {split.test_frames[0]} (cameras "
            f"{crops.camera_names}, held out {list(split.heldout_cameras)}); hold out fewer "
            "cameras (bench.heldout_cameras)"
            + (" or use mode 3d (single views)" if need > 1 else "")
        )


def bench_scene(
    p: BenchSettings,
    crops_h5: Path,
    synth: Path,
    pretrained: Path,
    out: Path,
    *,
    scene: str = "scene",
    workspace: Path | None = None,
) -> list:
    """Train every variant with the same budget, time and score it, and write `out`
    (table.md, table.csv, pareto.png); returns the table rows. `pretrained` (a GST
    checkpoint) is benchmarked as it is when `include_pretrained`."""
    root = workspace if workspace is not None else pretrained.parent.parent
    if p.threads:
        torch.set_num_threads(p.threads)
    t0 = time.perf_counter()
    crops, boxes = load_cropset(crops_h5)
    attach_scene_truth(crops, boxes, synth)
    trained = root / "models" / "gst.pt"
    trained_extra = (
        load_checkpoint(trained).extra if p.include_trained and trained.is_file() else {}
    )
    # default: the cameras the scene's model was held out from (train's own setting), so that it
    # can be scored beside the variants; else the rig's last camera
    heldout = tuple(
        p.heldout_cameras
        if p.heldout_cameras is not None
        else (trained_extra or {}).get("heldout_cameras") or crops.camera_names[-1:]
    )
    split = frame_split(crops, heldout, p.test_fraction)
    _check_training_samples(crops, split, p.mode)
    if p.landmarks:
        # Landmarks the extraction projected from the rig's skeleton hold every camera's
        # evidence, the held-out one included: every such row is read again by the landmark
        # model, training rows too (as train does), not only the scored ones.
        crops.landmarks, source = store_landmarks(
            crops_h5, crops.images, reread=np.ones(len(crops), bool)
        )
        log.info("bench: landmarks from %s", source)
    ckpt = load_checkpoint(pretrained)
    body_spec = ckpt.body_model
    body = load_body_model(body_spec)
    variants = []
    kept = [("pretrained", "models/pretrain.pt")] if p.include_pretrained else []
    if p.include_trained and trained.is_file():
        try:  # the scene's trained model: scored only on a split it never saw
            check_unseen(trained_extra, split.heldout_cameras, split.test_frames[0], trained)
            kept.append(("trained (models/gst.pt)", "models/gst.pt"))
        except ValueError as exc:
            log.warning(
                "bench: the trained model is left out of the table: %s (bench's split: "
                "heldout_cameras %s, test_fraction %s; set bench.include_trained=false to "
                "silence this)",
                str(exc).split(". Score it")[0],
                list(split.heldout_cameras),
                p.test_fraction,
            )
    for name, rel in kept:
        model = load_checkpoint(root / rel)
        cfg = network_from_checkpoint(model, root / rel).cfg
        variants.append(
            Variant(
                name=name,
                preset=cfg.name,
                image_size=cfg.image_size,
                checkpoint=rel,
                landmarks=cfg.num_landmarks if cfg.landmark_tokens else 0,
            )
        )
    variants += [
        Variant(
            v.name, v.preset, v.image_size, v.vertex_preset,
            landmarks=v.landmarks, landmark_point_tokens=v.landmark_point_tokens,
            landmark_refine=v.landmark_refine,
        )
        for v in p.variants
    ]  # fmt: skip

    def load(rel: str):
        c = load_checkpoint(root / rel)
        return network_from_checkpoint(c, root / rel), c.vertex_ids.numpy(), c.group_index.numpy()

    # LPIPS is left out of the short runs (equal for every variant) to keep the sweep on budget.
    train = FinetuneConfig(
        mode=p.mode,
        steps=p.steps,
        batch_size=p.batch_size,
        lr=p.lr,
        num_targets=3,
        render_size=p.render_size,
        weights=LossWeights(lpips=0.0),
    )
    log.info(
        "bench: %d variants, %d training rows, test frames %s, held out %s",
        len(variants),
        len(split.train_rows),
        split.test_frames,
        heldout,
    )
    rows = run_bench(
        variants,
        crops,
        split,
        body,
        body_spec,
        train,
        repeats=p.repeats,
        batch=p.timing_batch,
        render_size=p.render_size,
        max_groups=p.max_groups,
        log=log.info,
        load_checkpoint_fn=load,
    )
    out.mkdir(parents=True, exist_ok=True)
    seconds = time.perf_counter() - t0
    # the rows taken as they are, and only those, are named as such
    as_is = {
        "pretrained": "`pretrained` is models/pretrain.pt as it is (longer training, other "
        "synthetic worlds).",
        "trained (models/gst.pt)": "`trained (models/gst.pt)` is the train stage's model as it "
        "is (it trained on this scene's first frames without labels).",
    }
    names = " and ".join(f"`{n}`" for n, _ in kept)
    as_is_rows = f" except {names} (taken as they are)" if kept else ""
    header = (
        f"# Run time against error (scene `{scene}`)\n\n"
        f"CPU, {torch.get_num_threads()} threads; time = median of {p.repeats} runs of one "
        f"batch of {p.timing_batch} real crops after a warm-up, all variants timed round-robin "
        "(pose-only: Gaussian tokens skipped; full: network plus posed Gaussians, no rendering). "
        f"Every variant{as_is_rows} was trained from scratch with the same budget: "
        f"{p.steps} steps of batch {p.batch_size}, mode `{p.mode}` (3D truth + image terms, no "
        f"LPIPS) on {len(split.train_rows)} crops of frames < {split.test_frames[0]} in cameras "
        f"other than {', '.join(heldout)}. MPJPE/PA-MPJPE on crops of frames "
        f"{split.test_frames[0]}-{split.test_frames[1] - 1} (all cameras); PSNR of those frames "
        f"rendered at {p.render_size} px into the held-out camera(s). "
        + "".join(f"{as_is[name]} " for name, _ in kept)
        + "Landmark variants take each crop's BlazePose landmarks "
        f"({'the store' if p.landmarks else 'none'}); their time is the network's alone (BlazePose "
        f"runs anyway in tracking). Whole sweep: {seconds:.0f} s."
    )
    write_bench_table(out, rows, header)
    write_pareto_plot(out / "pareto.png", rows)
    log.info("bench: %d rows in %.0f s -> reports/bench/table.md", len(rows), seconds)
    return rows

"""Render-free pretraining of GST's landmark -> body path, and its evaluation on detected crops.

The network runs in its landmark-only mode (no image tokens): simulated BlazePose detections
of sampled bodies (`gst.lift.sampler`) go in, SMPL pose, shape and the crop camera come out, and
the same supervised terms as the rendered pretraining (`gst.train.losses.supervised_terms`: 3D
joints root-relative in the camera, the root, 2D reprojection in the crop, rotation matrices and
betas) pull them to the sampled truth. No image is rendered, so a step costs milliseconds and
every step sees fresh bodies, cameras and detection errors.

Trained here: the landmark encoder and the SMPL head's decoder (its landmark cross-attention,
self-attention and feed-forward layers) and linear decoders. The image path (ViT, the image
cross-attention) gets no gradient; the Gaussian head is left to a short rendered phase
(`gst.train`), which this module does not run.

`evaluate_world(net, body, world)` scores the single-image prediction from real BlazePose
detections of rendered crops (`gst.lift.dataset.LandmarkWorld`) against the truth, as
`gst.train.evaluation.pose_metrics` does: world joints, MPJPE root-aligned at the pelvis and
PA-MPJPE, in millimetres.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from gst.body import BodyModel
from gst.cores import available_cores, torch_threads
from gst.lift.dataset import LandmarkWorld, named_worlds
from gst.lift.errors import LANDMARK_SETS, LIMBS
from gst.lift.noise import set_landmarks
from gst.lift.sampler import LiftBatch, LiftSampler
from gst.metrics.pose import mpjpe, pa_mpjpe
from gst.model.assemble import camera_translation, to_world
from gst.model.landmarks import LandmarkInput, camera_up, hide_up
from gst.model.network import GSTNetwork
from gst.model.refine import DEFAULT_ROUNDS
from gst.prefetch import background
from gst.train.losses import LossWeights, combine, supervised_terms
from gst.train.steps import project
from gst.train.trainer import adamw, warmup_cosine


@dataclass(frozen=True)
class LiftPretrainConfig:
    steps: int = 4000
    batch_size: int = 64
    lr: float = 1e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 100
    grad_clip: float = 1.0
    crop_size: int = 256
    seed: int = 0
    val_every: int = 500
    # batches sampled this many steps ahead in a background thread (0: in the loop); the
    # sampler's generator runs in order either way, so the batches are the same
    prefetch: int = 2
    # the sampled bodies (gst.lift.sampler, docs/landmark_prior.md "Pose mix and flips"): the
    # share of joint-limited random poses in the bank, the share drawn uniformly within the
    # joint limits, and whether BlazePose's whole-body flips are simulated (no: a flipped
    # sample cannot be told from its landmarks, so it only teaches the network to hedge)
    random_share: float = 0.15
    uniform_p: float = 0.03
    whole_body_flips: bool = False
    # spread (deg, normal) of a whole-body lean about a random horizontal axis: the motion
    # library's people stand straighter (pelvis-neck tilt median 2.6-6.8 deg) than real ones
    # (the lab's fused bodies: 12.1, p90 26.8); docs/landmark_prior.md "Lean"
    lean_deg: float = 12.0
    # factor on the simulated detections' scatter and gross-error rates (gst.lift.noise): the
    # model was measured on our renders; on real people BlazePose errs about half as much
    # (docs/landmark_prior.md "Noise level"), and a lifter taught the renders' noise trusts
    # real landmarks too little
    noise_scale: float = 0.5
    # limb mixing (gst.lift.sampler, docs/landmark_prior.md "Limb mixing"): the chance that an
    # arm (a leg) of a sampled pose takes another pose's angles, for limb combinations the
    # library never authored (the lab's single-image bodies follow their landmarks more closely)
    arm_mix_p: float = 0.3
    leg_mix_p: float = 0.0
    # torch threads of the training loop; None: with `prefetch` the sampler runs beside it in a
    # background thread, so the loop takes the cores that leaves (without: left as they are)
    threads: int | None = None
    weights: LossWeights = field(
        default_factory=lambda: LossWeights(joints3d=1.0, joints2d=1.0, root=0.2, params=0.5)
    )

    def __post_init__(self):
        # steps 0 ended in an UnboundLocalError after the loop, val_every 0 in a modulo by zero
        # at the first step, batch_size 0 in "body_pose has an empty batch" from the body model
        for name in ("steps", "batch_size", "val_every", "crop_size"):
            v = getattr(self, name)
            if not v >= 1:
                raise ValueError(f"LiftPretrainConfig.{name} must be >= 1, got {v}")
        if not self.warmup_steps >= 0:
            raise ValueError(
                f"LiftPretrainConfig.warmup_steps must be >= 0, got {self.warmup_steps}"
            )

    def sampler(self, body: BodyModel, landmark_set: str, crop_size: int | None = None):
        """The recipe's sampler: the bodies, leans and detection noise the pretraining draws and
        the rehearsal of scene training (gst.lift.rehearsal) draws again; `crop_size` defaults
        to the recipe's."""
        return LiftSampler(
            body,
            crop_size=self.crop_size if crop_size is None else crop_size,
            seed=self.seed,
            landmark_set=landmark_set,
            random_share=self.random_share,
            uniform_p=self.uniform_p,
            whole_body_flips=self.whole_body_flips,
            lean_deg=self.lean_deg,
            noise_scale=self.noise_scale,
            arm_mix_p=self.arm_mix_p,
            leg_mix_p=self.leg_mix_p,
        )


@dataclass
class PoseScore:
    mpjpe_mm: float
    pa_mpjpe_mm: float
    crops: int
    # the predicted limb joints, projected, against the detected limb landmarks (`limb_agreement`)
    limb_landmarks_pct: float | None = None


@dataclass
class LiftPretrainResult:
    steps: int
    seconds: float
    samples_per_s: float  # training throughput: sampling + forward + backward
    sampler_samples_per_s: float  # the sampler alone
    last_loss: float
    train_mpjpe_mm: float  # root-relative, camera frame, on the last batches (simulated)
    validation: list[dict] = field(default_factory=list)  # {step, name, mpjpe_mm, pa_mpjpe_mm}


def body_joints(
    net_out, body: BodyModel, K: torch.Tensor, crop_size: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """(joints in the crop's camera (B, 24, 3), their 2D projection (B, 24, 2)) of an output;
    only the joints are posed (one vertex is requested, the joints come from the full mesh)."""
    transl = camera_translation(net_out.cam, K, crop_size)
    one = torch.zeros(1, dtype=torch.long)
    out = body(net_out.betas, net_out.rotmats[:, 1:], net_out.rotmats[:, 0], transl, vertex_ids=one)
    return out.joints, project(out.joints, K)


def simulated_up(b: LiftBatch) -> torch.Tensor:
    """The sampled world's up (+z) in each sample's camera, hidden (zero) for every
    `UNCALIBRATED_EVERY`-th sample (gst.model.landmarks.hide_up)."""
    return hide_up(camera_up(b.R))


def lift_terms(net, body: BodyModel, b: LiftBatch, weights: LossWeights):
    """(the weighted supervised terms, the root-relative joint error in mm) of one simulated
    batch through `net`'s landmark-only mode (no image tokens)."""
    inp = LandmarkInput.from_pixels(b.landmarks, b.K, b.crop_size, up=simulated_up(b))
    out = net(None, with_gaussians=False, landmarks=inp)
    joints, joints2d = body_joints(out, body, b.K, b.crop_size)
    parts = supervised_terms(
        joints, joints2d, out.rotmats, out.betas, b.joints_cam, b.joints2d, b.rotmats_cam,
        b.betas[:, : out.betas.shape[1]], b.crop_size, b.visible.float(),
    )  # fmt: skip
    with torch.no_grad():
        error_mm = 1000 * mpjpe(joints, b.joints_cam, root=0).mean()
    return combine(parts, weights), error_mm


def trainable_parameters(net: GSTNetwork) -> list[torch.nn.Parameter]:
    """The landmark path: the landmark encoder, the SMPL head without its image
    cross-attention (never used in the landmark-only mode), and the reprojection refiner."""
    skip = {
        id(p)
        for layer in net.smpl_head.transformer.transformer.layers
        for p in layer[1].parameters()
    }
    params = list(net.landmark_encoder.parameters()) + [
        p for p in net.smpl_head.parameters() if id(p) not in skip
    ]
    if net.refiner is not None:
        params += list(net.refiner.parameters())
    return [p for p in params if p.requires_grad]


def pretrain_landmark_path(
    net: GSTNetwork,
    body: BodyModel,
    cfg: LiftPretrainConfig = LiftPretrainConfig(),
    sampler: LiftSampler | None = None,
    validation: dict[str, LandmarkWorld] | None = None,
    log=print,
) -> LiftPretrainResult:
    """Train `net`'s landmark path in place on simulated detections; returns what it measured.
    The loop runs on `cfg.threads` torch threads (None: the cores the background sampler
    leaves, when it prefetches) and puts the caller's back."""
    threads = cfg.threads
    if threads is None and cfg.prefetch > 0:
        threads = max(1, available_cores() - 1)
    with torch_threads(threads):
        return _pretrain(net, body, cfg, sampler, validation, log)


def _pretrain(net, body, cfg, sampler, validation, log) -> LiftPretrainResult:
    if net.landmark_encoder is None:
        raise ValueError("pretrain_landmark_path needs a network built with landmark_tokens")
    torch.manual_seed(cfg.seed)
    sampler = sampler or cfg.sampler(body, landmark_set_of(net).name)
    if len(sampler.lset) != net.cfg.num_landmarks:
        raise ValueError(
            f"the sampler simulates {len(sampler.lset)} landmarks, the network takes "
            f"{net.cfg.num_landmarks}"
        )
    params = trainable_parameters(net)
    opt = adamw(params, cfg.lr, cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: warmup_cosine(s, cfg.steps, cfg.warmup_steps)
    )
    result = LiftPretrainResult(0, 0.0, 0.0, 0.0, float("nan"), float("nan"))
    t0, recent = time.perf_counter(), []
    sample_seconds = [0.0]

    def draw():
        for _ in range(cfg.steps):
            ts = time.perf_counter()
            b = sampler.sample(cfg.batch_size)
            sample_seconds[0] += time.perf_counter() - ts
            yield b

    batches = background(draw(), cfg.prefetch, "lift-sampler") if cfg.prefetch > 0 else draw()
    net.train()
    for step, b in enumerate(batches):
        terms, error_mm = lift_terms(net, body, b, cfg.weights)
        opt.zero_grad(set_to_none=True)
        terms.total.backward()
        torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
        opt.step()
        sched.step()
        recent.append(float(error_mm))
        recent = recent[-50:]
        last = step + 1 == cfg.steps
        if validation and ((step + 1) % cfg.val_every == 0 or last):
            for name, world in validation.items():
                s = evaluate_world(net, body, world)
                result.validation.append(
                    {
                        "step": step + 1,
                        "name": name,
                        "mpjpe_mm": s.mpjpe_mm,
                        "pa_mpjpe_mm": s.pa_mpjpe_mm,
                    }
                )
                log(
                    f"step {step + 1}: {name} MPJPE {s.mpjpe_mm:.1f} mm, PA {s.pa_mpjpe_mm:.1f} mm "
                    f"(train batches {np.mean(recent):.1f} mm, {time.perf_counter() - t0:.0f} s)"
                )
            net.train()
        elif (step + 1) % 100 == 0:
            log(
                f"step {step + 1}: loss {float(terms.total.detach()):.4f}, "
                f"train {np.mean(recent):.1f} mm"
            )
    seconds = time.perf_counter() - t0
    result.steps = cfg.steps
    result.seconds = seconds
    result.samples_per_s = cfg.steps * cfg.batch_size / seconds
    result.sampler_samples_per_s = cfg.steps * cfg.batch_size / max(sample_seconds[0], 1e-9)
    result.last_loss = float(terms.total.detach())
    result.train_mpjpe_mm = float(np.mean(recent))
    net.eval()
    return result


@torch.no_grad()
def predict_world_joints(
    net: GSTNetwork,
    body: BodyModel,
    landmarks: torch.Tensor,
    K: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    crop_size: int,
    images: torch.Tensor | None = None,
    batch: int = 256,
) -> torch.Tensor:
    """World joints (N, 24, 3) predicted from limb landmarks (N, 12, 3) crop px + confidence
    (and ImageNet-normalised network images, when given)."""
    net.eval()
    out = []
    for i in range(0, len(landmarks), batch):
        sl = slice(i, i + batch)
        inp = LandmarkInput.from_pixels(landmarks[sl], K[sl], crop_size, up=camera_up(R[sl]))
        o = net(None if images is None else images[sl], with_gaussians=False, landmarks=inp)
        joints, _ = body_joints(o, body, K[sl], crop_size)
        out.append(to_world(joints, R[sl], t[sl]))
    return torch.cat(out)


def score(pred_world: torch.Tensor, gt_world: torch.Tensor) -> PoseScore:
    """MPJPE root-aligned at the pelvis and PA-MPJPE over the 24 joints, millimetres."""
    return PoseScore(
        1000 * float(mpjpe(pred_world, gt_world, root=0).mean()),
        1000 * float(pa_mpjpe(pred_world, gt_world).mean()),
        int(len(gt_world)),
    )


def limb_agreement(
    joints2d: np.ndarray, landmarks: np.ndarray, crop_size: int, min_confidence: float = 0.5
) -> float | None:
    """Median distance, in % of the crop, from the body's limb joints projected into the crop
    (N, 24, 2) to BlazePose's limb landmarks (N, 33, 3: u, v, confidence) at least
    `min_confidence` sure, after shifting each crop's joints by their mean offset (`track`
    shifts a body onto its landmarks too, with a robust fit over 13 joints, gst.track.align):
    close to, not the same as, the agreement track's summary reports on video
    (gst.track.agreement, which the training library does not import). None when no landmark
    is sure enough."""
    lm = np.asarray(landmarks, np.float64)[:, list(LIMBS.ids)]
    pred = np.asarray(joints2d, np.float64)[:, list(LIMBS.joints)]
    ok = np.isfinite(lm).all(-1) & (lm[..., 2] >= min_confidence)
    if not ok.any():
        return None
    diff = np.where(ok[..., None], lm[..., :2] - pred, 0.0)
    shift = diff.sum(1) / np.maximum(ok.sum(1), 1)[:, None]
    dist = np.linalg.norm(diff - shift[:, None], axis=-1)[ok]
    return float(100 * np.median(dist) / crop_size)


def landmark_set_of(net: GSTNetwork):
    """The landmark set a network takes (by its number of landmarks)."""
    for lset in LANDMARK_SETS.values():
        if len(lset) == net.cfg.num_landmarks:
            return lset
    raise ValueError(f"no landmark set has {net.cfg.num_landmarks} landmarks")


def evaluate_world(net: GSTNetwork, body: BodyModel, world: LandmarkWorld) -> PoseScore:
    """Single-image pose from the world's real BlazePose detections, landmark path only: 3D
    against the truth, and 2D against the detections (`limb_agreement`)."""
    f32 = torch.float32
    lset = landmark_set_of(net)
    lm = torch.as_tensor(set_landmarks(world.landmarks, world.presence, lset), dtype=f32)
    K = torch.as_tensor(world.K_crop, dtype=f32)
    R, t = torch.as_tensor(world.R, dtype=f32), torch.as_tensor(world.t, dtype=f32)
    pred = predict_world_joints(net, body, lm, K, R, t, world.crop_size)
    result = score(pred.double(), torch.as_tensor(world.joints_world, dtype=torch.float64))
    joints2d = project(pred @ R.transpose(1, 2) + t[:, None], K).numpy()
    # confidence as the network reads it (`set_landmarks`): visibility x the person's presence,
    # so that a crop where the model found nobody does not count
    sure = np.array(world.landmarks, np.float64)
    sure[..., 2] *= np.asarray(world.presence, np.float64)[:, None]
    result.limb_landmarks_pct = limb_agreement(joints2d, sure, world.crop_size)
    return result


def main(argv: list[str] | None = None) -> None:
    """Pretrain the landmark path of a tiny GST and score it on landmark worlds:

    python -m gst.lift.pretrain --out lift.pt --steps 3000 --val held=world_7000.npz
    """
    import argparse
    import json

    from gst.body import load_body_model
    from gst.model.checkpoint import save_checkpoint
    from gst.model.presets import PRESETS, get_preset
    from gst.train.recipe import build_network

    ap = argparse.ArgumentParser(description="render-free pretraining of the landmark path")
    ap.add_argument("--out", type=Path, required=True, help="checkpoint to write")
    ap.add_argument("--preset", default="tiny", choices=sorted(PRESETS))
    ap.add_argument("--steps", type=int, default=LiftPretrainConfig.steps)
    ap.add_argument("--batch-size", type=int, default=LiftPretrainConfig.batch_size)
    ap.add_argument("--lr", type=float, default=LiftPretrainConfig.lr)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--val", action="append", default=[], help="NAME=world.npz (repeatable)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: cores - 1)")
    ap.add_argument("--landmarks", default="limbs", choices=sorted(LANDMARK_SETS))
    ap.add_argument("--no-point-tokens", action="store_true", help="lift tokens only")
    ap.add_argument(
        "--refine",
        type=int,
        default=DEFAULT_ROUNDS,
        help=f"rounds of reprojection feedback (gst.model.refine; {DEFAULT_ROUNDS}; 0: none)",
    )
    args = ap.parse_args(argv)
    val = named_worlds(args.val)
    body = load_body_model("anny")
    n = len(LANDMARK_SETS[args.landmarks])
    cfg_net = get_preset(
        args.preset,
        landmark_tokens=True,
        num_landmarks=n,
        landmark_point_tokens=not args.no_point_tokens,
        landmark_gravity=True,
        landmark_refine=args.refine,
    )
    net, ids, groups = build_network(cfg_net, body, args.seed)
    cfg = LiftPretrainConfig(
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        seed=args.seed,
        val_every=max(1, args.steps // 6),
        threads=args.threads,
    )
    res = pretrain_landmark_path(net, body, cfg, validation=val)
    save_checkpoint(args.out, net, "anny", ids, groups, {"lift_pretrain": asdict(res)})
    print(json.dumps(asdict(res), indent=1))


if __name__ == "__main__":
    main()

"""Can a flip check learnt on many rendered worlds see BlazePose's left/right flips elsewhere?

The per-scene check (commit 36c90ee, reverted; benchmarks/bench_mirror_check.py) learnt
camera-specific looks from a scene's two people. This one learns from many: it renders
`--worlds` pretraining-style worlds (random people, rigs and motions; the pretrain stage's
`world_specs` with other seeds), runs BlazePose on every person crop as the pipeline does, puts
each crop's landmarks right against the truth (`gst.metrics.flips.landmark_sides`) and trains
the check on them (the same crop flipped horizontally is a second example). The check: frozen
ImageNet features (LPIPS's AlexNet, first three layers, at 128 px, 15 x 15 cells) sampled at
each landmark, and a small head whose score f(reading) - f(reading with left and right
exchanged) is antisymmetric; early stopping on a held-out world.

Then, with nothing of theirs seen, it scores the demo's crops (against the truth) and the lab
capture's (against the fused bodies) as BlazePose read them: AUC, and at the decision rule
(posterior log-odds above 0 with the training worlds' flip rate as prior) the flips found and
the unmirrored crops it would wrongly exchange, per camera.

    python benchmarks/bench_flip_check_worlds.py --demo WS/demo --lab WS/lab [--worlds 10]

(WS/lab needs `python -m pipeline run fuse --scene lab`.)

2026-11-28, `--worlds 16 --steps 1500` (3998 crops, 330 of the 3200 training crops mirrored;
rendering and BlazePose 439 s, training 98 s; validation world loss 0.343 at step 400,
temperature 1.30, prior 0.103), with the demo's and the lab's workspaces of that evening:
- demo (truth; 549 crops, 37 mirrored): AUC 0.844 (the per-scene check: 0.65-0.70); at the rule
  2 found, 4 unmirrored crops wrongly exchanged.
- lab (fused bodies; 796 crops, 58 mirrored): AUC 0.763; 1 found, 8 wrongly exchanged (4 in
  cam02, 4 in cam04).
More people and viewpoints help the ranking, but BlazePose's flips are the side views where
facing is hardest to see, and 3200 rendered crops do not teach low-level ImageNet features to
see it with the confidence a swap needs (a wrong swap costs what a right one saves). Not in the
pipeline.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn as nn  # noqa: E402
import torch.nn.functional as F  # noqa: E402

from benchmarks.cli import bench_parser  # noqa: E402
from benchmarks.flip_data import labelled_scene_crops  # noqa: E402
from gst.body.markers import BLAZEPOSE_MIRROR  # noqa: E402
from gst.lift.recipe import attach_landmarks  # noqa: E402
from gst.metrics.flips import landmark_sides, reference_in_crops, unmirror  # noqa: E402
from gst.metrics.lpips import load_lpips  # noqa: E402
from gst.train.pretrain import PretrainConfig, render_world, world_specs  # noqa: E402
from gst.train.synthetic_crops import crops_from_synth_scene  # noqa: E402

GRID, FEATURE_INPUT = 15, 128
MIRROR = list(BLAZEPOSE_MIRROR)
DECIDING = (11, 12, 23, 24)


class Features(nn.Module):
    """LPIPS's AlexNet, frozen, read at its second and third layers: (N, S, S, 3) uint8 ->
    (N, 576, 15, 15), the third upsampled to the second's cells."""

    def __init__(self):
        super().__init__()
        self.lpips = load_lpips()  # its input scaling and backbone, as the LPIPS distance uses

    @torch.no_grad()
    def forward(self, images) -> torch.Tensor:
        x = torch.as_tensor(images).permute(0, 3, 1, 2).float() / 255.0
        x = F.interpolate(x, size=(FEATURE_INPUT, FEATURE_INPUT), mode="area")
        x = (x * 2 - 1 - self.lpips.shift) / self.lpips.scale
        _, second, third, *_ = self.lpips.backbone(x)
        third = F.interpolate(third, size=second.shape[-2:], mode="bilinear", align_corners=False)
        return torch.cat([second, third], 1)


def sampled(features: torch.Tensor, landmarks, crop_size: int) -> torch.Tensor:
    """(N, 33, C + 1): features at each landmark (cell m is centred on pixel 8 m + 7 of the
    128 px input) times its confidence, and the confidence."""
    lm = torch.as_tensor(landmarks).float()
    cells = ((lm[..., :2] + 0.5) * FEATURE_INPUT / crop_size - 0.5 - 7.0) / 8.0
    grid = torch.nan_to_num(cells * (2.0 / (GRID - 1)) - 1.0, 0.0)
    read = F.grid_sample(features, grid[:, :, None], align_corners=True, padding_mode="border")
    conf = torch.nan_to_num(lm[..., 2], 0.0).clamp(0, 1)
    conf = torch.where(torch.isfinite(cells).all(-1), conf, torch.zeros_like(conf))
    return torch.cat([read[..., 0].transpose(1, 2) * conf[..., None], conf[..., None]], -1)


class Head(nn.Module):
    def __init__(self, channels: int, width: int = 32):
        super().__init__()
        self.norm = nn.LayerNorm(channels, elementwise_affine=False)
        self.reduce = nn.Sequential(nn.Dropout(0.2), nn.Linear(channels, width), nn.ReLU())
        self.decide = nn.Sequential(
            nn.Dropout(0.3), nn.Linear(33 * (width + 1), 64), nn.ReLU(), nn.Linear(64, 1)
        )

    def forward(self, x):
        conf = x[..., -1:]
        per = self.reduce(self.norm(x[..., :-1])) * conf
        return self.decide(torch.cat([per, conf], -1).flatten(1))[:, 0]

    def score(self, x):
        out = self(torch.cat([x, x[:, MIRROR]]))
        return out[: len(x)] - out[len(x) :]


def inputs(feat: Features, images, landmarks, batch: int = 64) -> torch.Tensor:
    s = images.shape[1]
    return torch.cat(
        [sampled(feat(images[i : i + batch]), landmarks[i : i + batch], s)
         for i in range(0, len(images), batch)]
    )  # fmt: skip


def hflip(images: torch.Tensor, landmarks: torch.Tensor):
    lm = landmarks.clone()
    lm[..., 0] = (images.shape[2] - 1) - lm[..., 0]
    return images.flip(2), lm[:, MIRROR]


def decidable(lm: np.ndarray) -> np.ndarray:
    p = lm[:, list(DECIDING)]
    return (np.isfinite(p).all(-1) & (np.nan_to_num(p[..., 2]) >= 0.5)).all(1)


def labelled_worlds(n: int, seed: int, work: Path):
    """Rendered worlds' crops, BlazePose landmarks and truth sides, and the world of each."""
    p = PretrainConfig(worlds=n, world_seed=seed, world_people=2, world_frames=20)
    imgs, lms, sides, world = [], [], [], []
    for k, spec in enumerate(world_specs(p)):
        d = render_world((spec, str(work / spec["name"])))
        crops = crops_from_synth_scene(d, crop_size=256)
        attach_landmarks(crops)
        ref = reference_in_crops(crops.truth["joints_world"], crops.R, crops.t, crops.K)
        s = landmark_sides(crops.landmarks.numpy(), ref)
        imgs.append(crops.images)
        lms.append(crops.landmarks.float())
        sides.append(s)
        world.append(np.full(len(s), k))
        print(f"  world {k}: {len(s)} crops, {int((s < 0).sum())} mirrored", flush=True)
    return torch.cat(imgs), torch.cat(lms), np.concatenate(sides), np.concatenate(world)


VALIDATE_EVERY = 50


def train(feat, imgs, lms, sides, world, steps: int, seed: int = 0):
    """(the head at its best validation loss, temperature, prior log-odds); the loss on the last
    world is taken every `VALIDATE_EVERY` steps and at the last step."""
    if steps < 1:
        raise ValueError(f"steps must be at least 1, got {steps}")
    torch.manual_seed(seed)
    rows = np.flatnonzero(sides != 0)
    val = world[rows] == world.max()  # the last world validates
    right = unmirror(lms[rows], sides[rows] < 0)
    tr = rows[~val]
    fi, fl = hflip(imgs[tr], right[~val])
    x_tr = torch.cat([inputs(feat, imgs[tr], right[~val]), inputs(feat, fi, fl)])
    x_val = inputs(feat, imgs[rows[val]], right[val])
    head = Head(x_tr.shape[-1] - 1)
    opt = torch.optim.AdamW(head.parameters(), 2e-3, weight_decay=1e-2)
    best, order = (float("inf"), 0, None), torch.zeros(0, dtype=torch.long)
    for step in range(1, steps + 1):
        if len(order) < 64:
            order = torch.randperm(len(x_tr))
        b, order = order[:64], order[64:]
        head.train()
        loss = F.softplus(head.score(x_tr[b])).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % VALIDATE_EVERY == 0 or step == steps:
            head.eval()
            with torch.no_grad():
                v = float(F.softplus(head.score(x_val)).mean())
            if v < best[0]:  # False for NaN: a non-finite loss is never the best
                best = (v, step, {k: t.clone() for k, t in head.state_dict().items()})
    if best[2] is None:
        raise SystemExit(
            f"the validation world's loss was never finite ({len(x_val)} crops with a side; "
            "no head to keep): check the last world's crops and the training (learning rate)"
        )
    head.load_state_dict(best[2])
    head.eval()
    with torch.no_grad():
        s_val = head.score(x_val).double().numpy()
    grid = np.geomspace(0.5, 16.0, 41)
    temp = float(grid[np.argmin([np.logaddexp(0, s_val / t).mean() for t in grid])])
    prior = ((sides < 0).sum() + 0.5) / ((sides != 0).sum() + 1.0)
    print(
        f"trained on {len(tr)} crops ({int((sides[tr] < 0).sum())} mirrored) x2 (flipped); "
        f"validation world {int(val.sum())} crops: loss {best[0]:.3f} at step {best[1]}; "
        f"temperature {temp:.2f}, prior {prior:.3f}"
    )
    return head, temp, float(np.log(prior / (1 - prior)))


def score_set(name, feat, head, temp, prior_lo, imgs, lms, sides, cams, cam_names):
    rows = np.flatnonzero(decidable(lms.numpy()) & (sides != 0))
    t0 = time.perf_counter()
    with torch.no_grad():
        lo = head.score(inputs(feat, imgs[rows], lms[rows])).double().numpy() / temp + prior_lo
    ms = 1000 * (time.perf_counter() - t0) / max(len(rows), 1)
    s = sides[rows]
    pos, neg = lo[s < 0], lo[s > 0]
    auc = (pos[:, None] > neg[None]).mean() if len(pos) and len(neg) else float("nan")
    called = lo > 0
    print(
        f"{name}: {len(rows)} crops with a reference, {len(pos)} mirrored; AUC {auc:.3f}; found "
        f"{int((called & (s < 0)).sum())} of {len(pos)}, false {int((called & (s > 0)).sum())} "
        f"of {len(neg)} ({ms:.1f} ms a crop)"
    )
    for c, cname in enumerate(cam_names):
        m = cams[rows] == c
        mir, own = s[m] < 0, s[m] > 0
        print(
            f"  {cname}: mirrored {int(mir.sum())}, found {int((called[m] & mir).sum())}, "
            f"false {int((called[m] & own).sum())} of {int(own.sum())}"
        )


def scene_set(ws: Path, reference: str):
    crops, lm, sides = labelled_scene_crops(ws, reference)
    return crops.images, lm, sides, crops.camera.numpy(), crops.camera_names


def main() -> None:
    ap = bench_parser(__doc__)
    ap.add_argument("--demo", type=Path, help="the demo's workspace folder (WS/demo)")
    ap.add_argument("--lab", type=Path, help="the lab's workspace folder (WS/lab), fused")
    ap.add_argument("--worlds", type=int, default=10, help="rendered worlds (the last validates)")
    ap.add_argument("--seed", type=int, default=5000)
    ap.add_argument(
        "--steps",
        type=int,
        default=600,
        help=f"training steps (validated every {VALIDATE_EVERY} and at the last)",
    )
    args = ap.parse_args()
    if args.worlds < 2:  # the last world validates, the others train
        ap.error("--worlds must be at least 2 (the last one validates)")
    if args.steps < 1:
        ap.error("--steps must be at least 1")
    feat = Features()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="flip_worlds_") as tmp:
        data = labelled_worlds(args.worlds, args.seed, Path(tmp))
    print(f"rendered and read {len(data[0])} crops in {time.perf_counter() - t0:.0f} s")
    t0 = time.perf_counter()
    head, temp, prior_lo = train(feat, *data, steps=args.steps)
    print(f"trained in {time.perf_counter() - t0:.0f} s")
    if args.demo:
        score_set("demo (truth)", feat, head, temp, prior_lo, *scene_set(args.demo, "truth"))
    if args.lab:
        score_set("lab (fused)", feat, head, temp, prior_lo, *scene_set(args.lab, "fused"))


if __name__ == "__main__":
    main()

"""Simulated BlazePose detections: the detector's error measured on rendered crops, replayed on
true joint projections, so the landmark -> body path can be pretrained without rendering.

For each of the 12 limb landmarks (`gst.lift.errors.LIMB_LANDMARKS`) and each truth state
(visible / occluded) the model holds, fitted on the landmark worlds (`gst.lift.dataset`):

- a systematic offset in the frame of the limb's bone in the image (along the bone, across it),
  because a landmark is not exactly where the body model's joint is (BlazePose's shoulder sits
  higher than the joint, its knee lower);
- Gaussian scatter around it (per axis, from the median residual, robust to the tail);
- gross errors: with a per-landmark, per-state probability the landmark lands a distance drawn
  from the measured gross-error distribution away, in a random direction;
- left/right confusion: a whole-body flip (every pair exchanged: the person read as facing the
  other way) and independent single-pair swaps;
- the confidence (visibility x presence), drawn from the measured histogram of its landmark and
  state, so occluded arms come out with low confidence as they do on real detections.

`LandmarkNoise.fit(worlds)` builds it, `save`/`load` keep it as a small JSON
(`gst/lift/blazepose_noise.json`, refit with `python -m gst.lift.noise --worlds DIR`), and
`simulate` turns true 2D joints + visibility into detections. The statistics it reproduces are
measured by `gst.lift.errors.detection_stats`, the same function for real and simulated
detections; `tests/test_lift_noise.py` compares them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch

from gst.atomic import atomic_write_text
from gst.lift.errors import (
    CONF_BINS,
    LIMB_LANDMARKS,
    LR_PAIRS,
    OUTLIER,
    detection_stats,
    pair_swaps,
)

DEFAULT_PATH = Path(__file__).with_name("blazepose_noise.json")
STATS_PATH = Path(__file__).with_name("blazepose_error.json")
N_LIMB = len(LIMB_LANDMARKS)
# The bone whose image direction defines each limb landmark's offset frame: (from, to) joints.
BONE_OF_LANDMARK: tuple[tuple[int, int], ...] = (
    (16, 18),  # shoulder: upper arm
    (17, 19),
    (16, 18),  # elbow: upper arm
    (17, 19),
    (18, 20),  # wrist: forearm
    (19, 21),
    (1, 4),  # hip: thigh
    (2, 5),
    (1, 4),  # knee: thigh
    (2, 5),
    (4, 7),  # ankle: shin
    (5, 8),
)
CONF_BANDS = (0.5, 0.9)  # band edges: below 0.5 (a dropped detection), 0.5-0.9, above 0.9
_MEDIAN_RADIUS = float(np.sqrt(2 * np.log(2)))  # median radius of a 2D unit Gaussian


def bone_frames(joints2d: torch.Tensor | np.ndarray) -> tuple:
    """Unit bone directions (..., 12, 2) and their normals (+90 degrees) in the image, for each
    limb landmark; zero where the bone is shorter than 1e-3 crop sizes in the image."""
    lib = torch if isinstance(joints2d, torch.Tensor) else np
    a = joints2d[..., [b[0] for b in BONE_OF_LANDMARK], :]
    b = joints2d[..., [b[1] for b in BONE_OF_LANDMARK], :]
    d = b - a
    n = (d**2).sum(-1, keepdims=True) ** 0.5 if lib is np else d.norm(dim=-1, keepdim=True)
    unit = d / (n + 1e-9) * (n > 1e-3)
    normal = (
        lib.stack([-unit[..., 1], unit[..., 0]], -1)
        if lib is torch
        else np.stack([-unit[..., 1], unit[..., 0]], -1)
    )
    return unit, normal


@dataclass(frozen=True)
class LandmarkNoise:
    """Fitted detection-error model (crop-size units; state 0 = visible, 1 = occluded)."""

    offset: np.ndarray  # (12, 2) mean (along bone, across bone) of inlier errors
    sigma: np.ndarray  # (12, 2) scatter per state
    gross: np.ndarray  # (12, 2) gross-error probability per state
    gross_quantiles: np.ndarray  # (21,) distance of gross errors, quantiles 0, 0.05, .., 1
    pair_swap: np.ndarray  # (6,) single-pair swap probability (outside whole-body flips)
    flip: float  # whole-body left/right flip probability
    conf_hist: np.ndarray  # (12, 2, 10) confidence histogram per landmark and state
    # Low confidence goes with larger errors: scatter and gross-error probability are scaled
    # per state and confidence band (CONF_BANDS), pooled over the landmarks.
    band_sigma: np.ndarray  # (2, 3)
    band_gross: np.ndarray  # (2, 3)
    presence_quantiles: np.ndarray  # (21,)

    # -- fitting ---------------------------------------------------------------------------

    @classmethod
    def fit(cls, landmarks, presence, joints2d, visible, crop_size: float) -> LandmarkNoise:
        """From detections (N, 33, 3) and presence (N,) against the truth (N, 24, 2), (N, 24)."""
        lm_idx = [lm for lm, _ in LIMB_LANDMARKS]
        j_idx = [j for _, j in LIMB_LANDMARKS]
        det = landmarks[:, lm_idx, :2] / crop_size
        conf = landmarks[:, lm_idx, 2] * presence[:, None]
        tru = joints2d[:, j_idx] / crop_size
        vis = visible[:, j_idx].astype(bool)
        in_image = ((tru >= 0) & (tru <= 1)).all(-1)
        swapped, countable = pair_swaps(det, tru, in_image)
        swapped_lm = np.zeros_like(vis)
        for k, (a, b) in enumerate(LR_PAIRS):
            swapped_lm[:, a] |= swapped[:, k]
            swapped_lm[:, b] |= swapped[:, k]
        diff = det - tru
        err = np.linalg.norm(diff, axis=-1)
        unit, normal = bone_frames(joints2d / crop_size)
        local = np.stack([(diff * unit).sum(-1), (diff * normal).sum(-1)], -1)
        offset = np.zeros((N_LIMB, 2))
        sigma = np.zeros((N_LIMB, 2))
        gross = np.zeros((N_LIMB, 2))
        hist = np.zeros((N_LIMB, 2, len(CONF_BINS) - 1))
        gross_d = []
        for k in range(N_LIMB):
            good = vis[:, k] & ~swapped_lm[:, k] & (err[:, k] <= OUTLIER)
            offset[k] = local[good, k].mean(0)
            for s, state in enumerate((vis[:, k], ~vis[:, k])):
                pool = state & ~swapped_lm[:, k]
                inl = pool & (err[:, k] <= OUTLIER)
                resid = local[inl, k] - offset[k]
                sigma[k, s] = np.median(np.linalg.norm(resid, axis=-1)) / _MEDIAN_RADIUS
                gross[k, s] = (err[pool, k] > OUTLIER).mean()
                gross_d.append(err[pool & (err[:, k] > OUTLIER), k])
                h, _ = np.histogram(np.clip(conf[state, k], 0, 1), bins=CONF_BINS)
                hist[k, s] = h / max(1, h.sum())
        band = np.digitize(conf, CONF_BANDS)  # (N, 12) in 0..2
        band_sigma = np.ones((2, len(CONF_BANDS) + 1))
        band_gross = np.ones_like(band_sigma)
        for s, state in enumerate((vis, ~vis)):
            pool = state & ~swapped_lm
            all_med = np.median(err[pool & (err <= OUTLIER)])
            all_gross = (err[pool] > OUTLIER).mean()
            for b in range(len(CONF_BANDS) + 1):
                sel = pool & (band == b)
                if sel.sum() >= 20:
                    band_sigma[s, b] = np.median(err[sel & (err <= OUTLIER)]) / all_med
                    band_gross[s, b] = (err[sel] > OUTLIER).mean() / max(all_gross, 1e-6)
        n_count = countable.sum(1)
        flipped = (n_count > 0) & (swapped.sum(1) * 2 > n_count)
        flip = float(flipped.mean())
        # single-pair swaps outside flips; in a flipped crop a pair is swapped unless it is
        # itself swapped back, so only unflipped crops measure the independent rate
        unflipped = countable & ~flipped[:, None]
        pair = (swapped & unflipped).sum(0) / np.maximum(unflipped.sum(0), 1)
        q = np.linspace(0, 1, 21)
        model = cls(
            offset=offset,
            sigma=sigma,
            gross=gross,
            gross_quantiles=np.quantile(np.concatenate(gross_d), q),
            pair_swap=pair,
            flip=flip,
            conf_hist=hist,
            band_sigma=band_sigma,
            band_gross=band_gross,
            presence_quantiles=np.quantile(presence, q),
        )
        return model.calibrated(landmarks, presence, joints2d, visible, crop_size)

    def calibrated(
        self, landmarks, presence, joints2d, visible, crop_size: float, rounds: int = 4
    ) -> LandmarkNoise:
        """Moment matching: simulate on the same truth, then scale each landmark's scatter and
        gross-error probability, and shift the pair-swap rates, until the simulated median
        error, gross-error and swap rates equal the measured ones (the confidence bands and
        the Gaussian tail make the closed-form estimates above biased)."""
        real = detection_stats(landmarks, presence, joints2d, visible, crop_size)
        model = self
        j2 = torch.as_tensor(joints2d, dtype=torch.float64)
        vis = torch.as_tensor(visible)
        for r in range(rounds):
            gen = torch.Generator().manual_seed(1234 + r)
            reps = max(1, 20000 // len(j2))
            sim, pres = model.simulate(j2.repeat(reps, 1, 1), vis.repeat(reps, 1), crop_size, gen)
            st = detection_stats(
                as_detections(sim, pres),
                pres.numpy(),
                j2.repeat(reps, 1, 1).numpy(),
                vis.repeat(reps, 1).numpy(),
                crop_size,
            )
            with np.errstate(invalid="ignore", divide="ignore"):
                med = np.stack(
                    [
                        real.err_median_visible / st.err_median_visible,
                        real.err_median_occluded / st.err_median_occluded,
                    ],
                    1,
                )
                out = np.stack(
                    [
                        real.outlier_visible / st.outlier_visible,
                        real.outlier_occluded / st.outlier_occluded,
                    ],
                    1,
                )
            model = dataclasses.replace(
                model,
                sigma=model.sigma * np.nan_to_num(med, nan=1.0),
                gross=np.clip(model.gross * np.nan_to_num(out, nan=1.0, posinf=1.0), 0, 1),
                pair_swap=np.clip(
                    model.pair_swap + np.nan_to_num(real.swap_rate - st.swap_rate), 0, 1
                ),
            )
        return model

    # -- storage ---------------------------------------------------------------------------

    def to_json(self) -> dict:
        return {
            f.name: np.asarray(getattr(self, f.name)).round(6).tolist()
            if isinstance(getattr(self, f.name), np.ndarray)
            else round(float(getattr(self, f.name)), 6)
            for f in fields(self)
        }

    @classmethod
    def from_json(cls, d: dict, where: str = "") -> LandmarkNoise:
        expected = {f.name for f in fields(cls)}
        if set(d) != expected:
            raise ValueError(f"{where}: keys {sorted(d)} differ from {sorted(expected)}")
        return cls(
            **{k: (np.asarray(v) if isinstance(v, list) else float(v)) for k, v in d.items()}
        )

    @classmethod
    def load(cls, path: str | Path = DEFAULT_PATH, kind: str = "motion") -> LandmarkNoise:
        """The model of one pose kind ('motion' or 'random') from a saved JSON."""
        models = json.loads(Path(path).read_text())
        if kind not in models:
            raise ValueError(f"{path}: no noise model for pose kind '{kind}' ({sorted(models)})")
        return cls.from_json(models[kind], f"{path} [{kind}]")

    # -- simulation ------------------------------------------------------------------------

    def simulate(
        self,
        joints2d: torch.Tensor,
        visible: torch.Tensor,
        crop_size: float,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """True joints (B, 24, 2) crop px and visibility (B, 24) -> simulated limb landmarks
        (B, 12, 3): u, v crop px and confidence (visibility x presence, as detections carry),
        and the presence (B,). Landmarks are in LIMB_LANDMARKS order."""
        g = generator
        dev, dt = joints2d.device, joints2d.dtype
        B = joints2d.shape[0]
        j_idx = [j for _, j in LIMB_LANDMARKS]

        def t(x):
            return torch.as_tensor(np.asarray(x), dtype=dt, device=dev)

        def rand(*shape):
            return torch.rand(*shape, generator=g, device=dev, dtype=dt)

        def randn(*shape):
            return torch.randn(*shape, generator=g, device=dev, dtype=dt)

        tru = joints2d[:, j_idx] / crop_size  # (B, 12, 2)
        occ = ~visible[:, j_idx].bool()
        state = occ.long()  # 0 visible, 1 occluded
        # confidence from the landmark's histogram in its state, uniform within the bin
        cdf = t(np.cumsum(self.conf_hist, -1))  # (12, 2, 10)
        cdf_b = cdf[torch.arange(N_LIMB, device=dev)[None], state]  # (B, 12, 10)
        r = rand(B, N_LIMB, 1)
        bin_ = (r > cdf_b).sum(-1).clamp(max=len(CONF_BINS) - 2)
        conf = (bin_.to(dt) + rand(B, N_LIMB)) / (len(CONF_BINS) - 1)
        band = torch.bucketize(conf, t(CONF_BANDS), right=True)  # (B, 12) in 0..2
        unit, normal = bone_frames(joints2d / crop_size)
        off = t(self.offset)
        det = tru + off[None, :, :1] * unit + off[None, :, 1:] * normal
        sig = t(self.sigma).gather(1, state.T).T * t(self.band_sigma)[state, band]  # (B, 12)
        det = det + randn(B, N_LIMB, 2) * sig[..., None]
        # gross errors: inverse-CDF draw of the distance, uniform direction
        p_gross = t(self.gross).gather(1, state.T).T * t(self.band_gross)[state, band]
        is_gross = rand(B, N_LIMB) < p_gross
        q = t(self.gross_quantiles)
        u = rand(B, N_LIMB) * (len(q) - 1)
        lo = u.floor().long().clamp(max=len(q) - 2)
        dist = q[lo] + (u - lo) * (q[lo + 1] - q[lo])
        ang = rand(B, N_LIMB) * (2 * np.pi)
        jump = torch.stack([ang.cos(), ang.sin()], -1) * dist[..., None]
        det = torch.where(is_gross[..., None], tru + jump, det)
        # left/right: whole-body flips, then independent pair swaps (exchange the detections)
        flip = rand(B) < self.flip
        swap = flip[:, None] ^ (rand(B, len(LR_PAIRS)) < t(self.pair_swap))
        left = torch.tensor([a for a, _ in LR_PAIRS], device=dev)
        right = torch.tensor([b for _, b in LR_PAIRS], device=dev)
        dl, dr = det[:, left], det[:, right]
        det = det.clone()
        det[:, left] = torch.where(swap[..., None], dr, dl)
        det[:, right] = torch.where(swap[..., None], dl, dr)
        # presence: inverse CDF; the landmark confidence already includes it (measured product)
        pq = t(self.presence_quantiles)
        u = rand(B) * (len(pq) - 1)
        lo = u.floor().long().clamp(max=len(pq) - 2)
        presence = pq[lo] + (u - lo) * (pq[lo + 1] - pq[lo])
        out = torch.cat([det * crop_size, conf[..., None]], -1)
        return out, presence


def save_models(models: dict[str, LandmarkNoise], path: str | Path = DEFAULT_PATH) -> None:
    text = json.dumps({k: m.to_json() for k, m in models.items()}, indent=1)
    atomic_write_text(path, text)


def load_models(path: str | Path = DEFAULT_PATH) -> dict[str, LandmarkNoise]:
    """Every pose kind's model: {'motion': ..., 'random': ...}."""
    return {
        k: LandmarkNoise.from_json(v, f"{path} [{k}]")
        for k, v in json.loads(Path(path).read_text()).items()
    }


def limb_landmarks(landmarks: np.ndarray | torch.Tensor, presence) -> np.ndarray | torch.Tensor:
    """Real detections (N, 33, 3) + presence (N,) -> (N, 12, 3) in the simulator's layout:
    u, v crop px and confidence = visibility x presence."""
    idx = [lm for lm, _ in LIMB_LANDMARKS]
    sub = landmarks[:, idx]
    conf = sub[..., 2] * presence[:, None]
    if isinstance(sub, torch.Tensor):
        return torch.cat([sub[..., :2], conf[..., None]], -1)
    return np.concatenate([sub[..., :2], conf[..., None]], -1)


def as_detections(sim: torch.Tensor, presence: torch.Tensor) -> np.ndarray:
    """Simulated (B, 12, 3) limb landmarks -> (B, 33, 3) in BlazePose's layout with the
    visibility = confidence / presence (others zero), for `detection_stats`."""
    out = np.zeros((sim.shape[0], 33, 3), np.float32)
    idx = [lm for lm, _ in LIMB_LANDMARKS]
    s = sim.detach().cpu().numpy()
    p = presence.detach().cpu().numpy()
    out[:, idx, :2] = s[..., :2]
    out[:, idx, 2] = s[..., 2] / np.maximum(p[:, None], 1e-6)
    return out


POSE_KINDS = ("motion", "random")


def pose_kind(motion: np.ndarray) -> np.ndarray:
    """(N,) motion names -> 'random' for independent random poses, else 'motion'."""
    return np.where(np.asarray(motion) == "random_static", "random", "motion")


def main(argv: list[str] | None = None) -> None:
    from gst.lift.dataset import load_worlds

    ap = argparse.ArgumentParser(description="fit the BlazePose noise model on landmark worlds")
    ap.add_argument("--worlds", type=Path, required=True)
    ap.add_argument("--exclude-seed", type=int, action="append", default=[])
    args = ap.parse_args(argv)
    worlds = [w for w in load_worlds(args.worlds) if w.seed not in args.exclude_seed]

    def cat(k):
        return np.concatenate([getattr(w, k) for w in worlds])

    kind = pose_kind(cat("motion"))
    size = worlds[0].crop_size
    models, stats = {}, {"worlds": [w.seed for w in worlds]}
    for k in POSE_KINDS:
        sel = kind == k
        arrays = tuple(cat(n)[sel] for n in ("landmarks", "presence", "joints2d", "visible"))
        models[k] = LandmarkNoise.fit(*arrays, size)
        stats[k] = detection_stats(*arrays, size).to_json()
        print(f"{k}: fitted on {int(sel.sum())} crops")
    save_models(models, DEFAULT_PATH)
    text = json.dumps(stats, indent=1)
    atomic_write_text(STATS_PATH, text)
    print(f"worlds {stats['worlds']}: {DEFAULT_PATH}, {STATS_PATH}")


if __name__ == "__main__":
    main()

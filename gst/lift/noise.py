"""Simulated BlazePose detections: the detector's error measured on rendered crops, replayed on
true landmark positions, so the landmark -> body path can be pretrained without rendering.

For each landmark of a set (`gst.lift.errors.LIMBS`: 12 limb landmarks against the joints;
`ALL`: the 33 against the virtual markers) and each truth state (visible / occluded) the model
holds, fitted on the landmark worlds (`gst.lift.dataset`):

- a systematic offset in the frame of a bone in the image (along the bone, across it), for
  what the reference point does not capture (BlazePose's shoulder sits higher than the joint);
- Gaussian scatter around it (per axis, from the median residual, robust to the tail);
- gross errors: with a per-landmark, per-state probability the landmark lands a distance drawn
  from the measured gross-error distribution away, in a random direction;
- left/right confusion: a whole-body flip (every pair exchanged: the person read as facing the
  other way) and independent swaps per group of pairs (hand landmarks swap with the wrists);
- the confidence (visibility x presence), drawn from the measured histogram of its landmark and
  state, so occluded arms come out with low confidence as they do on real detections; low
  confidence goes with larger errors (scatter and gross rate scaled per confidence band).

BlazePose is much worse on unusual poses, so each set has one model per pose kind ('motion':
the motion library, 'random': independent random poses). `python -m gst.lift.noise --worlds DIR`
fits them into `gst/lift/blazepose_noise.json` and writes the measured statistics beside it
(`blazepose_error.json`); `tests/test_lift_noise.py` compares simulated and measured statistics
(`gst.lift.errors.detection_stats`, the same function for both).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch

from gst.atomic import atomic_write_text
from gst.lift.errors import (
    CONF_BINS,
    LANDMARK_SETS,
    LIMBS,
    OUTLIER,
    LandmarkSet,
    detection_stats,
    flipped_crops,
    pair_swaps,
    set_arrays,
    swapped_landmarks,
)

DEFAULT_PATH = Path(__file__).with_name("blazepose_noise.json")
STATS_PATH = Path(__file__).with_name("blazepose_error.json")
POSE_KINDS = ("motion", "random")
CONF_BANDS = (0.5, 0.9)  # band edges: below 0.5 (a dropped detection), 0.5-0.9, above 0.9
_MEDIAN_RADIUS = float(np.sqrt(2 * np.log(2)))  # median radius of a 2D unit Gaussian


def bone_frames(joints2d, lset: LandmarkSet = LIMBS) -> tuple:
    """Unit bone directions (..., L, 2) and their normals (+90 degrees) in the image, for each
    landmark of the set; zero where the bone is shorter than 1e-3 crop sizes in the image."""
    a = joints2d[..., [b[0] for b in lset.bones], :]
    b = joints2d[..., [b[1] for b in lset.bones], :]
    d = b - a
    if isinstance(d, torch.Tensor):
        n = d.norm(dim=-1, keepdim=True)
        unit = d / (n + 1e-9) * (n > 1e-3)
        return unit, torch.stack([-unit[..., 1], unit[..., 0]], -1)
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    unit = d / (n + 1e-9) * (n > 1e-3)
    return unit, np.stack([-unit[..., 1], unit[..., 0]], -1)


def _reference(lset: LandmarkSet, reference2d, visible):
    """The LIMBS set takes the 24 joints and picks its own; any set takes (N, L) references."""
    if reference2d.shape[1] != len(lset):
        if lset.joints is None:
            raise ValueError(f"set '{lset.name}' needs ({len(lset)}) reference points per crop")
        return reference2d[:, list(lset.joints)], visible[:, list(lset.joints)]
    return reference2d, visible


@dataclass(frozen=True)
class LandmarkNoise:
    """Fitted detection-error model of one landmark set and pose kind (crop-size units;
    state 0 = visible, 1 = occluded; L landmarks, G swap groups)."""

    set_name: str
    offset: np.ndarray  # (L, 2) mean (along bone, across bone) of inlier errors
    sigma: np.ndarray  # (L, 2) scatter per state
    gross: np.ndarray  # (L, 2) gross-error probability per state
    gross_quantiles: np.ndarray  # (21,) distance of gross errors, quantiles 0, 0.05, .., 1
    pair_swap: np.ndarray  # (G,) swap probability per group (outside whole-body flips)
    flip: float  # whole-body left/right flip probability
    flip_follow: np.ndarray  # (G,) probability that a group is swapped in a flipped crop
    conf_hist: np.ndarray  # (L, 2, 10) confidence histogram per landmark and state
    band_sigma: np.ndarray  # (2, 3) scatter factor per state and confidence band
    band_gross: np.ndarray  # (2, 3) gross-error factor per state and confidence band
    presence_quantiles: np.ndarray  # (21,)

    @property
    def lset(self) -> LandmarkSet:
        return LANDMARK_SETS[self.set_name]

    def scaled(self, factor: float) -> LandmarkNoise:
        """The model with its scatter and gross-error probabilities times `factor` (offsets,
        swaps, flips, confidences and presence as measured)."""
        if not factor >= 0:
            raise ValueError(f"LandmarkNoise.scaled: factor must be >= 0, got {factor}")
        return replace(self, sigma=self.sigma * factor, gross=np.clip(self.gross * factor, 0, 1))

    # -- fitting ---------------------------------------------------------------------------

    @classmethod
    def fit(
        cls,
        landmarks,
        presence,
        reference2d,
        visible,
        joints2d,
        crop_size: float,
        lset: LandmarkSet = LIMBS,
    ) -> LandmarkNoise:
        """From detections (N, 33, 3) and presence (N,) against reference points (N, L, 2) crop
        px with visibility (N, L) (for LIMBS the joints (N, 24, 2), (N, 24) do), and the true
        joints (N, 24, 2) for the bone frames."""
        if len(landmarks) == 0:
            raise ValueError(f"LandmarkNoise.fit: no crops to fit the '{lset.name}' model on")
        ref, vis = _reference(lset, reference2d, visible)
        L = len(lset)
        det, conf = set_arrays(landmarks, presence, lset, crop_size)
        tru = ref / crop_size
        vis = vis.astype(bool)
        in_image = ((tru >= 0) & (tru <= 1)).all(-1)
        swapped, countable = pair_swaps(det, tru, in_image, lset.pairs)
        swapped_lm = swapped_landmarks(swapped, lset.pairs, L)
        diff = det - tru
        err = np.linalg.norm(diff, axis=-1)
        unit, normal = bone_frames(joints2d / crop_size, lset)
        local = np.stack([(diff * unit).sum(-1), (diff * normal).sum(-1)], -1)
        offset = np.zeros((L, 2))
        sigma = np.full((L, 2), 0.02)
        gross = np.zeros((L, 2))
        hist = np.zeros((L, 2, len(CONF_BINS) - 1))
        hist[..., -1] = 1.0
        gross_d = []
        for k in range(L):
            good = vis[:, k] & ~swapped_lm[:, k] & (err[:, k] <= OUTLIER)
            if good.sum() >= 5:
                offset[k] = local[good, k].mean(0)
            for s, state in enumerate((vis[:, k], ~vis[:, k])):
                pool = state & ~swapped_lm[:, k]
                inl = pool & (err[:, k] <= OUTLIER)
                if inl.sum() >= 5:
                    resid = local[inl, k] - offset[k]
                    sigma[k, s] = np.median(np.linalg.norm(resid, axis=-1)) / _MEDIAN_RADIUS
                if pool.sum() >= 5:
                    gross[k, s] = (err[pool, k] > OUTLIER).mean()
                    gross_d.append(err[pool & (err[:, k] > OUTLIER), k])
                if state.sum() >= 5:
                    h, _ = np.histogram(np.clip(conf[state, k], 0, 1), bins=CONF_BINS)
                    hist[k, s] = h / h.sum()
        band = np.digitize(conf, CONF_BANDS)  # (N, L) in 0..2
        band_sigma = np.ones((2, len(CONF_BANDS) + 1))
        band_gross = np.ones_like(band_sigma)
        for s, state in enumerate((vis, ~vis)):
            pool = state & ~swapped_lm
            if not (pool & (err <= OUTLIER)).any():  # none in this state (all visible): bands 1
                continue
            all_med = np.median(err[pool & (err <= OUTLIER)])
            all_gross = (err[pool] > OUTLIER).mean()
            for b in range(len(CONF_BANDS) + 1):
                sel = pool & (band == b)
                if sel.sum() >= 20:
                    band_sigma[s, b] = np.median(err[sel & (err <= OUTLIER)]) / all_med
                    band_gross[s, b] = (err[sel] > OUTLIER).mean() / max(all_gross, 1e-6)
        flipped = flipped_crops(swapped, countable)
        # swaps outside flips: in a flipped crop a pair is swapped unless swapped back, so only
        # unflipped crops measure the independent rate (pooled over each group's pairs)
        unflipped = countable & ~flipped[:, None]
        group = np.asarray(lset.swap_group)
        pair = np.array(
            [
                (swapped & unflipped)[:, group == g].sum() / max(unflipped[:, group == g].sum(), 1)
                for g in range(lset.n_groups)
            ]
        )
        follow = np.array(
            [
                (swapped & countable)[flipped][:, group == g].sum()
                / max(countable[flipped][:, group == g].sum(), 1)
                for g in range(lset.n_groups)
            ]
        )
        q = np.linspace(0, 1, 21)
        model = cls(
            set_name=lset.name,
            offset=offset,
            sigma=sigma,
            gross=gross,
            # no gross error measured: every rate is 0, so the distances are never drawn
            gross_quantiles=np.quantile(np.concatenate(gross_d), q)
            if sum(map(len, gross_d))
            else np.full(len(q), OUTLIER),
            pair_swap=pair,
            flip=float(flipped.mean()),
            flip_follow=follow,
            conf_hist=hist,
            band_sigma=band_sigma,
            band_gross=band_gross,
            presence_quantiles=np.quantile(presence, q),
        )
        return model.calibrated(landmarks, presence, ref, vis, joints2d, crop_size)

    def calibrated(
        self, landmarks, presence, reference2d, visible, joints2d, crop_size: float, rounds: int = 4
    ) -> LandmarkNoise:
        """Moment matching: simulate on the same truth, then scale each landmark's scatter and
        gross-error probability, and shift the swap rates, until the simulated median error,
        gross-error and swap rates equal the measured ones (the confidence bands and the
        Gaussian tail make the closed-form estimates above biased)."""
        lset = self.lset
        real = detection_stats(landmarks, presence, reference2d, visible, crop_size, lset)
        model = self
        ref = torch.as_tensor(reference2d, dtype=torch.float64)
        vis = torch.as_tensor(visible)
        j2 = torch.as_tensor(joints2d, dtype=torch.float64)
        reps = max(1, 20000 // len(ref))
        ref_r, vis_r, j2_r = ref.repeat(reps, 1, 1), vis.repeat(reps, 1), j2.repeat(reps, 1, 1)
        group = np.asarray(lset.swap_group)
        for r in range(rounds):
            gen = torch.Generator().manual_seed(1234 + r)
            sim, pres = model.simulate(ref_r, vis_r, j2_r, crop_size, gen)
            st = detection_stats(
                as_detections(sim, pres, lset),
                pres.numpy(),
                ref_r.numpy(),
                vis_r.numpy(),
                crop_size,
                lset,
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
                dswap = real.swap_rate - st.swap_rate
                shift = np.array(
                    [
                        np.nanmean(dswap[group == g]) if np.isfinite(dswap[group == g]).any() else 0
                        for g in range(lset.n_groups)
                    ]
                )
            model = dataclasses.replace(
                model,
                sigma=model.sigma * np.nan_to_num(med, nan=1.0, posinf=1.0),
                gross=np.clip(model.gross * np.nan_to_num(out, nan=1.0, posinf=1.0), 0, 1),
                pair_swap=np.clip(model.pair_swap + shift, 0, 1),
            )
        return model

    # -- storage ---------------------------------------------------------------------------

    def to_json(self) -> dict:
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                out[f.name] = np.asarray(v, np.float64).round(6).tolist()
            elif isinstance(v, str):
                out[f.name] = v
            else:
                out[f.name] = round(float(v), 6)
        return out

    @classmethod
    def from_json(cls, d: dict, where: str = "") -> LandmarkNoise:
        expected = {f.name for f in fields(cls)}
        if set(d) != expected:
            raise ValueError(f"{where}: keys {sorted(d)} differ from {sorted(expected)}")
        kw = {}
        for k, v in d.items():
            kw[k] = (
                np.asarray(v) if isinstance(v, list) else (v if isinstance(v, str) else float(v))
            )
        if kw["set_name"] not in LANDMARK_SETS:
            raise ValueError(f"{where}: unknown landmark set {kw['set_name']!r}")
        return cls(**kw)

    @classmethod
    def load(
        cls, path: str | Path = DEFAULT_PATH, kind: str = "motion", set_name: str = "limbs"
    ) -> LandmarkNoise:
        """The model of one landmark set and pose kind ('motion' or 'random') from a JSON."""
        return load_models(path, set_name)[kind] if kind in POSE_KINDS else _bad_kind(path, kind)

    # -- simulation ------------------------------------------------------------------------

    def simulate(
        self,
        reference2d: torch.Tensor,
        visible: torch.Tensor,
        joints2d: torch.Tensor,
        crop_size: float,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """True landmark positions (B, L, 2) crop px (for LIMBS the joints (B, 24, 2) do) with
        visibility, and the true joints (B, 24, 2) for the bone frames -> simulated landmarks
        (B, L, 3): u, v crop px and confidence (visibility x presence, as detections carry),
        and the presence (B,)."""
        lset = self.lset
        reference2d, visible = _reference(lset, reference2d, visible)
        g = generator
        dev, dt = reference2d.device, reference2d.dtype
        B, L = reference2d.shape[:2]

        def t(x):
            return torch.as_tensor(np.asarray(x), dtype=dt, device=dev)

        def rand(*shape):
            return torch.rand(*shape, generator=g, device=dev, dtype=dt)

        tru = reference2d / crop_size
        state = (~visible.bool()).long()  # 0 visible, 1 occluded
        # confidence from the landmark's histogram in its state, uniform within the bin
        cdf = t(np.cumsum(self.conf_hist, -1))  # (L, 2, 10)
        cdf_b = cdf[torch.arange(L, device=dev)[None], state]  # (B, L, 10)
        bin_ = (rand(B, L, 1) > cdf_b).sum(-1).clamp(max=len(CONF_BINS) - 2)
        conf = (bin_.to(dt) + rand(B, L)) / (len(CONF_BINS) - 1)
        band = torch.bucketize(conf, t(CONF_BANDS), right=True)  # (B, L) in 0..2
        unit, normal = bone_frames(joints2d.to(dt) / crop_size, lset)
        off = t(self.offset)
        det = tru + off[None, :, :1] * unit + off[None, :, 1:] * normal
        idx = torch.arange(L, device=dev)[None].expand(B, L)
        sig = t(self.sigma)[idx, state] * t(self.band_sigma)[state, band]
        det = det + torch.randn(B, L, 2, generator=g, device=dev, dtype=dt) * sig[..., None]
        # gross errors: inverse-CDF draw of the distance, uniform direction
        p_gross = t(self.gross)[idx, state] * t(self.band_gross)[state, band]
        is_gross = rand(B, L) < p_gross
        dist = _inverse_cdf(t(self.gross_quantiles), rand(B, L))
        ang = rand(B, L) * (2 * np.pi)
        jump = torch.stack([ang.cos(), ang.sin()], -1) * dist[..., None]
        det = torch.where(is_gross[..., None], tru + jump, det)
        # left/right: whole-body flips, then independent swaps per group (exchange detections)
        flip = rand(B) < self.flip
        u = rand(B, lset.n_groups)
        grp = torch.where(flip[:, None], u < t(self.flip_follow), u < t(self.pair_swap))
        swap = grp[:, list(lset.swap_group)]  # (B, P)
        left = torch.tensor([a for a, _ in lset.pairs], device=dev)
        right = torch.tensor([b for _, b in lset.pairs], device=dev)
        # (positions only: the measured confidence of a landmark follows its own truth state)
        dl, dr = det[:, left], det[:, right]
        det = det.clone()
        det[:, left] = torch.where(swap[..., None], dr, dl)
        det[:, right] = torch.where(swap[..., None], dl, dr)
        presence = _inverse_cdf(t(self.presence_quantiles), rand(B))
        return torch.cat([det * crop_size, conf[..., None]], -1), presence


def _bad_kind(path, kind):
    raise ValueError(f"{path}: no noise model for pose kind '{kind}' (expected {POSE_KINDS})")


def _inverse_cdf(q: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear inverse CDF through the quantiles q (K,) at u in [0, 1)."""
    x = u * (len(q) - 1)
    lo = x.floor().long().clamp(max=len(q) - 2)
    return q[lo] + (x - lo) * (q[lo + 1] - q[lo])


def save_models(
    models: dict[str, dict[str, LandmarkNoise]], path: str | Path = DEFAULT_PATH
) -> None:
    """{set name: {pose kind: model}} as one JSON."""
    doc = {s: {k: m.to_json() for k, m in kinds.items()} for s, kinds in models.items()}
    atomic_write_text(path, json.dumps(doc, indent=1))


def load_models(
    path: str | Path = DEFAULT_PATH, set_name: str = "limbs"
) -> dict[str, LandmarkNoise]:
    """Every pose kind's model of one landmark set: {'motion': ..., 'random': ...}."""
    doc = json.loads(Path(path).read_text())
    if set_name not in doc:
        raise ValueError(f"{path}: no noise models for landmark set '{set_name}' ({sorted(doc)})")
    return {
        k: LandmarkNoise.from_json(v, f"{path} [{set_name}/{k}]") for k, v in doc[set_name].items()
    }


def set_landmarks(landmarks, presence, lset: LandmarkSet = LIMBS):
    """Real detections (N, 33, 3) + presence (N,) -> (N, L, 3) in the simulator's layout:
    u, v crop px and confidence = visibility x presence."""
    sub = landmarks[:, list(lset.ids)]
    conf = sub[..., 2] * presence[:, None]
    if isinstance(sub, torch.Tensor):
        return torch.cat([sub[..., :2], conf[..., None]], -1)
    return np.concatenate([sub[..., :2], conf[..., None]], -1)


def limb_landmarks(landmarks, presence):
    return set_landmarks(landmarks, presence, LIMBS)


def as_detections(
    sim: torch.Tensor, presence: torch.Tensor, lset: LandmarkSet = LIMBS
) -> np.ndarray:
    """Simulated (B, L, 3) landmarks -> (B, 33, 3) in BlazePose's layout with the
    visibility = confidence / presence (others zero), for `detection_stats`."""
    out = np.zeros((sim.shape[0], 33, 3), np.float32)
    idx = list(lset.ids)
    s = sim.detach().cpu().numpy()
    p = presence.detach().cpu().numpy()
    out[:, idx, :2] = s[..., :2]
    out[:, idx, 2] = s[..., 2] / np.maximum(p[:, None], 1e-6)
    return out


def pose_kind(motion: np.ndarray) -> np.ndarray:
    """(N,) motion names -> 'random' for independent random poses, else 'motion'."""
    return np.where(np.asarray(motion) == "random_static", "random", "motion")


def main(argv: list[str] | None = None) -> None:
    from gst.body import load_body_model
    from gst.lift.dataset import load_worlds
    from gst.lift.references import world_references

    ap = argparse.ArgumentParser(description="fit the BlazePose noise models on landmark worlds")
    ap.add_argument("--worlds", type=Path, required=True)
    ap.add_argument("--exclude-seed", type=int, action="append", default=[])
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    worlds = [w for w in load_worlds(args.worlds) if w.seed not in args.exclude_seed]
    body = load_body_model("anny")
    refs = [world_references(w, body) for w in worlds]

    def cat(k):
        return np.concatenate([getattr(w, k) for w in worlds])

    kind = pose_kind(cat("motion"))
    size = worlds[0].crop_size
    truth = {
        "limbs": (cat("joints2d"), cat("visible")),
        "all": (np.concatenate([r[0] for r in refs]), np.concatenate([r[1] for r in refs])),
    }
    models: dict = {}
    stats: dict = {"worlds": [w.seed for w in worlds]}
    for set_name, (ref, vis) in truth.items():
        lset = LANDMARK_SETS[set_name]
        models[set_name], stats[set_name] = {}, {}
        for k in POSE_KINDS:
            sel = kind == k
            if not sel.any():  # the sampler needs both kinds' models
                raise SystemExit(
                    f"no crops of pose kind '{k}' in worlds {stats['worlds']} (random poses: "
                    "every fourth world, python -m gst.lift.dataset --worlds 4 or more)"
                )
            args_ = (cat("landmarks")[sel], cat("presence")[sel], ref[sel], vis[sel])
            models[set_name][k] = LandmarkNoise.fit(*args_, cat("joints2d")[sel], size, lset)
            stats[set_name][k] = detection_stats(*args_, size, lset).to_json()
            print(f"{set_name}/{k}: fitted on {int(sel.sum())} crops")
    save_models(models, DEFAULT_PATH)
    atomic_write_text(STATS_PATH, json.dumps(stats, indent=1))
    print(f"worlds {stats['worlds']}: {DEFAULT_PATH}, {STATS_PATH}")


if __name__ == "__main__":
    main()

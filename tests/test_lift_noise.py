"""The detection noise model against the measured BlazePose error (docs/landmark_prior.md).

Tolerances (stated in the doc too), where both sides have at least 150 points of a landmark
in a state (or countable crops of a pair): per landmark, the simulated median error of visible
and of occluded joints within 10% / 20% of the measured one; dropout (confidence < 0.5), gross
error and swap rates within 3 points (dropouts of occluded joints 8, their gross errors 10:
occluded joints in the sampler come from a z-buffer proxy and a random occluder box, not from
rendered occluders, and are fewer); whole-body flips
within 2 points; each bin of the pooled confidence histogram within 3 points (limb set only:
pooled over 33 landmarks it mostly measures how many heads each side occludes). Random poses
(953 measured crops): twice these. Swaps of the 33-landmark set: 4 points.
"""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from gst.body import load_body_model
from gst.lift.errors import LANDMARK_SETS, LIMB_LANDMARKS, DetectionStats, detection_stats
from gst.lift.noise import (
    DEFAULT_PATH,
    STATS_PATH,
    LandmarkNoise,
    as_detections,
    load_models,
    pose_kind,
    save_models,
)
from gst.lift.sampler import LiftSampler

WORLDS = Path("/work/data/landmark_worlds")
_BODY = []


_SAMPLES = {}


def _body():
    if not _BODY:
        _BODY.append(load_body_model("anny"))
    return _BODY[0]


def _sampled(set_name):
    """One batch per landmark set, shared by the tests (only bank poses: the uniform
    joint-limit draws have no measured counterpart)."""
    if set_name not in _SAMPLES:
        sampler = LiftSampler(_body(), seed=11, uniform_p=0.0, landmark_set=set_name)
        _SAMPLES[set_name] = sampler.sample(5000)
    return _SAMPLES[set_name]


def _measured(kind: str = "motion", set_name: str = "limbs") -> DetectionStats:
    return DetectionStats.from_json(json.loads(STATS_PATH.read_text())[set_name][kind])


MIN_CELL = (
    150  # per-landmark/state and per-pair statistics: compared where both sides have this many
)


def _compare(sim: DetectionStats, real: DetectionStats, scale: float = 1.0) -> list[str]:
    """Names of the statistics outside tolerance (scale > 1 loosens every tolerance)."""
    bad = []
    cells = {
        "visible": (real.n_visible >= MIN_CELL) & (sim.n_visible >= MIN_CELL),
        "occluded": (real.n_occluded >= MIN_CELL) & (sim.n_occluded >= MIN_CELL),
        "swap_rate": (real.n_pairs >= MIN_CELL) & (sim.n_pairs >= MIN_CELL),
    }

    def pick(name, a):
        for key, ok in cells.items():
            if name.endswith(key) and a.shape == ok.shape:
                return a[ok]
        return a

    def rel(name, tol):
        a, b = pick(name, getattr(sim, name)), pick(name, getattr(real, name))
        if a.size and np.nanmax(np.abs(a / b - 1)) > tol * scale:
            bad.append(f"{name}: sim {np.round(a, 3)} real {np.round(b, 3)}")

    def absdiff(name, tol):
        a = pick(name, np.asarray(getattr(sim, name)))
        b = pick(name, np.asarray(getattr(real, name)))
        if a.size and np.nanmax(np.abs(a - b)) > tol * scale:
            bad.append(f"{name}: sim {np.round(a, 3)} real {np.round(b, 3)}")

    rel("err_median_visible", 0.10)
    rel("err_median_occluded", 0.20)
    absdiff("drop_visible", 0.03)
    absdiff("drop_occluded", 0.08)
    absdiff("outlier_visible", 0.03)
    absdiff("outlier_occluded", 0.10)
    # 33 landmarks: face pairs and hips swap with the whole-body flips in ways the sampler's view
    # mix reproduces less well (mouth corners: 4.2% measured, 7.8% simulated)
    absdiff("swap_rate", 0.03 if len(real.n_visible) == 12 else 0.04)
    absdiff("flip_rate", 0.02)
    if len(real.n_visible) == 12:  # pooled over the landmarks: only where the mix is the same
        absdiff("conf_hist_visible", 0.03)
        absdiff("conf_hist_occluded", 0.03)
    return bad


def _simulated_stats(noise: LandmarkNoise, j2, vis, seed=0) -> DetectionStats:
    """Limb-set model simulated on joints (B, 24, 2) and their visibility."""
    sim, pres = noise.simulate(j2, vis, j2, 256, torch.Generator().manual_seed(seed))
    return detection_stats(as_detections(sim, pres), pres.numpy(), j2.numpy(), vis.numpy(), 256)


@pytest.mark.parametrize("set_name", ["limbs", "all"])
@pytest.mark.parametrize("kind", ["motion", "random"])
def test_simulated_detections_match_the_measured_statistics(kind, set_name):
    """On the sampler's render-free crops (other poses and cameras than the worlds the model
    was fitted on), per pose kind and landmark set (12 limb landmarks against the joints, all
    33 against the virtual markers): the statistics conditional on visibility carry over."""
    b = _sampled(set_name)
    sel = b.random_pose if kind == "random" else ~b.random_pose
    lset = LANDMARK_SETS[set_name]
    st = detection_stats(
        as_detections(b.landmarks[sel], b.presence[sel], lset),
        b.presence[sel].numpy(),
        b.reference2d[sel].numpy(),
        b.reference_visible[sel].numpy(),
        256,
        lset,
    )
    # random poses: 953 measured crops (2839 for motions), so 2 x the tolerances
    real = _measured(kind, set_name)
    assert _compare(st, real, scale=2.0 if kind == "random" else 1.0) == []


def test_the_comparison_catches_a_wrong_model():
    """The same check fails for a model with half the scatter, or no left/right confusion."""
    noise = LandmarkNoise.load(kind="motion")
    b = _sampled("limbs")  # the bank poses the comparison above passes on
    j2, vis = b.joints2d, b.visible
    assert _compare(_simulated_stats(noise, j2, vis), _measured()) == []
    tight = dataclasses.replace(noise, sigma=noise.sigma / 2)
    assert any(
        "err_median_visible" in s for s in _compare(_simulated_stats(tight, j2, vis), _measured())
    )
    no_swaps = dataclasses.replace(noise, flip=0.0, pair_swap=np.zeros(6))
    bad = _compare(_simulated_stats(no_swaps, j2, vis), _measured())
    assert any("swap_rate" in s for s in bad) and any("flip_rate" in s for s in bad)


def test_simulation_mechanics():
    noise = LandmarkNoise.load(kind="motion")
    j2 = torch.rand(500, 24, 2) * 200 + 28
    vis = torch.ones(500, 24, dtype=torch.bool)
    # no scatter, no gross errors, no swaps: the landmarks sit at the joint + the bone offset
    exact = dataclasses.replace(
        noise, sigma=noise.sigma * 0, gross=noise.gross * 0, flip=0.0, pair_swap=np.zeros(6)
    )
    sim, pres = exact.simulate(j2, vis, j2, 256)
    ji = [j for _, j in LIMB_LANDMARKS]
    shift = (sim[..., :2] - j2[:, ji]).norm(dim=-1) / 256
    assert shift.max() <= np.linalg.norm(noise.offset, axis=1).max() + 1e-5
    # every crop flipped: left landmarks land on the right joints
    flipped = dataclasses.replace(exact, flip=1.0, flip_follow=np.ones(6), offset=noise.offset * 0)
    sim, _ = flipped.simulate(j2, vis, j2, 256)
    assert torch.allclose(sim[:, 0, :2], j2[:, 17]) and torch.allclose(sim[:, 1, :2], j2[:, 16])
    # occluded joints get lower confidence than visible ones, as measured
    sim_v, _ = noise.simulate(j2, vis, j2, 256, torch.Generator().manual_seed(0))
    sim_o, _ = noise.simulate(j2, ~vis, j2, 256, torch.Generator().manual_seed(0))
    assert sim_o[..., 2].mean() < sim_v[..., 2].mean() - 0.2
    assert 0.0 <= pres.min() and pres.max() <= 1.0


def test_noise_json_round_trip_and_errors(tmp_path):
    models = {s: load_models(DEFAULT_PATH, s) for s in ("limbs", "all")}
    assert set(models["limbs"]) == {"motion", "random"}
    assert models["all"]["motion"].sigma.shape == (33, 2)
    # BlazePose is worse on random poses than on the motion library's (measured)
    for s in models.values():
        assert (s["random"].sigma[:, 0] > s["motion"].sigma[:, 0]).mean() > 0.7
        assert s["random"].flip > s["motion"].flip
    save_models(models, tmp_path / "n.json")
    back = LandmarkNoise.load(tmp_path / "n.json", kind="random", set_name="all")
    assert np.allclose(back.sigma, models["all"]["random"].sigma) and back.set_name == "all"
    assert back.flip == pytest.approx(models["all"]["random"].flip)
    with pytest.raises(ValueError, match="walking"):
        LandmarkNoise.load(tmp_path / "n.json", kind="walking")
    with pytest.raises(ValueError, match="hands"):
        load_models(tmp_path / "n.json", "hands")
    d = json.loads((tmp_path / "n.json").read_text())
    d["limbs"]["motion"].pop("flip")
    (tmp_path / "bad.json").write_text(json.dumps(d))
    with pytest.raises(ValueError, match="flip"):
        LandmarkNoise.load(tmp_path / "bad.json")


@pytest.mark.skipif(not WORLDS.is_dir(), reason="the landmark worlds are not on this machine")
def test_held_out_world_pooled_over_landmarks():
    """Fitted on the other motion worlds, simulated on world 5006's truth (other people,
    cameras, motions). Worlds differ from each other more than the model errs (leave-one-out
    over the six motion worlds: median error ratio 0.79-1.11, docs/landmark_prior.md), so the
    held-out check is pooled over the 12 landmarks: median error within 25%, dropout rate of
    visible joints within 3 points, gross errors and swaps within 4, flips within 5."""
    from gst.lift.dataset import load_worlds

    worlds = [w for w in load_worlds(WORLDS) if (pose_kind(w.motion) == "motion").all()]
    fit = [w for w in worlds if w.seed != 5006]
    test = [w for w in worlds if w.seed == 5006]
    assert test, "world 5006 is missing"

    def cat(ws, k):
        return np.concatenate([getattr(w, k) for w in ws])

    keys = ("landmarks", "presence", "joints2d", "visible")
    noise = LandmarkNoise.fit(*(cat(fit, k) for k in keys), cat(fit, "joints2d"), 256)
    real = detection_stats(*(cat(test, k) for k in keys), 256)
    j2 = torch.as_tensor(np.tile(cat(test, "joints2d"), (8, 1, 1)))
    vis = torch.as_tensor(np.tile(cat(test, "visible"), (8, 1)))
    sim = _simulated_stats(noise, j2, vis)
    ratio = np.median(sim.err_median_visible / real.err_median_visible)
    assert 0.75 <= ratio <= 1.25
    assert abs(sim.drop_visible.mean() - real.drop_visible.mean()) < 0.03
    assert abs(sim.outlier_visible.mean() - real.outlier_visible.mean()) < 0.04
    assert abs(sim.swap_rate.mean() - real.swap_rate.mean()) < 0.04
    assert abs(sim.flip_rate - real.flip_rate) < 0.05


def test_scaled_noise_scales_the_scatter_and_gross_rates_only():
    from gst.lift.noise import load_models

    m = load_models(set_name="limbs")["motion"]
    half = m.scaled(0.5)
    np.testing.assert_allclose(half.sigma, m.sigma * 0.5)
    np.testing.assert_allclose(half.gross, m.gross * 0.5)
    np.testing.assert_array_equal(half.offset, m.offset)
    np.testing.assert_array_equal(half.pair_swap, m.pair_swap)
    assert half.flip == m.flip
    with pytest.raises(ValueError, match="factor"):
        m.scaled(-1.0)


def test_the_sampler_simulates_smaller_errors_with_a_smaller_noise_scale():
    from gst.lift.sampler import LiftSampler

    body = load_body_model("anny")
    err = {}
    for scale in (1.0, 0.3):
        b = LiftSampler(body, seed=4, noise_scale=scale, whole_body_flips=False).sample(256)
        d = (b.landmarks[..., :2] - b.reference2d).norm(dim=-1)
        err[scale] = float(d.median())
    assert err[0.3] < 0.6 * err[1.0], err


def _clean_detections(n: int, seed: int = 0):
    """n crops whose limb landmarks sit within a few pixels of their joints (no gross error)."""
    rng = np.random.default_rng(seed)
    j2 = rng.uniform(20, 230, (n, 24, 2)).astype(np.float32)
    det = np.zeros((n, 33, 3), np.float32)
    lset = LANDMARK_SETS["limbs"]
    det[:, list(lset.ids), :2] = j2[:, list(lset.joints)] + rng.normal(0, 1, (n, len(lset), 2))
    det[..., 2] = 0.9
    return det, np.full(n, 0.99, np.float32), j2, np.ones((n, 24), bool)


def test_fitting_without_a_gross_error_or_without_crops():
    """Clean detections (no gross error anywhere) crashed the fit in np.quantile of nothing;
    no crops at all (a pose kind missing from the worlds) in np.concatenate of nothing."""
    det, pres, j2, vis = _clean_detections(40)
    model = LandmarkNoise.fit(det, pres, j2, vis, j2, 256)
    assert (model.gross == 0).all() and np.isfinite(model.gross_quantiles).all()
    sim, _ = model.simulate(
        torch.as_tensor(j2), torch.as_tensor(vis), torch.as_tensor(j2), 256,
        torch.Generator().manual_seed(0),
    )  # fmt: skip
    assert torch.isfinite(sim).all()
    with pytest.raises(ValueError, match="no crops"):
        LandmarkNoise.fit(det[:0], pres[:0], j2[:0], vis[:0], j2[:0], 256)

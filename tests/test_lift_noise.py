"""The detection noise model against the measured BlazePose error (docs/landmark_prior.md).

Tolerances (stated in the doc too): per limb landmark, the simulated median error of visible
and of occluded joints within 10% / 20% of the measured one; dropout (confidence < 0.5), gross
error and swap rates within 3 points (dropouts of occluded joints 8, their gross errors 10:
occluded joints in the sampler come from a z-buffer proxy and a random occluder box, not from
rendered occluders, and are fewer); whole-body flips
within 2 points; each confidence-histogram bin within 3 points.
"""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from gst.body import load_body_model
from gst.lift.errors import LIMB_LANDMARKS, DetectionStats, detection_stats
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


def _measured(kind: str = "motion") -> DetectionStats:
    return DetectionStats.from_json(json.loads(STATS_PATH.read_text())[kind])


def _compare(sim: DetectionStats, real: DetectionStats, scale: float = 1.0) -> list[str]:
    """Names of the statistics outside tolerance (scale > 1 loosens every tolerance)."""
    bad = []

    def rel(name, tol):
        a, b = getattr(sim, name), getattr(real, name)
        if np.nanmax(np.abs(a / b - 1)) > tol * scale:
            bad.append(f"{name}: sim {np.round(a, 3)} real {np.round(b, 3)}")

    def absdiff(name, tol):
        a, b = np.asarray(getattr(sim, name)), np.asarray(getattr(real, name))
        if np.nanmax(np.abs(a - b)) > tol * scale:
            bad.append(f"{name}: sim {np.round(a, 3)} real {np.round(b, 3)}")

    rel("err_median_visible", 0.10)
    rel("err_median_occluded", 0.20)
    absdiff("drop_visible", 0.03)
    absdiff("drop_occluded", 0.08)
    absdiff("outlier_visible", 0.03)
    absdiff("outlier_occluded", 0.10)
    absdiff("swap_rate", 0.03)
    absdiff("flip_rate", 0.02)
    absdiff("conf_hist_visible", 0.03)
    absdiff("conf_hist_occluded", 0.03)
    return bad


def _simulated_stats(noise: LandmarkNoise, j2, vis, seed=0) -> DetectionStats:
    sim, pres = noise.simulate(j2, vis, 256, torch.Generator().manual_seed(seed))
    return detection_stats(as_detections(sim, pres), pres.numpy(), j2.numpy(), vis.numpy(), 256)


@pytest.mark.parametrize("kind", ["motion", "random"])
def test_simulated_detections_match_the_measured_statistics(kind):
    """On the sampler's render-free crops (other poses and cameras than the worlds the model
    was fitted on), per pose kind: the statistics conditional on visibility carry over."""
    # only bank poses (the uniform joint-limit draws have no measured counterpart)
    sampler = LiftSampler(load_body_model("anny"), seed=11, uniform_p=0.0)
    b = sampler.sample(9000)
    sel = b.random_pose if kind == "random" else ~b.random_pose
    st = detection_stats(
        as_detections(b.landmarks[sel], b.presence[sel]),
        b.presence[sel].numpy(),
        b.joints2d[sel].numpy(),
        b.visible[sel].numpy(),
        256,
    )
    # random poses: 953 measured crops (2839 for motions), so 1.5 x the tolerances
    assert _compare(st, _measured(kind), scale=1.5 if kind == "random" else 1.0) == []


def test_the_comparison_catches_a_wrong_model():
    """The same check fails for a model with half the scatter, or no left/right confusion."""
    noise = LandmarkNoise.load(kind="motion")
    b = LiftSampler(load_body_model("anny"), noise=noise, seed=12).sample(3000)
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
    sim, pres = exact.simulate(j2, vis, 256)
    ji = [j for _, j in LIMB_LANDMARKS]
    shift = (sim[..., :2] - j2[:, ji]).norm(dim=-1) / 256
    assert shift.max() <= np.linalg.norm(noise.offset, axis=1).max() + 1e-5
    # every crop flipped: left landmarks land on the right joints
    flipped = dataclasses.replace(exact, flip=1.0, offset=noise.offset * 0)
    sim, _ = flipped.simulate(j2, vis, 256)
    assert torch.allclose(sim[:, 0, :2], j2[:, 17]) and torch.allclose(sim[:, 1, :2], j2[:, 16])
    # occluded joints get lower confidence than visible ones, as measured
    sim_v, _ = noise.simulate(j2, vis, 256, torch.Generator().manual_seed(0))
    sim_o, _ = noise.simulate(j2, ~vis, 256, torch.Generator().manual_seed(0))
    assert sim_o[..., 2].mean() < sim_v[..., 2].mean() - 0.2
    assert 0.5 < pres.min() and pres.max() <= 1.0 or pres.min() >= 0.0


def test_noise_json_round_trip_and_errors(tmp_path):
    models = load_models(DEFAULT_PATH)
    assert set(models) == {"motion", "random"}
    # BlazePose is worse on random poses than on the motion library's (measured)
    assert (models["random"].sigma[:, 0] > models["motion"].sigma[:, 0]).mean() > 0.7
    assert models["random"].flip > models["motion"].flip
    save_models(models, tmp_path / "n.json")
    back = LandmarkNoise.load(tmp_path / "n.json", kind="random")
    assert np.allclose(back.sigma, models["random"].sigma)
    assert back.flip == pytest.approx(models["random"].flip)
    with pytest.raises(ValueError, match="walking"):
        LandmarkNoise.load(tmp_path / "n.json", kind="walking")
    d = json.loads((tmp_path / "n.json").read_text())
    d["motion"].pop("flip")
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
    noise = LandmarkNoise.fit(*(cat(fit, k) for k in keys), 256)
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

"""The render-free pretraining of the landmark path: what it trains, what it leaves alone, and
the scoring of single-image predictions."""

import dataclasses

import numpy as np
import pytest
import torch

from gst.body import load_body_model
from gst.lift.errors import LIMBS
from gst.lift.pretrain import (
    LiftPretrainConfig,
    body_joints,
    limb_agreement,
    pretrain_landmark_path,
    score,
    trainable_parameters,
)
from gst.lift.sampler import LiftSampler
from gst.model.landmarks import LandmarkInput
from gst.model.presets import get_preset
from gst.train.recipe import build_network


@pytest.fixture(scope="module")
def body():
    return load_body_model("anny")


def test_pretraining_moves_only_the_landmark_path(body):
    torch.manual_seed(0)
    net, _, _ = build_network(get_preset("tiny", landmark_tokens=True), body)
    before = {k: v.clone() for k, v in net.state_dict().items()}
    sampler = LiftSampler(body, seed=2)
    cfg = LiftPretrainConfig(steps=25, batch_size=16, warmup_steps=5, lr=2e-3)
    res = pretrain_landmark_path(net, body, cfg, sampler=sampler, log=lambda *_: None)
    assert res.steps == 25 and res.samples_per_s > 0 and res.last_loss == res.last_loss
    after = net.state_dict()
    moved = {k for k in after if not torch.equal(after[k], before[k])}
    assert any(k.startswith("landmark_encoder.") for k in moved)
    assert any(".landmark_layers." in k for k in moved)
    assert any(k.startswith("smpl_head.decpose") for k in moved)
    # the image path and the Gaussian head are untouched (image cross-attention included)
    assert not any(k.startswith(("backbone.", "gaussian_head.")) for k in moved)
    assert not any(".layers.0.1." in k or ".layers.1.1." in k for k in moved)
    ids = {id(p) for p in trainable_parameters(net)}
    assert all(id(p) not in ids for p in net.backbone.parameters())


def test_a_few_hundred_samples_already_lower_the_error(body):
    """Same batch before/after 40 steps: the 3D error on fresh simulated crops falls."""
    torch.manual_seed(1)
    net, _, _ = build_network(get_preset("tiny", landmark_tokens=True), body)
    probe = LiftSampler(body, seed=99).sample(128)

    def err():
        with torch.no_grad():
            inp = LandmarkInput.from_pixels(probe.landmarks, probe.K, probe.crop_size)
            out = net.eval()(None, with_gaussians=False, landmarks=inp)
            j, _ = body_joints(out, body, probe.K, probe.crop_size)
            rel = (j - j[:, :1]) - (probe.joints_cam - probe.joints_cam[:, :1])
            return float(rel.norm(dim=-1).mean())

    e0 = err()
    cfg = LiftPretrainConfig(steps=40, batch_size=32, warmup_steps=5, lr=2e-3)
    pretrain_landmark_path(net, body, cfg, sampler=LiftSampler(body, seed=3), log=lambda *_: None)
    assert err() < 0.85 * e0


def test_score_is_zero_for_the_truth_and_rejects_plain_networks(body):
    j = torch.randn(5, 24, 3, dtype=torch.float64)
    s = score(j, j)
    assert s.mpjpe_mm < 1e-9 and s.pa_mpjpe_mm < 1e-6 and s.crops == 5
    shifted = score(j + torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64), j)
    assert shifted.mpjpe_mm < 1e-9  # root-aligned
    net, _, _ = build_network(get_preset("tiny"), body)
    with pytest.raises(ValueError, match="landmark_tokens"):
        pretrain_landmark_path(net, body, dataclasses.replace(LiftPretrainConfig(), steps=1))


def test_the_loop_runs_on_its_own_threads_and_puts_the_callers_back(body, monkeypatch):
    import gst.lift.pretrain as lp

    net, _, _ = build_network(get_preset("tiny", landmark_tokens=True), body)
    seen = []
    real = lp._pretrain

    def spy(*args, **kwargs):
        seen.append(torch.get_num_threads())
        return real(*args, **kwargs)

    monkeypatch.setattr(lp, "_pretrain", spy)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        cfg = LiftPretrainConfig(steps=2, batch_size=4, warmup_steps=1, threads=1)
        pretrain_landmark_path(net, body, cfg, sampler=LiftSampler(body), log=lambda *_: None)
        assert seen == [1] and torch.get_num_threads() == 3
        # default: the cores the background sampler leaves
        monkeypatch.setattr(lp, "available_cores", lambda: 4)
        cfg = dataclasses.replace(cfg, threads=None)
        pretrain_landmark_path(net, body, cfg, sampler=LiftSampler(body), log=lambda *_: None)
        assert seen == [1, 3] and torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)


def test_pretraining_trains_the_reprojection_refiner_too(body):
    torch.manual_seed(0)
    cfg = get_preset("tiny", landmark_tokens=True, num_landmarks=33, landmark_refine=2)
    net, _, _ = build_network(cfg, body)
    ids = {id(p) for p in trainable_parameters(net)}
    assert all(id(p) in ids for p in net.refiner.parameters())
    before = net.refiner.out.weight.clone()
    sampler = LiftSampler(body, seed=2, landmark_set="all")
    run = LiftPretrainConfig(steps=5, batch_size=8, warmup_steps=1, lr=2e-3)
    pretrain_landmark_path(net, body, run, sampler=sampler, log=lambda *_: None)
    assert not torch.equal(net.refiner.out.weight, before)


def test_limb_agreement_ignores_a_shift_and_unsure_landmarks():
    rng = np.random.default_rng(0)
    joints2d = rng.uniform(0, 256, (4, 24, 2))
    lm = np.full((4, 33, 3), np.nan)
    lm[:, list(LIMBS.ids), :2] = joints2d[:, list(LIMBS.joints)] + [7.0, -3.0]  # a shift only
    lm[:, list(LIMBS.ids), 2] = 0.9
    assert limb_agreement(joints2d, lm, 256) == pytest.approx(0.0, abs=1e-9)
    # every right-side limb landmark 2.56 px (1 % of the crop) off: half of the 12 -> median
    # between 0 and about 1 %; with those unsure, 0 again
    off = lm.copy()
    right = [i for i in LIMBS.ids if i % 2 == 0]
    off[:, right, 0] += 2.56
    assert 0.0 < limb_agreement(joints2d, off, 256) < 1.0
    off[:, right, 2] = 0.2
    assert limb_agreement(joints2d, off, 256) == pytest.approx(0.0, abs=1e-9)
    lm[..., 2] = 0.1
    assert limb_agreement(joints2d, lm, 256) is None


def test_evaluate_world_weighs_landmarks_by_the_persons_presence(body, monkeypatch):
    """The 2D agreement read visibility alone: crops where the model found nobody (presence
    0.05, visibility 0.9) counted, unlike in the network's input and in track's agreement."""
    import gst.lift.pretrain as pretrain
    from tests.test_lift_dataset import _world

    torch.manual_seed(0)
    net, _, _ = build_network(get_preset("tiny", landmark_tokens=True), body)
    world = _world(4)
    world.landmarks[..., 2] = 0.9
    world.presence[:] = [1.0, 0.05, 1.0, 0.5]
    world.K_crop[:] = [[200, 0, 127.5], [0, 200, 127.5], [0, 0, 1]]
    world.t[:] = [0.0, 0.0, 3.0]
    seen = {}
    monkeypatch.setattr(pretrain, "limb_agreement", lambda j2d, lm, size: seen.update(lm=lm))
    pretrain.evaluate_world(net, body, world)
    want = np.broadcast_to([[0.9], [0.045], [0.9], [0.45]], (4, 33))
    np.testing.assert_allclose(seen["lm"][..., 2], want, rtol=1e-6)
    np.testing.assert_array_equal(seen["lm"][..., :2], world.landmarks[..., :2])


def test_crop_jitter_is_refused_where_it_would_do_nothing():
    """`pretrain.augment` jitters mode 3d's supervised crops; with mode pretrain (multi-view
    batches) or lift it was accepted and silently did nothing."""
    from pydantic import ValidationError

    from gst.train.pretrain import PretrainConfig

    assert PretrainConfig(mode="3d", augment=True).augment
    for mode in ("pretrain", "lift"):
        with pytest.raises(ValidationError, match="augment jitters the supervised crops"):
            PretrainConfig(mode=mode, augment=True)


def test_lift_mode_without_its_rendered_phase_is_refused_up_front():
    """gaussian_steps: 0 in mode lift was accepted and crashed on a missing last.pt after the
    lifting, the world renders and the landmark model on every crop."""
    from pydantic import ValidationError

    from gst.train.pretrain import PretrainConfig

    with pytest.raises(ValidationError, match="gaussian_steps: 0 leaves mode 'lift'"):
        PretrainConfig(mode="lift", gaussian_steps=0)
    assert PretrainConfig(mode="3d", gaussian_steps=0).gaussian_steps == 0


def test_a_crop_size_that_lift_mode_would_ignore_is_refused():
    """pretrain.crop_size was accepted in mode lift, which cuts its crops at 256 px whatever it
    says."""
    from pydantic import ValidationError

    from gst.train.pretrain import PretrainConfig

    with pytest.raises(ValidationError, match="crop_size .64. sets the crops of modes"):
        PretrainConfig(mode="lift", crop_size=64)
    assert PretrainConfig(mode="3d", crop_size=160).crop_size == 160
    assert PretrainConfig().mode == "lift"  # the default is not refused
    assert PretrainConfig(mode="lift", crop_size=256).crop_size == 256  # nor what lift uses


@pytest.mark.parametrize(
    "preset, mode, crop_size, given",
    [
        ("huge", "3d", 128, "128"),
        ("tiny", "pretrain", 64, "64"),
        ("small", "3d", 128, "128"),
    ],
)
def test_image_modes_refuse_crops_smaller_than_the_networks_input(preset, mode, crop_size, given):
    """Modes 3d and pretrain upsampled crops smaller than the network's input without a word
    (the huge preset's 256x192 input from 128 px crops: blown up 2x)."""
    from pydantic import ValidationError

    from gst.train.pretrain import PretrainConfig

    side = get_preset(preset).image_size[0]
    kw = {"crop_size": crop_size}
    with pytest.raises(
        ValidationError, match=rf"crop_size \({given}\) is smaller than .* \({side} px high\)"
    ):
        PretrainConfig(preset=preset, mode=mode, **kw)
    assert PretrainConfig(preset=preset, mode=mode, crop_size=side).crop_size == side
    assert PretrainConfig(mode="3d").crop_size == 128  # the tiny preset's default fits
    # left out, the crop size follows a larger preset's input
    assert PretrainConfig(preset="small", mode="3d").crop_size == 256


def test_the_default_and_the_demo_pretrain_settings_validate():
    from pathlib import Path

    import yaml

    from gst.train.pretrain import PretrainConfig

    demo = yaml.safe_load((Path(__file__).parents[1] / "pipeline.yaml").read_text())
    assert PretrainConfig(**demo["stages"]["pretrain"]["params"]).mode == "lift"
    assert PretrainConfig().crop_size == 128


def test_the_train_summary_says_which_frames_its_mpjpe_is_on(tmp_path):
    """summary.md's MPJPE rows were measured on training frames, labelled only 'against the
    synthetic truth'; the held-out frames' figure reached summary.json only."""
    from types import SimpleNamespace

    from gst.train.recipe import FitSummary
    from gst.train.scene_training import _write_markdown

    fit = FitSummary(10, 0, None, 1.0, {"mpjpe_mm": 92.4}, {"mpjpe_mm": 74.3}, 5, ["c2"])
    _write_markdown(tmp_path / "s.md", fit, 36, SimpleNamespace(mpjpe_mm=105.1))
    md = (tmp_path / "s.md").read_text()
    assert "| mpjpe_mm, held-out frames (36-) | | 105.1 |" in md and "on training frames" in md


def test_the_pretrain_threads_setting_holds_in_the_lifting_loop(tmp_path, monkeypatch):
    """`pretrain.threads` was set before the lift phase, which then ran on the cores less one
    whatever was set (on 16 cores with threads: 1, the loop took 15)."""
    import gst.lift.pretrain as lift_pretrain
    import gst.lift.recipe as recipe
    from gst.train.pretrain import PretrainConfig

    monkeypatch.setattr(lift_pretrain, "available_cores", lambda: 16)
    monkeypatch.setattr(recipe, "render_corpus", lambda *a, **k: [])
    seen = []

    def stop(net, body, cfg, sampler, validation, log):
        seen.append(torch.get_num_threads())
        raise KeyboardInterrupt  # enough: the loop's threads are known

    monkeypatch.setattr(lift_pretrain, "_pretrain", stop)
    before = torch.get_num_threads()
    p = PretrainConfig(mode="lift", threads=1, lift_steps=2)
    with pytest.raises(KeyboardInterrupt):
        recipe.pretrain(p, tmp_path, tmp_path / "p.pt", tmp_path / "r")
    torch.set_num_threads(before)
    assert seen == [1]


@pytest.mark.parametrize("setting", ["steps", "batch_size", "val_every", "crop_size"])
def test_a_pretraining_setting_below_one_is_refused_by_name(setting):
    """steps 0 ended in an UnboundLocalError after the loop (`--steps 0`), val_every 0 in a
    ZeroDivisionError at the first step, batch_size 0 deep in the body model."""
    with pytest.raises(ValueError, match=f"LiftPretrainConfig.{setting} must be >= 1"):
        LiftPretrainConfig(**{setting: 0})


def test_a_resumed_lift_mode_keeps_its_finished_lifting(tmp_path, monkeypatch):
    """A run killed (or failed) after the lifting, in the renders, BlazePose or the rendered
    phase, lifted again from scratch when resumed (3000 steps in pipeline.yaml): the lifting
    kept nothing in the stage's work folder. Now its result is kept there, and a rerun with the
    same settings starts the rendered phase from exactly the lifted weights."""
    from types import SimpleNamespace

    import gst.lift.recipe as recipe
    from gst.lift.pretrain import LiftPretrainResult
    from gst.train.pretrain import PretrainConfig

    lifted = []

    def fake_lift(net, body, steps, batch_size, lr, seed=0, threads=None):
        with torch.no_grad():
            for q in net.landmark_encoder.parameters():
                q.add_(torch.randn_like(q))  # what a lifting would leave: other weights
        lifted.append({k: v.clone() for k, v in net.state_dict().items()})
        return LiftPretrainResult(steps, 1.0, 2.0, 3.0, 0.5, 120.0)

    seen = []

    class Killed(Exception):
        pass

    def rendered(net, *a, **k):
        seen.append({k: v.clone() for k, v in net.state_dict().items()})
        raise Killed

    crops = SimpleNamespace(crop_size=256)
    monkeypatch.setattr(recipe, "lift_phase", fake_lift)
    monkeypatch.setattr(recipe, "render_corpus", lambda *a, **k: ["w0", "val"])
    monkeypatch.setattr(recipe, "corpus_crops", lambda *a, **k: (crops, crops))
    monkeypatch.setattr(recipe, "attach_landmarks", lambda *a, **k: None)
    monkeypatch.setattr(recipe, "make_task", lambda *a, **k: None)
    monkeypatch.setattr(recipe, "rendered_phase", rendered)
    p = PretrainConfig(
        worlds=1, lift_steps=2, appearance_on_truth=False,
        losses={"lpips": 0.0},
    )  # fmt: skip
    for _ in range(2):
        with pytest.raises(Killed):
            recipe.pretrain(p, tmp_path, tmp_path / "p.pt", tmp_path / "r")
    assert len(lifted) == 1  # the second run did not lift again
    gate = "smpl_head.transformer.smpl_image_gate"
    for state in seen:
        assert all(
            torch.equal(state[k], v) for k, v in lifted[0].items() if k != gate
        )  # the lifted weights, the image gate closed as before
    # other lifting settings lift again
    with pytest.raises(Killed):
        recipe.pretrain(p.model_copy(update={"lift_steps": 3}), tmp_path, tmp_path / "p.pt",
                        tmp_path / "r")  # fmt: skip
    assert len(lifted) == 2


def test_the_image_modes_step_count_and_rate_are_refused_in_lift_mode():
    """`steps` and `lr` set the image modes' run; mode lift's rendered phase runs
    `gaussian_steps` at `gaussian_lr` / `lift_body_lr`, so `steps: 2000` in mode lift was accepted
    and did nothing (the tiny end-to-end config set `steps: 2` believing it shortened it)."""
    from pydantic import ValidationError

    from gst.train.pretrain import PretrainConfig

    for field, value, instead in [("steps", 2000, "gaussian_steps"), ("lr", 1e-3, "gaussian_lr")]:
        with pytest.raises(ValidationError, match=rf"{field} \(.*\) sets .* {instead}"):
            PretrainConfig(mode="lift", **{field: value})
        assert getattr(PretrainConfig(mode="3d", **{field: value}), field) == value
    assert PretrainConfig().steps == 1000  # the defaults are not refused

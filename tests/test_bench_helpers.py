"""The benchmark scripts' shared means and timing (benchmarks/summary.py, benchmarks/timing.py):
what a mean leaves out is counted, and round-robin timing calls every variant in turn."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from benchmarks.summary import finite_mean, known_mean, left_out, weighted_mean
from benchmarks.timing import round_robin_medians


def test_finite_mean_leaves_out_non_finite_values():
    assert finite_mean([0.1, float("nan"), 0.3, float("inf")]) == (pytest.approx(0.2), 2)
    assert finite_mean([[0.1], [0.3]]) == (pytest.approx(0.2), 0)
    mean, dropped = finite_mean([float("nan")])
    assert math.isnan(mean) and dropped == 1
    mean, dropped = finite_mean([])
    assert math.isnan(mean) and dropped == 0


def test_known_mean_leaves_out_none_not_as_zero():
    assert known_mean([0.8, None, 0.6]) == (pytest.approx(0.7), 1)
    assert known_mean([0.0, 1.0]) == (pytest.approx(0.5), 0)  # a real 0 counts
    mean, dropped = known_mean([None, None])
    assert math.isnan(mean) and dropped == 2


def test_weighted_mean_counts_a_weight_only_with_its_value():
    # 10 matches at 50 mm, 30 matches without a pose error: the mean is 50, not 12.5
    assert weighted_mean([(50.0, 10), (None, 30)]) == pytest.approx(50.0)
    assert weighted_mean([(50.0, 10), (90.0, 30)]) == pytest.approx(80.0)
    assert math.isnan(weighted_mean([(None, 5)]))
    assert math.isnan(weighted_mean([(40.0, 0)]))


def test_left_out_says_nothing_when_nothing_was():
    assert left_out(0, 4, "scenes") == ""
    assert left_out(1, 4, "scenes") == " (1 of 4 scenes left out)"


def test_round_robin_medians_warms_up_then_alternates():
    calls: list[str] = []

    def make(name):
        def fn():
            calls.append(name)
            return len(calls)

        return fn

    out = round_robin_medians([make("a"), make("b")], repeats=2, warmup=1)
    assert calls == ["a", "a", "b", "a", "b"]
    assert [r for _, r in out] == [4, 5]  # each call's last result
    assert all(s >= 0 for s, _ in out)
    with pytest.raises(ValueError):
        round_robin_medians([make("a")], repeats=0)


def test_lift_variants_sampler_is_the_recipe_with_the_variants_keys(monkeypatch):
    import gst.lift.pretrain as pretrain
    from benchmarks.lift_variants import SAMPLER_KEYS, parse_variant, sampler_config

    sampler_args, run_args = parse_variant("uniform_p=0.1,whole_body_flips=0,steps=30")
    assert sampler_args == {"uniform_p": 0.1, "whole_body_flips": False}
    assert run_args == {"steps": 30}
    cfg = sampler_config(sampler_args, seed=3)
    recipe = pretrain.LiftPretrainConfig()
    assert cfg.uniform_p == 0.1 and cfg.seed == 3
    for key in ("lean_deg", "noise_scale", "arm_mix_p", "leg_mix_p", "random_share"):
        assert getattr(cfg, key) == getattr(recipe, key)  # the recipe's, not LiftSampler's
    # every key the recipe passes to its sampler is a variant key, and no other
    monkeypatch.setattr(pretrain, "LiftSampler", lambda body, **kw: kw)
    passed = set(recipe.sampler(None, "all")) - {"crop_size", "seed", "landmark_set"}
    assert passed == set(SAMPLER_KEYS)


def _flip_set(n: int = 12, size: int = 32):
    g = torch.Generator().manual_seed(0)
    imgs = torch.zeros(n, size, size, 3, dtype=torch.uint8)
    lms = torch.cat([torch.rand(n, 33, 2, generator=g) * size, torch.ones(n, 33, 1)], -1)
    sides = np.where(np.arange(n) % 3 == 0, -1, 1)
    world = np.repeat([0, 1], n // 2)
    return imgs, lms, sides, world


def test_flip_check_trains_fewer_steps_than_a_validation_interval():
    from benchmarks.bench_flip_check_worlds import VALIDATE_EVERY, train

    def feat(images):
        return torch.ones(len(images), 4, 15, 15)

    head, temp, prior_lo = train(feat, *_flip_set(), steps=VALIDATE_EVERY // 10)
    assert math.isfinite(temp) and math.isfinite(prior_lo)


def test_flip_check_says_so_when_validation_is_never_finite():
    from benchmarks.bench_flip_check_worlds import train

    def feat(images):
        return torch.full((len(images), 4, 15, 15), float("nan"))

    with pytest.raises(SystemExit, match="never finite"):
        train(feat, *_flip_set(), steps=3)

"""The evaluate and bench stages are declared right: bench applies to scenes with truth only,
evaluate to every scene (real ones against the rig's fused bodies), and their parameters are
validated."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from pipeline.config import SceneConfig
from pipeline.registry import load_stage


def test_bench_applies_only_to_scenes_with_truth_evaluate_to_all():
    synthetic = SceneConfig(synthetic={"preset": "demo", "seed": 0})
    real = SceneConfig(videos=["cam0.mp4", "cam1.mp4"])
    bench, evaluate = load_stage("bench"), load_stage("evaluate")
    assert bench.applies(synthetic) and not bench.applies(real)
    assert evaluate.applies(synthetic) and evaluate.applies(real)


def test_params_reject_unknown_keys_and_bad_variants():
    bench = load_stage("bench")
    p = bench.params_model(variants=[{"name": "t", "preset": "tiny", "image_size": [64, 48]}])
    assert p.variants[0].image_size == (64, 48)
    with pytest.raises(ValidationError):
        bench.params_model(variants=[{"name": "t", "preset": "giant"}])
    with pytest.raises(ValidationError):
        load_stage("evaluate").params_model(render_sise=64)

"""The evaluate and bench stages are declared right: they apply to scenes with truth only, and
their parameters are validated."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from pipeline.config import SceneConfig
from pipeline.registry import load_stage


@pytest.mark.parametrize("name", ["evaluate", "bench"])
def test_applies_only_to_scenes_with_truth(name):
    stage = load_stage(name)
    assert stage.applies(SceneConfig(synthetic={"preset": "demo", "seed": 0}))
    assert not stage.applies(SceneConfig(videos=["cam0.mp4", "cam1.mp4"]))


def test_params_reject_unknown_keys_and_bad_variants():
    bench = load_stage("bench")
    p = bench.params_model(variants=[{"name": "t", "preset": "tiny", "image_size": [64, 48]}])
    assert p.variants[0].image_size == (64, 48)
    with pytest.raises(ValidationError):
        bench.params_model(variants=[{"name": "t", "preset": "giant"}])
    with pytest.raises(ValidationError):
        load_stage("evaluate").params_model(render_sise=64)

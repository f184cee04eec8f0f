"""The pretraining corpus: distinct worlds, the validation world last and never trained on."""

from gst.train.pretrain import PretrainConfig as Params
from gst.train.pretrain import world_specs


def test_world_specs_vary_and_end_with_the_validation_world():
    p = Params(worlds=6, world_rigs=["dome", "h36m"], static_every=3, world_fov_deg=(40.0, 75.0))
    specs = world_specs(p)
    assert len(specs) == 7
    assert [s["name"] for s in specs][-1] == "pretrain_val"
    assert len({s["seed"] for s in specs}) == 7
    assert [s["rig"]["kind"] for s in specs[:4]] == ["dome", "h36m", "dome", "h36m"]
    static = [
        i for i, s in enumerate(specs) if s["motions"] == [["random_static"]] * p.world_people
    ]
    assert static == [2, 5]
    fovs = [s["rig"]["fov_deg"] for s in specs]
    assert all(40 <= f <= 75 for f in fovs) and len(set(fovs)) == 7
    assert specs == world_specs(p)  # deterministic: a resumed stage renders the same worlds


def _ctx(tmp_path, params):
    import logging

    from pipeline.stage import StageContext

    return StageContext(
        stage="pretrain",
        scene_name="s",
        scene=None,
        config=None,
        workspace=tmp_path / "ws",
        staging=tmp_path / "staging",
        params=params,
        log=logging.getLogger("test"),
    )


def test_reuse_copies_a_checked_checkpoint_and_fingerprints_it(tmp_path):
    import json

    import pytest

    from gst.body import BodyModel
    from gst.body.random_model import random_body_data
    from gst.model.checkpoint import save_checkpoint
    from gst.model.presets import get_preset
    from gst.train.recipe import build_network
    from stages.pretrain import STAGE, run

    body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
    net, ids, groups = build_network(get_preset("tiny", vertex_preset="full"), body)
    ckpt = tmp_path / "other_scene_pretrain.pt"
    save_checkpoint(ckpt, net, "random", ids, groups)
    ctx = _ctx(tmp_path, Params(body_model="random", reuse=ckpt))
    run(ctx)
    assert (ctx.staging / "models/pretrain.pt").read_bytes() == ckpt.read_bytes()
    assert json.loads((ctx.staging / "reports/pretrain/summary.json").read_text()) == {
        "reused": str(ckpt)
    }
    assert STAGE.inputs(ctx) == [ckpt]
    with pytest.raises(ValueError, match="body model 'random'"):
        run(_ctx(tmp_path / "b", Params(body_model="anny", reuse=ckpt)))
    not_gst = tmp_path / "x.pt"
    import torch

    torch.save({"state_dict": {}}, not_gst)
    with pytest.raises(ValueError, match="not a GST checkpoint"):
        run(_ctx(tmp_path / "c", Params(reuse=not_gst)))


def _saved_tiny(path, spec="random"):
    from gst.body import BodyModel
    from gst.body.random_model import random_body_data
    from gst.model.checkpoint import save_checkpoint
    from gst.model.presets import get_preset
    from gst.train.recipe import build_network

    body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
    net, ids, groups = build_network(get_preset("tiny", vertex_preset="full"), body)
    save_checkpoint(path, net, spec, ids, groups)
    return path


def test_reuse_refuses_weights_that_do_not_fit_or_are_not_finite_naming_the_file(tmp_path):
    """reuse only read the file and copied it: a config that names no network, or
    NaN weights, failed in the train stage naming models/pretrain.pt, or at the first batch."""
    import pytest
    import torch

    from stages.pretrain import run

    good = torch.load(_saved_tiny(tmp_path / "good.pt"), weights_only=True)
    no_vit = {**good, "config": {k: v for k, v in good["config"].items() if k != "vit"}}
    torch.save(no_vit, tmp_path / "novit.pt")
    key = "smpl_head.decpose.weight"
    nan = {**good, "model": {**good["model"], key: torch.full_like(good["model"][key], torch.nan)}}
    torch.save(nan, tmp_path / "nan.pt")
    for name, why in [("novit", "config lacks 'vit'"), ("nan", f"'{key}' is not")]:
        ctx = _ctx(tmp_path / name, Params(body_model="random", reuse=tmp_path / f"{name}.pt"))
        with pytest.raises(ValueError, match=rf"{name}\.pt: .*{why}"):
            run(ctx)
        assert not (ctx.staging / "models/pretrain.pt").exists()


def test_world_settings_that_cannot_make_a_world_are_refused_by_name():
    """world_rigs: [] ended in a ZeroDivisionError, world_seed: -1 in numpy's bare 'expected
    non-negative integer', world_people: 0 / world_fps: 0 / a field of view outside 5-150 deg in
    a SceneSpec error naming n_people / rig.fps / rig.fov_deg; static_every: -3 was taken as 0;
    world_cameras: 1 failed after the lifting, the renders and BlazePose with 'no training
    samples' (the multi-view phases need a person seen by two cameras)."""
    import pytest
    from pydantic import ValidationError

    for field, value in [
        ("world_rigs", []),
        ("world_seed", -1),
        ("world_people", 0),
        ("world_fps", 0.0),
        ("world_fov_deg", (2.0, 60.0)),
        ("world_fov_deg", (40.0, 150.0)),
        ("static_every", -3),
        ("world_cameras", 1),
    ]:
        with pytest.raises(ValidationError, match=field):
            Params(**{field: value})
    with pytest.raises(ValidationError, match="world_cameras"):
        Params(mode="3d", world_cameras=1)  # its Gaussian phase is multi-view too
    # single views suffice where nothing multi-view runs
    assert Params(mode="3d", gaussian_steps=0, world_cameras=1).world_cameras == 1
    assert Params(world_seed=0, static_every=0).static_every == 0


def test_a_kept_world_is_reused_only_when_it_is_that_world(tmp_path, monkeypatch):
    """render_world kept any finished folder of the world's name: a work folder reused with
    other settings (benchmarks/bench_flip_check_worlds.py renders into one with its own
    `worlds`) trained on stale worlds, and with more worlds than before the old 'pretrain_val'
    (seed world_seed + old worlds) was the new training world of that seed: the validation
    world was a training world."""
    import json
    from pathlib import Path

    import gst.train.pretrain as pretrain

    rendered = []

    def fake_render(spec, out):
        rendered.append(spec.seed)
        Path(out).mkdir(parents=True, exist_ok=True)
        scene = {"format": "synth-scene", "spec": spec.model_dump(mode="json")}
        (Path(out) / "scene.json").write_text(json.dumps(scene))

    monkeypatch.setattr(pretrain, "render_scene", fake_render)
    for worlds in (2, 2, 3):
        pretrain.render_corpus(Params(worlds=worlds), tmp_path)
    # 2 worlds + val; the same again: nothing; 3 worlds: the new world 2 and the new val
    assert rendered == [1000, 1001, 1002, 1002, 1003]
    val = json.loads((tmp_path / "worlds/pretrain_val/scene.json").read_text())
    assert val["spec"]["seed"] == 1003

"""GST checkpoints (gst.model.checkpoint) as readers meet them: weights that are not finite,
fields of the wrong type and vertex ids beyond the body are refused when the file is read,
naming the file, not at the first batch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gst.body import BodyModel
from gst.body.random_model import random_body_data
from gst.model.checkpoint import load_checkpoint, network_from_checkpoint, save_checkpoint
from gst.model.network import GSTNetwork
from gst.model.presets import get_preset
from gst.train.recipe import build_network


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A tiny network's checkpoint on a small random body saved as a file (its spec: the path),
    and the checkpoint's dict as written."""
    root = tmp_path_factory.mktemp("ckpt")
    data = random_body_data(num_vertices=400, with_posedirs=False)
    spec = str(data.save_npz(root / "body.npz"))
    net, ids, groups = build_network(get_preset("tiny"), BodyModel(data))
    path = root / "good.pt"
    save_checkpoint(path, net, spec, ids, groups)
    return path, torch.load(path, weights_only=True)


def _variant(saved, tmp_path, name: str, change) -> str:
    _, base = saved
    ckpt = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    change(ckpt)
    path = tmp_path / f"{name}.pt"
    torch.save(ckpt, path)
    return str(path)


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_weights_that_are_not_finite_are_refused_naming_the_file_and_the_key(
    saved, tmp_path, value
):
    """A NaN checkpoint loaded and failed at the first batch (`body_pose contains NaN`),
    naming no file."""
    from gst.model.inference import GSTPredictor

    key = "smpl_head.decpose.weight"

    def poison(ckpt):
        ckpt["model"][key] = ckpt["model"][key].clone()
        ckpt["model"][key][3, 5] = value

    bad = _variant(saved, tmp_path, "bad", poison)
    with pytest.raises(ValueError, match=rf"bad\.pt: the checkpoint's weight '{key}' is not"):
        network_from_checkpoint(load_checkpoint(bad), bad)
    with pytest.raises(ValueError, match=rf"bad\.pt: .*'{key}' is not finite"):
        GSTPredictor(bad)
    network_from_checkpoint(load_checkpoint(saved[0]), saved[0])  # the good one loads


def test_the_refiners_body_buffers_may_be_nan_until_set_body(tmp_path):
    """A refiner's skeleton and markers are NaN by design until `set_body` runs: a network saved
    before it is not refused for them (it refuses to run without a body, gst.model.refine)."""
    data = random_body_data(num_vertices=400, with_posedirs=False)
    cfg = get_preset("tiny", landmark_tokens=True, num_landmarks=33, landmark_refine=2)
    _, ids, groups = build_network(cfg, BodyModel(data))
    bare = GSTNetwork(cfg, groups)  # no set_body
    assert not bool(torch.isfinite(bare.refiner.rest_joints).all())
    save_checkpoint(tmp_path / "bare.pt", bare, "anny", ids, groups)
    back = network_from_checkpoint(load_checkpoint(tmp_path / "bare.pt"), tmp_path / "bare.pt")
    assert back.refiner is not None


@pytest.mark.parametrize(
    "key, value, kind",
    [("config", "tiny", "str"), ("extra", "x", "str"), ("model", [1, 2], "list")],
)
def test_fields_that_must_be_dicts_are_checked_naming_the_file(saved, tmp_path, key, value, kind):
    """`config` or `extra` of another type passed the reader, then an AttributeError came from
    whatever called .get on it (the tracks' model provenance)."""

    def change(ckpt):
        ckpt[key] = value

    bad = _variant(saved, tmp_path, "typed", change)
    with pytest.raises(ValueError, match=rf"typed\.pt: '{key}' must be a dict, got {kind}"):
        load_checkpoint(bad)


def test_a_checkpoint_without_extra_still_reads(saved, tmp_path):
    bad = _variant(saved, tmp_path, "noextra", lambda c: c.pop("extra"))
    assert load_checkpoint(bad).extra == {}


def test_vertex_ids_beyond_the_checkpoints_own_body_are_refused_naming_both(saved, tmp_path):
    """Checked only when another body was passed: with the checkpoint's own spec it failed at the
    first batch (`vertex_ids must lie in [0, 400)`), naming no file."""
    from gst.model.inference import GSTPredictor

    def shift(ckpt):
        ckpt["vertex_ids"] = ckpt["vertex_ids"] + 1000

    bad = _variant(saved, tmp_path, "ids", shift)
    spec = load_checkpoint(bad).body_model
    with pytest.raises(ValueError, match=r"ids\.pt: body model '.*body\.npz' has 400 vertices"):
        GSTPredictor(bad)
    with pytest.raises(ValueError, match=r"ids\.pt: body model '.*body\.npz' has 400 vertices"):
        GSTPredictor(bad, body_model=spec)
    crops = np.zeros((1, 128, 128, 3), np.uint8)
    K = np.array([[[150.0, 0, 64], [0, 150, 64], [0, 0, 1]]], np.float32)
    assert GSTPredictor(saved[0])(crops, K)["rotmats"].shape == (1, 24, 3, 3)


def test_the_module_doc_describes_every_field_a_checkpoint_holds(saved):
    """The layout said `extra` held the training step and optimiser state; those sit under
    `trainer` (gst.train.trainer), which it did not name."""
    import dataclasses
    import re

    import gst.model.checkpoint as module
    from gst.model.checkpoint import GSTCheckpoint

    layout = module.__doc__.split("Layout", 1)[1].split("Writes go", 1)[0]
    documented = set(re.findall(r"(\w+): ", layout))  # "key: what it holds"
    fields = {f.name for f in dataclasses.fields(GSTCheckpoint)}
    assert fields | set(saved[1]) <= documented, sorted(fields | set(saved[1]) - documented)
    extra = re.search(r"^    extra:(.*?)^    \w+:", layout, flags=re.M | re.S).group(1)
    assert "optimiser" not in extra and "trained_on" in extra


def _body_at(path, seed=0):
    path.parent.mkdir(parents=True, exist_ok=True)
    data = random_body_data(num_vertices=400, with_posedirs=False, seed=seed)
    return str(data.save_npz(path)), data


def _checkpoint_with_body(tmp_path, spec, data):
    net, ids, groups = build_network(get_preset("tiny"), BodyModel(data))
    path = tmp_path / "pretrain.pt"
    save_checkpoint(path, net, spec, ids, groups)
    return path


def test_a_body_file_gone_from_its_recorded_path_names_the_checkpoint(tmp_path):
    """A checkpoint records its body model as an absolute path: once the project folder moved,
    loading it failed with a FileNotFoundError naming the body's path alone."""
    from gst.model.inference import GSTPredictor

    spec, data = _body_at(tmp_path / "old/body.npz")
    ckpt = _checkpoint_with_body(tmp_path, spec, data)
    (tmp_path / "old/body.npz").rename(tmp_path / "new.npz")
    with pytest.raises(ValueError, match=r"pretrain\.pt: cannot load the body model .*put it back"):
        GSTPredictor(ckpt)
    assert GSTPredictor(ckpt, body_model=str(tmp_path / "new.npz")).body.num_vertices == 400
    # evaluate loads the models the same way (a bare FileNotFoundError there too)
    from gst.eval.scene import _model

    with pytest.raises(ValueError, match=r"pretrain\.pt: cannot load the body model"):
        _model(ckpt, {})


def test_reuse_and_train_take_the_same_body_file_at_another_path(tmp_path, caplog):
    """pretrain.reuse and train compared body models as text: the same file at another path (a
    moved project folder) was refused as another body."""
    import shutil

    from gst.body import load_body_model
    from gst.train.pretrain import PretrainConfig, reuse_checkpoint
    from gst.train.scene_training import TrainSettings, _initial_network

    spec, data = _body_at(tmp_path / "old/body.npz")
    ckpt = _checkpoint_with_body(tmp_path, spec, data)
    moved = tmp_path / "new/body.npz"
    moved.parent.mkdir()
    shutil.copyfile(spec, moved)

    def reuse(body_spec: str, name: str):
        p = PretrainConfig(reuse=ckpt, body_model=body_spec)
        (tmp_path / name).mkdir()
        return reuse_checkpoint(p, tmp_path / name / "pretrain.pt", tmp_path / name / "reports")

    def train(body_spec: str):
        settings = TrainSettings(body_model=body_spec)
        return _initial_network(settings, ckpt, load_body_model(body_spec))

    reuse(str(moved), "a")  # both files there: compared by content
    assert train(str(moved))[0] is not None
    other, _ = _body_at(tmp_path / "other/body.npz", seed=1)
    for refused in (lambda: reuse(other, "b"), lambda: train(other)):
        with pytest.raises(ValueError, match=r"trained with body model .*another body"):
            refused()
    (tmp_path / "old/body.npz").unlink()  # the old folder gone: a file of the same name is taken
    reuse(str(moved), "c")
    assert "not found here" in caplog.text
    assert train(str(moved))[0] is not None
    with pytest.raises(ValueError, match=r"cannot be loaded here to compare"):
        reuse(str(tmp_path / "new.npz"), "d")  # another name: not taken on trust


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda c: c["config"].pop("decoder"), r"config lacks 'decoder'"),
        (lambda c: c["config"].update(colour="red"), r"config .*unexpected keyword .*'colour'"),
        (lambda c: c["config"].update(vit=[1, 2]), r"config .*'vit'"),
    ],
)
def test_a_config_that_is_no_network_config_is_named(saved, tmp_path, change, message):
    """A config without 'decoder' was reported as "the checkpoint's weights do not fit its
    network ('decoder')": the weights blamed, the config's missing key a bare word."""
    path = _variant(saved, tmp_path, "config", change)
    with pytest.raises(ValueError, match=message) as info:
        network_from_checkpoint(load_checkpoint(path), path)
    assert str(path) in str(info.value) and "weights" not in str(info.value)

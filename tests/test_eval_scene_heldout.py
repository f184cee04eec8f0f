"""Which cameras `evaluate` scores as novel views: what the trained model recorded."""

from types import SimpleNamespace

import pytest

from gst.eval import scene
from gst.eval.split import check_unseen


def _setup(monkeypatch, extra):
    monkeypatch.setattr(scene, "load_checkpoint", lambda path: SimpleNamespace(extra=extra))
    crops = SimpleNamespace(camera_names=["a", "b", "c"], frame=None)
    return scene._heldout_setup(scene.EvaluateSettings(), {"gst": "model.pt"}, crops)


def test_a_model_that_held_out_no_camera_has_none_scored_as_held_out(monkeypatch):
    # before: [] read as "not recorded", and camera 'c', which the model trained on, was scored
    # as a novel view
    assert _setup(monkeypatch, {"heldout_cameras": [], "first_heldout_frame": 30}) == ([], 30, None)


def test_the_recorded_cameras_and_the_fallback(monkeypatch):
    assert _setup(monkeypatch, {"heldout_cameras": ["b"], "first_heldout_frame": 30}) == (
        ["b"],
        30,
        None,
    )
    assert _setup(monkeypatch, {"first_heldout_frame": -1}) == (["c"], None, None)


def test_held_out_cameras_or_frames_the_model_trained_on_are_refused(monkeypatch):
    """`evaluate.heldout_cameras` set by hand (or a bench `test_fraction` of its own) scored the
    trained model on a camera or frames it trained on, as if they were unseen."""
    trained = {"cameras": ["a", "b"], "frames": [0, 29], "scene": "demo"}
    extra = {"heldout_cameras": ["c"], "first_heldout_frame": 30, "trained_on": trained}
    monkeypatch.setattr(scene, "load_checkpoint", lambda path: SimpleNamespace(extra=extra))
    crops = SimpleNamespace(camera_names=["a", "b", "c"], frame=None)
    settings = scene.EvaluateSettings(heldout_cameras=["a"])
    with pytest.raises(ValueError, match=r"model.pt: held-out camera\(s\) \['a'\]"):
        scene._heldout_setup(settings, {"gst": "model.pt"}, crops)
    assert _setup(monkeypatch, extra) == (["c"], 30, None)  # the training's own split
    # the crop store it trained on, as recorded (bodycrops: cut from bodies fitted on every
    # camera and frame; evaluate's headline note says it is not clean)
    trained["crop_store"] = "bodycrops"
    assert _setup(monkeypatch, extra) == (["c"], 30, "bodycrops")
    with pytest.raises(ValueError, match="test frames from 20 include frames it trained on"):
        check_unseen(extra, ["c"], 20, "gst.pt")
    check_unseen({"trained_on": {"recorded": False}}, ["a"], 0, "old.pt")  # nothing to check


def test_a_render_size_without_lpips_need_only_hold_ssims_window():
    assert scene.EvaluateSettings(render_size=24, lpips=False).render_size == 24
    assert scene.EvaluateSettings(render_size=31).render_size == 31

"""Which cameras `evaluate` scores as novel views: what the trained model recorded."""

from types import SimpleNamespace

from gst.eval import scene


def _setup(monkeypatch, extra):
    monkeypatch.setattr(scene, "load_checkpoint", lambda path: SimpleNamespace(extra=extra))
    crops = SimpleNamespace(camera_names=["a", "b", "c"], frame=None)
    return scene._heldout_setup(scene.EvaluateSettings(), {"gst": "model.pt"}, crops)


def test_a_model_that_held_out_no_camera_has_none_scored_as_held_out(monkeypatch):
    # before: [] read as "not recorded", and camera 'c', which the model trained on, was scored
    # as a novel view
    assert _setup(monkeypatch, {"heldout_cameras": [], "first_heldout_frame": 30}) == ([], 30)


def test_the_recorded_cameras_and_the_fallback(monkeypatch):
    assert _setup(monkeypatch, {"heldout_cameras": ["b"], "first_heldout_frame": 30}) == (
        ["b"],
        30,
    )
    assert _setup(monkeypatch, {"first_heldout_frame": -1}) == (["c"], None)

"""The bench stage's split: landmarks projected from the rig (which carry the held-out camera's
evidence) are read again on every row, and the scene's trained model is scored beside the
variants on its own held-out cameras, or left out with a warning, never ending the sweep."""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import gst.eval.bench_scene as bs
from tests.test_train_recipe import crop_set


class _Stop(Exception):
    pass


def _stubbed(monkeypatch, tmp_path: Path, extra: dict | None):
    crops = crop_set(n_frames=8, n_cams=3)
    seen: dict = {}
    monkeypatch.setattr(bs, "load_cropset", lambda path: (crops, None))
    monkeypatch.setattr(bs, "attach_scene_truth", lambda c, b, s: None)

    def store_landmarks(path, images, reread=None, **kw):
        seen["reread"] = np.asarray(reread)
        return None, "stub"

    def stop(*args, **kwargs):
        raise _Stop  # everything the tests look at is decided before the first network

    monkeypatch.setattr(bs, "store_landmarks", store_landmarks)
    monkeypatch.setattr(
        bs, "load_checkpoint", lambda path: SimpleNamespace(extra=extra, body_model="x")
    )
    monkeypatch.setattr(bs, "load_body_model", lambda spec: None)
    monkeypatch.setattr(bs, "network_from_checkpoint", stop)
    models = tmp_path / "ws" / "models"
    models.mkdir(parents=True)
    if extra is not None:
        (models / "gst.pt").write_bytes(b"x")
    return crops, seen, models


def _run(p, models):
    with pytest.raises(_Stop):
        bs.bench_scene(p, Path("crops.h5"), Path("synth"), models / "pretrain.pt", Path("out"))


def test_every_row_reads_its_landmarks_again(monkeypatch, tmp_path):
    """Only the test rows were read again: training rows kept landmarks projected from the rig,
    triangulated with the held-out camera (train reads every row again for that reason)."""
    crops, seen, models = _stubbed(monkeypatch, tmp_path, None)
    _run(bs.BenchSettings(), models)
    assert seen["reread"].shape == (len(crops),) and seen["reread"].all()


def test_the_trained_models_held_out_cameras_are_the_default(monkeypatch, tmp_path):
    """train.heldout_cameras: [c0] made every `run bench` fail before any variant ran: bench
    held out the rig's last camera, which the model had trained on."""
    extra = {"heldout_cameras": ["c0"], "first_heldout_frame": 6,
             "trained_on": {"cameras": ["c1", "c2"], "frames": [0, 5]}}  # fmt: skip
    calls = []
    monkeypatch.setattr(bs, "frame_split", lambda c, h, f: calls.append(h) or _split(h))
    crops, seen, models = _stubbed(monkeypatch, tmp_path, extra)
    _run(bs.BenchSettings(), models)
    assert calls == [("c0",)]


def _split(heldout):
    return SimpleNamespace(heldout_cameras=tuple(heldout), test_frames=(6, 8), train_rows=None)


def test_a_trained_model_that_saw_the_test_frames_is_left_out_with_a_warning(
    monkeypatch, tmp_path, caplog
):
    """train.heldout_frames: 0 (every frame trained on): bench raised before any variant."""
    extra = {"heldout_cameras": ["c2"], "first_heldout_frame": -1,
             "trained_on": {"cameras": ["c0", "c1"], "frames": [0, 7]}}  # fmt: skip
    crops, seen, models = _stubbed(monkeypatch, tmp_path, extra)
    with caplog.at_level(logging.WARNING):
        _run(bs.BenchSettings(), models)
    assert "trained model is left out" in caplog.text and "include_trained=false" in caplog.text


def test_a_split_without_training_samples_is_refused_before_the_sweep(monkeypatch, tmp_path):
    """A two-camera scene with its last camera held out has one training camera, and the
    `pretrain` mode needs two: the sweep read every crop's landmarks and built the first
    variant, then fit_gst failed with "no training samples ... (held out: []; frames from
    None)", naming none of the bench's held-out cameras or frames."""
    crops, seen, models = _stubbed(monkeypatch, tmp_path, None)
    two = crop_set(n_frames=8, n_cams=2)
    monkeypatch.setattr(bs, "load_cropset", lambda path: (two, None))
    with pytest.raises(ValueError, match=r"held out \['c1'\].*or use mode 3d"):
        bs.bench_scene(
            bs.BenchSettings(), Path("c.h5"), Path("synth"), models / "pretrain.pt", Path("o")
        )
    assert "reread" not in seen  # refused before the landmarks were read
    _run(bs.BenchSettings(mode="3d"), models)  # single views: c0 trains


def test_the_header_names_the_rows_taken_as_they_are(monkeypatch, tmp_path):
    """table.md said "Every variant except `pretrained` was trained from scratch" above a
    `trained (models/gst.pt)` row taken as it is, and described `trained` when it was not in
    the table."""
    extra = {"heldout_cameras": ["c2"], "first_heldout_frame": 6,
             "trained_on": {"cameras": ["c0", "c1"], "frames": [0, 5]}}  # fmt: skip
    crops, seen, models = _stubbed(monkeypatch, tmp_path, extra)
    cfg = SimpleNamespace(name="tiny", image_size=(64, 48), landmark_tokens=False)
    monkeypatch.setattr(bs, "network_from_checkpoint", lambda c, p: SimpleNamespace(cfg=cfg))
    monkeypatch.setattr(bs, "run_bench", lambda variants, *a, **k: [])
    monkeypatch.setattr(bs, "write_pareto_plot", lambda *a: None)
    headers = []
    monkeypatch.setattr(bs, "write_bench_table", lambda out, rows, header: headers.append(header))
    out = tmp_path / "out"
    bs.bench_scene(bs.BenchSettings(), Path("c.h5"), Path("s"), models / "pretrain.pt", out)
    assert "except `pretrained` and `trained (models/gst.pt)` (taken as they are)" in headers[0]
    bs.bench_scene(
        bs.BenchSettings(include_trained=False), Path("c.h5"), Path("s"), models / "p.pt", out
    )
    assert "except `pretrained` (taken" in headers[1] and "gst.pt" not in headers[1]

"""The whole DAG on a tiny synthetic scene: every stage runs through the CLI and writes what
the README promises (numbers are meaningless at this size; the stages' own tests check them)."""

from __future__ import annotations

import shutil
import textwrap

import numpy as np
import pytest
import torch

from gst.metrics.lpips_weights import default_weights_path
from gst.track import read_tracks
from pipeline.cli import main
from tests.tiny_config import TINY_CONFIG

pytestmark = pytest.mark.skipif(
    not default_weights_path("alex").is_file(),
    reason="LPIPS weights missing: run `python -m gst.metrics.lpips fetch`",
)


def test_tiny_scene_runs_every_stage(tmp_path, capsys):
    cfg = tmp_path / "pipeline.yaml"
    cfg.write_text(
        textwrap.dedent(TINY_CONFIG)
        + "  track: {needs: [train], params: {overlay: false}}\n"
        + "  evaluate: {needs: [train], params: {max_groups: 4, render_size: 32}}\n"
    )
    assert main(["run", "all", "--config", str(cfg), "--quiet"]) == 0, capsys.readouterr().err
    ws = tmp_path / "ws" / "tiny"
    for rel in (
        "calibration/rig.json",
        "crops/crops.h5",
        "fused/bodies.parquet",
        "bodycrops/crops.h5",
        "reports/bodycrops/summary.json",
        "models/pretrain.pt",
        "models/gst.pt",
        "models/example.ply",
        "reports/train/summary.md",
        "reports/train/novel_views.png",
        "reports/pretrain/log.csv",
    ):
        assert (ws / rel).is_file(), rel
    tables = [read_tracks(p) for p in sorted((ws / "tracks").glob("video=*/tracks.parquet"))]
    assert len(tables) == 3
    rows = sum(t.num_rows for t in tables)
    assert rows > 0
    joints = np.stack(tables[0].column("joints3d").to_numpy(zero_copy_only=False))
    assert np.isfinite(joints).all()
    capsys.readouterr()
    assert main(["status", "--config", str(cfg)]) == 0
    status = capsys.readouterr().err
    assert "stale" not in status and "missing" not in status
    assert (ws / "reports/evaluate/summary.json").is_file()
    # A forced rerun of extract on unchanged inputs writes identical crops (its report's
    # timings are no input): everything downstream stays up to date.
    assert main(["run", "extract", "--config", str(cfg), "--quiet", "--force"]) == 0
    capsys.readouterr()
    assert main(["status", "--config", str(cfg)]) == 0
    status = capsys.readouterr().err
    assert "stale" not in status and "missing" not in status, status
    # A workspace copied to another path is still up to date, and its tracks read back.
    shutil.copytree(tmp_path / "ws", tmp_path / "moved")
    moved = tmp_path / "moved.yaml"
    moved.write_text(cfg.read_text().replace("workspace: ws", "workspace: moved"))
    assert main(["status", "--config", str(moved)]) == 0
    status = capsys.readouterr().err
    assert "stale" not in status and "missing" not in status, status
    copied = sorted((tmp_path / "moved/tiny/tracks").glob("video=*/tracks.parquet"))
    assert sum(read_tracks(p).num_rows for p in copied) == rows
    # the paper's 3D fine-tuning baseline through the same stage (synthetic truth)
    assert (
        main(["run", "train", "--config", str(cfg), "--quiet", "--set", "train.supervision=3d"])
        == 0
    )
    assert (ws / "models/gst.pt").is_file()
    # kept models hold the network, not the training loop's optimiser state (3x the file)
    for kept in ("models/pretrain.pt", "models/gst.pt"):
        assert "trainer" not in torch.load(ws / kept, weights_only=True), kept

"""The calibrate stage through the CLI: import a real calibration, refuse bad ones."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest

from calibration import Camera, Rig
from calibration.formats import read_rig, write_rig
from pipeline.cli import main

REPO = Path(__file__).resolve().parents[1]
LAB = REPO.parent / "shared" / "real" / "pose2sim-multiperson"
needs_lab = pytest.mark.skipif(
    not (LAB / "Calib.qca.txt").is_file(), reason=f"real lab capture not found at {LAB}"
)


def config(tmp_path: Path, calib: Path, fmt: str, videos: str) -> Path:
    cfg = tmp_path / "pipeline.yaml"
    cfg.write_text(
        textwrap.dedent(f"""
        workspace: ws
        scenes:
          lab: {{videos: "{videos}", calibration: {{file: "{calib}", format: {fmt}}}}}
        stages:
          calibrate: {{}}
    """)
    )
    return cfg


@needs_lab
def test_imports_real_qualisys_calibration(tmp_path):
    cfg = config(tmp_path, LAB / "Calib.qca.txt", "qualisys", str(LAB / "cam*.mp4"))
    assert main(["run", "calibrate", "--config", str(cfg), "--quiet"]) == 0
    rig = read_rig(tmp_path / "ws/lab/calibration/rig.json", "rig")
    assert rig.names == ["cam01", "cam02", "cam03", "cam04"]
    assert all(c.center[2] > 1.0 for c in rig)
    assert (tmp_path / "ws/lab/reports/calibrate/camera_poses.png").stat().st_size > 10_000
    assert (tmp_path / "ws/lab/reports/calibrate/overlay_cam01.png").is_file()


@needs_lab
def test_nan_calibration_fails_and_writes_nothing(tmp_path, capsys):
    write_rig(read_rig(LAB / "Calib.qca.txt", "qualisys"), tmp_path / "good.json", "rig")
    bad = json.loads((tmp_path / "good.json").read_text())
    bad["cameras"][1]["K"][0][0] = float("nan")
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    cfg = config(tmp_path, tmp_path / "bad.json", "rig", str(LAB / "cam*.mp4"))
    assert main(["run", "calibrate", "--config", str(cfg), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "calibrate" in err and "cam02" in err
    assert not (tmp_path / "ws/lab/calibration").exists()


@needs_lab
def test_video_without_camera_is_named(tmp_path, capsys):
    rig = read_rig(LAB / "Calib.qca.txt", "qualisys")
    write_rig(rig.subset(["cam01", "cam02", "cam03"]), tmp_path / "three.json", "rig")
    cfg = config(tmp_path, tmp_path / "three.json", "rig", str(LAB / "cam*.mp4"))
    assert main(["run", "calibrate", "--config", str(cfg)]) == 1  # not quiet: the console
    err = capsys.readouterr().err
    assert "cam04" in err and "leave the videos out of scenes.lab.videos" in err
    assert "Traceback" not in err  # an input error: one line (the traceback is in the log)
    assert not (tmp_path / "ws/lab/calibration").exists()


@needs_lab
def test_a_camera_without_video_is_said(tmp_path):
    """cam04 left out of the scene's videos: the rig kept it and extraction split the man into
    two ids, without a word."""
    cfg = config(tmp_path, LAB / "Calib.qca.txt", "qualisys", str(LAB / "cam0[123].mp4"))
    assert main(["run", "calibrate", "--config", str(cfg), "--quiet"]) == 0
    (log,) = (tmp_path / "ws" / ".pipeline" / "logs").glob("*-run.log")
    assert "cameras ['cam04'] have no video in the scene" in log.read_text()


def test_rig_below_floor_is_refused(tmp_path, capsys):
    R = np.diag([1.0, -1.0, -1.0])  # looking straight down from z = -2 (below the floor)
    cams = [
        Camera.create(
            f"c{i}",
            [[500, 0, 320], [0, 500, 240], [0, 0, 1]],
            [],
            R,
            -R @ np.array([i, 0, -2.0]),
            640,
            480,
        )
        for i in range(3)
    ]
    write_rig(Rig(tuple(cams)), tmp_path / "low.json", "rig")
    videos = tmp_path / "videos"
    videos.mkdir()
    for i in range(3):  # the rig is refused before its videos are read: any file will do
        (videos / f"c{i}.mp4").write_bytes(b"")
    cfg = config(tmp_path, tmp_path / "low.json", "rig", str(videos / "c*.mp4"))
    assert main(["run", "calibrate", "--config", str(cfg), "--quiet"]) == 1
    assert "below the floor" in capsys.readouterr().err

"""Multi-camera footage whose cameras disagree (frame rates, frame counts), through the real CLI
and `calibrate_scene`: a clear error that names the cameras and says what was expected, before
the heavy work, or a logged handling. (Bad files, sizes and config mistakes:
test_bad_input_corpus.py.)"""

from __future__ import annotations

import logging
import re
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.formats import write_rig
from pipeline.cli import main
from tests.test_bad_input_corpus import CAMERAS, H, W, _rig


def _video(path: Path, frames: int = 12, fps: float = 10.0) -> Path:
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (W, H))
    for k in range(frames):
        img = np.full((H, W, 3), 40, np.uint8)
        cv2.rectangle(img, (10 + 4 * k, 30), (40 + 4 * k, 90), (200, 180, 160), -1)
        out.write(img)
    out.release()
    return path


def _run(tmp: Path, capsys, videos: dict[str, dict], extra_scene: str = "") -> tuple[int, str]:
    folder = tmp / "videos"
    folder.mkdir()
    for name, kw in videos.items():
        _video(folder / f"{name}.mp4", **kw)
    write_rig(_rig(), tmp / "rig.json", "rig")
    cfg = tmp / "cfg.yaml"
    cfg.write_text(
        textwrap.dedent(f"""
        workspace: {tmp}/ws
        executor: {{kind: local, workers: 1}}
        scenes:
          s:
            videos: {folder}/c*.mp4
            calibration: {{file: {tmp}/rig.json, format: rig}}
            {extra_scene}
        stages:
          calibrate: {{}}
          extract: {{needs: [calibrate], params: {{crop_size: 64}}}}
        """)
    )
    code = main(["run", "extract", "--config", str(cfg), "--quiet"])
    printed = capsys.readouterr()
    return code, printed.out + printed.err


def test_cameras_at_different_rates_are_named_as_such(tmp_path, capsys):
    """A 50 frames/s camera among 60 frames/s ones, over the same span: the error said only
    "different frame counts ... expected synchronised videos of equal length", and a user who
    trimmed the videos to one length met the rates next (here 10 and 8.33 frames/s)."""
    code, err = _run(tmp_path, capsys, {"c1": {}, "c2": {"frames": 10, "fps": 50 / 6}, "c3": {}})
    assert code == 1, err
    assert "different frame counts" in err
    assert re.search(r"different frame rates \(c1: 10 .*c2: 8\.33", err), err


def test_a_scene_rate_over_headers_that_disagree_is_logged(tmp_path, capsys, caplog):
    """`scenes.NAME.fps` times every camera at one rate; where the headers disagree (one camera
    at 12 frames/s, the others at 10) frame i of every camera was taken for one instant without
    a word."""
    with caplog.at_level(logging.WARNING, logger="gst"):
        code, err = _run(
            tmp_path, capsys, {"c1": {}, "c2": {"fps": 12.0}, "c3": {}}, extra_scene="fps: 10"
        )
    assert code == 0, err
    said = err + caplog.text
    assert re.search(r"c2: 12.*scenes\.s\.fps|scene's 10 frames/s", said), said


def test_board_footage_at_different_rates_is_refused_before_detection(tmp_path):
    """Board clips are paired across cameras by frame index: a camera at another rate paired
    views of different instants; the solve ended in "focal lengths must be positive" for that
    camera (or a wrong rig), after detection and bundle adjustment."""
    from calibration.board import BoardSpec
    from calibration.scene import BoardFootage, calibrate_scene

    clips = {n: _video(tmp_path / f"{n}.mp4", fps=12.0 if n == "c2" else 10.0) for n in CAMERAS}
    board = BoardSpec("charuco", 5, 4, 0.1, 0.07, "DICT_5X5_100")
    with pytest.raises(ValueError, match=r"board videos have different frame rates \(.*c2: 12 "):
        calibrate_scene(
            {}, tmp_path / "rig.json", tmp_path / "rep", footage=BoardFootage(clips, board)
        )

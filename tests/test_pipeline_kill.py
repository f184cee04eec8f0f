"""A killed multi-worker run leaves no orphans, and the next run takes the lock over at once."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (dead, not yet reaped by its parent) does not count as running
    stat = Path(f"/proc/{pid}/stat")
    return not (stat.is_file() and stat.read_text().split(") ")[-1].startswith("Z"))


def _fanout_run(
    tmp_path: Path, workers: int, stderr=None
) -> tuple[Path, list[str], subprocess.Popen]:
    """`run fanout` started in its own process (its items sleep 60 s, each writing its pid in
    tmp_path/markers first): the config, the command and the process."""
    markers = tmp_path / "markers"
    markers.mkdir()
    cfg = tmp_path / "pipeline.yaml"
    cfg.write_text(
        textwrap.dedent(f"""
        workspace: ws
        executor: {{kind: local, workers: {workers}}}
        scenes: {{demo: {{synthetic: {{preset: demo}}}}}}
        stages:
          fanout: {{module: "tests.fake_stages:FANOUT",
                   params: {{seconds: 60, marker_dir: "{markers}"}}}}
        """)
    )
    cmd = [sys.executable, "-m", "pipeline", "run", "fanout", "--config", str(cfg), "--quiet"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return cfg, cmd, subprocess.Popen(cmd, cwd=REPO, env=env, stderr=stderr, text=True)


def test_kill_9_of_a_fanned_out_run_leaves_no_worker_and_a_rerun_succeeds(tmp_path):
    cfg, cmd, run = _fanout_run(tmp_path, workers=2)
    markers = tmp_path / "markers"
    deadline = time.time() + 120
    while len(list(markers.glob("worker-*.pid"))) < 2:
        assert time.time() < deadline, "the workers never started"
        assert run.poll() is None, "the run ended early"
        time.sleep(0.2)
    workers = [int(p.read_text()) for p in markers.glob("worker-*.pid")]
    os.kill(run.pid, signal.SIGKILL)
    run.wait()
    time.sleep(2)
    assert [pid for pid in workers if _alive(pid)] == []

    rerun = subprocess.run(
        [*cmd[:-1], "--set", "fanout.seconds=0", "--set", "fanout.marker_dir="],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert rerun.returncode == 0, rerun.stderr
    assert (tmp_path / "ws/demo/fanout/done.txt").read_text() == "0,1"


def test_sigterm_stops_a_run_as_ctrl_c_does(tmp_path, capsys):
    """`kill` (or a scheduler's time limit) printed a 40-line native stack dump from pycolmap's
    logging library, as a crash would. It now ends the run as Ctrl-C does: one line, exit 143,
    the workers gone, the stage recorded as interrupted."""
    from pipeline.cli import main

    cfg, _, run = _fanout_run(tmp_path, workers=2, stderr=subprocess.PIPE)
    markers = tmp_path / "markers"
    deadline = time.time() + 120
    while len(list(markers.glob("worker-*.pid"))) < 2:
        assert time.time() < deadline and run.poll() is None, "the workers never started"
        time.sleep(0.2)
    workers = [int(p.read_text()) for p in markers.glob("worker-*.pid")]
    run.terminate()
    err = run.communicate(timeout=60)[1]
    assert run.returncode == 143, err
    assert "terminated (SIGTERM)" in err and "stack trace" not in err and "Aborted" not in err
    time.sleep(2)
    assert [pid for pid in workers if _alive(pid)] == []
    capsys.readouterr()
    assert main(["status", "--config", str(cfg)]) == 0
    assert "a previous run was interrupted" in capsys.readouterr().out.replace("\n", " ")


def test_status_during_a_run_says_it_is_running_not_interrupted(tmp_path, capsys):
    """`status` in a second shell while a stage ran said 'a previous run was interrupted'."""
    from pipeline.cli import main

    cfg, _, run = _fanout_run(tmp_path, workers=1)
    markers = tmp_path / "markers"
    try:
        deadline = time.time() + 120
        while not list(markers.glob("worker-*.pid")):
            assert time.time() < deadline and run.poll() is None, "the stage never started"
            time.sleep(0.2)
        capsys.readouterr()
        assert main(["status", "--config", str(cfg)]) == 0
        table = capsys.readouterr().out.replace("\n", " ")
        assert "being written by the run now in progress" in table
        assert str(run.pid) in table and "interrupted" not in table
    finally:
        os.kill(run.pid, signal.SIGKILL)
        run.wait()
    capsys.readouterr()
    assert main(["status", "--config", str(cfg)]) == 0
    assert "a previous run was interrupted" in capsys.readouterr().out.replace("\n", " ")


@pytest.mark.slow  # tracks 2 x 900 frames three times (about 20 s on 2 idle cores)
def test_kill_9_of_a_two_worker_track_run_then_rerun_gives_identical_tracks(tmp_path):
    """The acceptance case: `run track --workers 2` killed mid-run; no process of it is alive
    2 s later, and an immediate rerun writes the same Parquet as an uninterrupted run."""
    from calibration.formats import write_rig
    from gst.body import BodyModel
    from gst.body.random_model import random_body_data
    from gst.model.checkpoint import save_checkpoint
    from gst.model.presets import get_preset
    from gst.train.recipe import build_network
    from tests.test_bad_input_corpus import _rig, _video

    videos = tmp_path / "videos"
    videos.mkdir()
    for name in ("c1", "c2"):
        # long enough that the kill lands mid-run: on an idle machine 150 frames took 0.3 s,
        # less than the time between the first committed rows and the end of the run
        _video(videos / f"{name}.mp4", frames=900)
    write_rig(_rig(), tmp_path / "rig.json", "rig")
    data = random_body_data(num_vertices=400, with_posedirs=False)
    body = data.save_npz(tmp_path / "body.npz")
    net, ids, groups = build_network(get_preset("tiny", vertex_preset="full"), BodyModel(data))

    def config(ws: str) -> Path:
        cfg = tmp_path / f"{ws}.yaml"
        cfg.write_text(
            textwrap.dedent(f"""
            workspace: {ws}
            executor: {{kind: local, workers: 2}}
            scenes:
              s: {{videos: {videos}/c*.mp4, calibration: {{file: {tmp_path}/rig.json}}}}
            stages:
              track: {{params: {{detector: background, overlay: false, batch_size: 4}}}}
            """)
        )
        (tmp_path / ws / "s/models").mkdir(parents=True)
        save_checkpoint(tmp_path / ws / "s/models/gst.pt", net, str(body), ids, groups)
        return cfg

    env = {**os.environ, "PYTHONPATH": str(REPO)}

    def cli(cfg: Path) -> list[str]:
        return [sys.executable, "-m", "pipeline", "run", "track", "--config", str(cfg), "--quiet"]

    ref = subprocess.run(cli(config("ref")), cwd=REPO, env=env, capture_output=True, text=True)
    assert ref.returncode == 0, ref.stderr
    cfg = config("ws")
    run = subprocess.Popen(cli(cfg), cwd=REPO, env=env, start_new_session=False)
    staging = tmp_path / "ws/s/.pipeline/staging/track"
    deadline = time.time() + 300
    while not list(staging.rglob("seg-*.parquet")):  # a worker has committed rows
        assert time.time() < deadline and run.poll() is None, "no rows committed in time"
        time.sleep(0.02)
    children = [
        int(p) for p in Path(f"/proc/{run.pid}/task/{run.pid}/children").read_text().split()
    ]
    os.kill(run.pid, signal.SIGKILL)
    run.wait()
    time.sleep(2)
    assert [pid for pid in children if _alive(pid)] == []
    again = subprocess.run(cli(cfg), cwd=REPO, env=env, capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    for name in ("c1", "c2"):
        rel = f"s/tracks/video={name}/tracks.parquet"
        assert (tmp_path / "ws" / rel).read_bytes() == (tmp_path / "ref" / rel).read_bytes()

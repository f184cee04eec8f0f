"""A killed multi-worker run leaves no orphans, and the next run takes the lock over at once."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (dead, not yet reaped by its parent) does not count as running
    stat = Path(f"/proc/{pid}/stat")
    return not (stat.is_file() and stat.read_text().split(") ")[-1].startswith("Z"))


def test_kill_9_of_a_fanned_out_run_leaves_no_worker_and_a_rerun_succeeds(tmp_path):
    markers = tmp_path / "markers"
    markers.mkdir()
    cfg = tmp_path / "pipeline.yaml"
    cfg.write_text(
        textwrap.dedent(f"""
        workspace: ws
        executor: {{kind: local, workers: 2}}
        scenes: {{demo: {{synthetic: {{preset: demo}}}}}}
        stages:
          fanout: {{module: "tests.fake_stages:FANOUT", params: {{seconds: 60, marker_dir: "{markers}"}}}}
        """)
    )
    cmd = [sys.executable, "-m", "pipeline", "run", "fanout", "--config", str(cfg), "--quiet"]
    run = subprocess.Popen(cmd, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
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

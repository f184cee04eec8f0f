"""`torchrun --nproc_per_node 2 -m pipeline run train` on CPU (gloo): both ranks train, rank 0
alone commits the stage's outputs and its record (slow: it builds a tiny workspace first)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from gst.metrics.lpips_weights import default_weights_path
from tests.tiny_config import TINY_CONFIG

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        not default_weights_path("alex").is_file(),
        reason="LPIPS weights missing: run `python -m gst.metrics.lpips fetch`",
    ),
]
REPO = Path(__file__).resolve().parents[1]
CONFIG = TINY_CONFIG


def _run(args, cwd):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=900)


def test_torchrun_two_cpu_ranks_train_and_rank0_commits(tmp_path):
    (tmp_path / "pipeline.yaml").write_text(textwrap.dedent(CONFIG))
    torchrun = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc_per_node",
        "2",
        "-m",
        "pipeline",
        "run",
        "train",
        "--set",
        "train.steps=4",
    ]
    early = _run(torchrun, tmp_path)
    assert early.returncode != 0 and "upstream stages must be up to date" in early.stderr
    for stage in ("extract", "fuse", "pretrain"):
        done = _run([sys.executable, "-m", "pipeline", "run", stage, "--quiet"], tmp_path)
        assert done.returncode == 0, done.stderr
    res = _run(torchrun, tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "[rank1]" in res.stderr  # the second rank really joined the DDP group
    # the landmark prior is rehearsed beside the DDP steps (its own backward outside the sync)
    assert "rehearsing the landmark prior" in res.stderr
    ws = tmp_path / "ws" / "tiny"
    assert (ws / "models" / "gst.pt").is_file() and (ws / "reports" / "train").is_dir()
    assert not (ws / ".pipeline" / "staging").exists() or not any(
        (ws / ".pipeline" / "staging").iterdir()
    )
    status = _run([sys.executable, "-m", "pipeline", "status", "--set", "train.steps=4"], tmp_path)
    assert (
        "train" in status.stderr and "stale" not in status.stderr and "missing" not in status.stderr
    )

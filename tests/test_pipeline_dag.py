"""The DAG runner: ordering, skipping, reruns on real changes only, atomicity, errors."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from pipeline.cli import main
from pipeline.dag import topological_order, upstream_closure
from pipeline.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]


def write_config(tmp_path: Path, extra_params: str = "", input_file: Path | None = None) -> Path:
    src_params = f"input_file: {input_file}" if input_file else ""
    cfg = tmp_path / "pipeline.yaml"
    cfg.write_text(
        textwrap.dedent(f"""
        workspace: ws
        default_scene: demo
        executor: {{kind: local, workers: 1}}
        scenes:
          demo: {{synthetic: {{preset: demo}}}}
        stages:
          source: {{module: "tests.fake_stages:SOURCE", params: {{{src_params}}}}}
          double: {{module: "tests.fake_stages:DOUBLE", needs: [source],
                   params: {{{extra_params}}}}}
          report: {{module: "tests.fake_stages:REPORT", needs: [double]}}
    """)
    )
    return cfg


def run(cfg: Path, *args: str) -> int:
    return main([*args[:2], "--config", str(cfg), "--quiet", *args[2:]])


def test_topological_order_respects_needs_and_declaration_order():
    needs = {
        "train": ["extract", "pretrain"],
        "pretrain": [],
        "extract": ["calibrate"],
        "calibrate": [],
    }
    order = topological_order(needs)
    assert order.index("calibrate") < order.index("extract") < order.index("train")
    assert order.index("pretrain") < order.index("train")
    assert upstream_closure(needs, ["extract"]) == ["calibrate", "extract"]


def test_cycle_is_a_config_error():
    with pytest.raises(ConfigError, match="cycle"):
        topological_order({"a": ["b"], "b": ["a"]})


def test_a_stage_that_sets_torch_threads_does_not_set_them_for_the_next(tmp_path):
    """torch's thread count is process-wide: the stages after one that changes it (in one `run`)
    see it as it was, so their results do not depend on what ran before them."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        cfg = write_config(tmp_path, input_file=None)
        cfg.write_text(cfg.read_text().replace("params: {}}", "params: {torch_threads: 1}}", 1))
        assert "torch_threads: 1" in cfg.read_text()
        assert run(cfg, "run", "report") == 0
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_runs_in_order_then_skips_when_up_to_date(tmp_path, counter):
    cfg = write_config(tmp_path)
    assert run(cfg, "run", "report") == 0
    assert counter() == ["source", "double", "report"]
    assert (tmp_path / "ws/demo/reports/summary.txt").read_text() == str(len("value=1\n") * 2)
    assert run(cfg, "run", "report") == 0
    assert counter() == ["source", "double", "report"]  # nothing reran


def test_param_change_reruns_stage_and_downstream_only(tmp_path, counter):
    cfg = write_config(tmp_path)
    assert run(cfg, "run", "all") == 0
    assert run(cfg, "run", "all", "--set", "double.factor=3") == 0
    assert counter() == ["source", "double", "report", "double", "report"]


def test_input_content_change_reruns_but_touch_does_not(tmp_path, counter):
    data = tmp_path / "input.txt"
    data.write_text("hello\n")
    cfg = write_config(tmp_path, input_file=data)
    assert run(cfg, "run", "all") == 0
    time.sleep(0.01)
    os.utime(data)  # a bare touch: same content, new mtime
    assert run(cfg, "run", "all") == 0
    assert counter() == ["source", "double", "report"]
    data.write_text("changed\n")
    assert run(cfg, "run", "all") == 0
    assert counter() == ["source", "double", "report"] * 2


def test_identical_upstream_output_does_not_rerun_downstream(tmp_path, counter):
    cfg = write_config(tmp_path)
    assert run(cfg, "run", "all") == 0
    assert run(cfg, "run", "source", "--force") == 0  # same output content
    assert run(cfg, "run", "all") == 0
    assert counter() == ["source", "double", "report", "source"]


def test_force_reruns_target_and_force_all_everything(tmp_path, counter):
    cfg = write_config(tmp_path)
    assert run(cfg, "run", "all") == 0
    assert run(cfg, "run", "double", "--force") == 0
    assert counter()[3:] == ["double"]
    assert run(cfg, "run", "report", "--force-all") == 0
    assert counter()[4:] == ["source", "double", "report"]


def test_dry_run_runs_nothing(tmp_path, counter, capsys):
    cfg = write_config(tmp_path)
    assert main(["run", "all", "--config", str(cfg), "--dry-run"]) == 0
    assert counter() == []
    assert not (tmp_path / "ws/demo/source").exists()
    assert "never run" in capsys.readouterr().out  # the plan is the command's output


def test_dry_run_and_status_write_nothing(tmp_path, counter, capsys):
    """A dry run saved the hash cache: on a workspace that never ran it made the workspace
    folder, and after a touch of an input it rewrote the cache. `status` of a never-run
    workspace made the folder too (it may keep its cache in a workspace that is there)."""
    data = tmp_path / "input.txt"
    data.write_text("hello\n")
    cfg = write_config(tmp_path, input_file=data)
    assert main(["run", "all", "--config", str(cfg), "--dry-run", "-q"]) == 0
    assert main(["status", "--config", str(cfg), "-q"]) == 0
    assert not (tmp_path / "ws").exists()
    assert run(cfg, "run", "all") == 0
    cache = tmp_path / "ws/.pipeline/hashcache.json"
    before = cache.read_bytes()
    time.sleep(0.01)
    os.utime(data)  # re-hashed: a run or `status` would save the new entry
    assert main(["run", "all", "--config", str(cfg), "--dry-run", "-q"]) == 0
    assert cache.read_bytes() == before
    assert counter() == ["source", "double", "report"]


def test_status_reports_reason(tmp_path, capsys):
    cfg = write_config(tmp_path)
    assert run(cfg, "run", "all") == 0
    capsys.readouterr()
    assert main(["status", "--config", str(cfg), "--set", "double.factor=5"]) == 0
    out = capsys.readouterr().out
    assert "factor: 2 -> 5" in out
    assert "upstream double will run first" in out


def test_killed_stage_is_missing_and_reruns(tmp_path, counter):
    cfg = write_config(tmp_path, extra_params="die_after_partial_write: true")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run(
        [sys.executable, "-m", "pipeline", "run", "double", "--config", str(cfg), "--quiet"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
    )
    assert proc.returncode == -9, proc.stderr  # SIGKILL while writing its output
    assert not (tmp_path / "ws/demo/double").exists()  # nothing half-written in the workspace
    capture = subprocess.run(
        [sys.executable, "-m", "pipeline", "status", "--config", str(cfg)],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
    )
    assert "interrupted" in capture.stdout + capture.stderr
    assert run(cfg, "run", "all", "--set", "double.die_after_partial_write=false") == 0
    assert (tmp_path / "ws/demo/double/result.txt").read_text() == "value=1\n" * 2


def test_failed_stage_exit_1_keeps_previous_outputs(tmp_path, capsys):
    cfg = write_config(tmp_path)
    with open(cfg, "a") as f:
        f.write('  fail: {module: "tests.fake_stages:FAIL", needs: [source]}\n')
    assert run(cfg, "run", "fail") == 1
    err = capsys.readouterr().err
    assert "stage 'fail'" in err and "boom" in err
    assert not (tmp_path / "ws/demo/fail").exists()
    # `status` says it failed and why (it said "a previous run was interrupted")
    assert main(["status", "--config", str(cfg)]) == 0
    table = " ".join(capsys.readouterr().out.split())
    assert "its last run failed" in table and "boom" in table and "interrupted" not in table


def test_a_stage_that_writes_no_declared_output_is_said_to_have_failed(tmp_path, capsys):
    """A stage that returned without its declared outputs failed the run, and `status` then
    said "a previous run was interrupted" instead of the error it stopped on."""
    cfg = write_config(tmp_path)
    with open(cfg, "a") as f:
        f.write('  nothing: {module: "tests.fake_stages:NO_OUTPUT", needs: [source]}\n')
    assert run(cfg, "run", "nothing") == 1
    assert "did not write its declared outputs" in capsys.readouterr().err
    assert main(["status", "--config", str(cfg)]) == 0
    table = " ".join(capsys.readouterr().out.split())
    assert "its last run failed" in table and "interrupted" not in table


@pytest.mark.parametrize("bad_input", [True, False])
def test_bad_input_fails_with_its_message_and_a_bug_with_its_traceback(tmp_path, capsys, bad_input):
    """A corrupt video printed a traceback of the stage's internals above the line that says
    what is wrong. The traceback of an input error now goes to the run's log file only; an
    error that is no input's (a bug) keeps it on the console, for the report."""
    cfg = write_config(tmp_path)
    with open(cfg, "a") as f:
        f.write('  fail: {module: "tests.fake_stages:FAIL", needs: [source]}\n')
    args = ["run", "fail", "--config", str(cfg), "--set", f"fail.bad_input={bad_input}"]
    assert main(args) == 1
    err = capsys.readouterr().err
    kind = "VideoError" if bad_input else "RuntimeError"
    assert f"failed: {kind}: boom" in err
    assert ("Traceback" in err) is not bad_input
    (log_file,) = (tmp_path / "ws" / ".pipeline" / "logs").glob("*-run.log")
    assert "Traceback" in log_file.read_text() and f"{kind}: boom" in log_file.read_text()
    # ... and the console names that file (only a run that succeeded did)
    assert f"log (with the traceback): {log_file}" in " ".join(err.split())


@pytest.mark.parametrize(
    "text, expected",
    [
        ("scenes: [oops", "not valid YAML"),
        ("scenes: {demo: {synthetic: {preset: demo}}}\nstagez: {}\n", "stagez: unknown key"),
        ("scenes: {demo: {synthetic: {preset: demo}, videos: a.mp4}}\n", "exactly one of"),
        (
            "scenes: {demo: {synthetic: {preset: demo}}}\nstages: {a: {needs: [b]}}\n",
            "unknown stage 'b'",
        ),
        ("scenes: {demo: {synthetic: {sed: 1}}}\n", "scenes.demo.synthetic.sed: unknown key"),
    ],
)
def test_bad_config_exit_2_names_key_and_writes_nothing(tmp_path, capsys, text, expected):
    cfg = tmp_path / "pipeline.yaml"
    cfg.write_text(text)
    assert main(["run", "all", "--config", str(cfg)]) == 2
    assert expected in capsys.readouterr().err
    assert not (tmp_path / "workspace").exists()


def test_unknown_stage_param_exit_2(tmp_path, capsys):
    cfg = write_config(tmp_path, extra_params="facter: 3")
    assert run(cfg, "run", "all") == 2
    assert "stages.double.params.facter: unknown key" in capsys.readouterr().err
    assert not (tmp_path / "ws").exists()


def test_bad_override_and_unknown_stage_exit_2(tmp_path, capsys):
    cfg = write_config(tmp_path)
    assert run(cfg, "run", "all", "--set", "nokey") == 2
    assert run(cfg, "run", "all", "--set", "nostage.x=1") == 2
    assert run(cfg, "run", "nostage") == 2
    err = capsys.readouterr().err
    assert (
        "expected KEY=VALUE" in err
        and "'nostage' is neither a stage" in err
        and "unknown stage 'nostage'" in err
    )


def test_scene_config_change_reruns(tmp_path, counter, capsys):
    cfg = write_config(tmp_path)
    assert run(cfg, "run", "all") == 0
    cfg.write_text(cfg.read_text().replace("preset: demo", "preset: demo, seed: 3"))
    capsys.readouterr()
    assert main(["status", "--config", str(cfg)]) == 0
    assert "scene synthetic.seed: 0 -> 3" in capsys.readouterr().out
    assert run(cfg, "run", "all") == 0
    assert counter() == ["source", "double", "report"] * 2


def test_scene_params_apply_to_that_scene_only_and_set_wins(tmp_path, counter, capsys):
    cfg = write_config(tmp_path)
    cfg.write_text(
        cfg.read_text().replace(
            "demo: {synthetic: {preset: demo}}",
            "demo: {synthetic: {preset: demo}}\n  other: "
            "{synthetic: {preset: demo}, params: {double: {factor: 3}}}",
        )
    )
    assert run(cfg, "run", "all") == 0
    assert run(cfg, "run", "all", "--scene", "other") == 0
    ws = tmp_path / "ws"
    demo, other = (
        (ws / "demo" / "double" / "result.txt").read_text(),
        (ws / "other" / "double" / "result.txt").read_text(),
    )
    assert len(other) == len(demo) * 3 // 2  # factor 3 there, the default 2 here
    # Changing the scene's own params reruns that scene's `double` (and downstream), not `source`.
    cfg.write_text(cfg.read_text().replace("factor: 3", "factor: 4"))
    before = len(counter())
    assert run(cfg, "run", "all", "--scene", "other") == 0
    assert counter()[before:] == ["double", "report"]
    # --set on the stage wins over the scene's value.
    assert run(cfg, "run", "all", "--scene", "other", "--set", "double.factor=2") == 0
    assert (ws / "other" / "double" / "result.txt").read_text() == demo


@pytest.mark.parametrize(
    "scene_params,expected",
    [
        ("{tripple: {factor: 3}}", "scenes.demo.params: unknown stage 'tripple'"),
        ("{double: {factr: 3}}", "scenes.demo.params.double"),
    ],
)
def test_bad_scene_params_exit_2_and_name_the_block(tmp_path, capsys, scene_params, expected):
    cfg = write_config(tmp_path)
    cfg.write_text(
        cfg.read_text().replace(
            "demo: {synthetic: {preset: demo}}",
            f"demo: {{synthetic: {{preset: demo}}, params: {scene_params}}}",
        )
    )
    assert run(cfg, "run", "all") == 2
    assert expected in capsys.readouterr().err


def config_with(tmp_path: Path, stages: str, name: str = "pipeline.yaml") -> Path:
    """A config in `tmp_path` with one synthetic scene and the given `stages:` block (YAML)."""
    cfg = tmp_path / name
    cfg.write_text(
        textwrap.dedent("""
        workspace: ws
        default_scene: demo
        executor: {kind: local, workers: 1}
        scenes:
          demo: {synthetic: {preset: demo}}
        stages:
        """)
        + textwrap.indent(textwrap.dedent(stages), "  ")
    )
    return cfg


def _chain_config(tmp_path: Path) -> Path:
    return config_with(
        tmp_path,
        """
        source: {module: "tests.fake_stages:SOURCE"}
        constant: {module: "tests.fake_stages:CONSTANT", needs: [source]}
        peek: {module: "tests.fake_stages:PEEK", needs: [constant]}
        double: {module: "tests.fake_stages:DOUBLE", needs: [source]}
        """,
        "chain.yaml",
    )


def test_a_stage_sees_a_change_two_stages_up(tmp_path, counter):
    """peek reads source's output but needs only constant, whose output never changes: a new
    source still makes peek stale (before: 'up to date' with the old copy)."""
    cfg = _chain_config(tmp_path)
    assert run(cfg, "run", "all") == 0
    assert run(cfg, "run", "source", "--set", "source.value=5") == 0
    assert run(cfg, "run", "constant", "--set", "source.value=5") == 0  # the same bytes again
    assert run(cfg, "run", "peek", "--set", "source.value=5") == 0
    assert counter().count("peek") == 2
    copy = tmp_path / "ws" / "demo" / "peek" / "copy.txt"
    assert copy.read_text() == "value=5\n"


def test_a_rerun_upstream_that_writes_the_same_outputs_reruns_nothing_below(tmp_path, counter):
    """source reruns (a setting that does not change its output) and writes the same bytes:
    the stages below it are up to date and do not run again (before: all of them ran)."""
    cfg = _chain_config(tmp_path)
    assert run(cfg, "run", "all") == 0
    assert run(cfg, "run", "all", "--set", "source.torch_threads=1") == 0
    first = counter()[:4]
    assert sorted(first) == ["constant", "double", "peek", "source"]
    assert counter()[4:] == ["source"]


def test_a_relative_path_parameter_is_the_config_folders(tmp_path, monkeypatch, counter):
    """A path-typed stage parameter given relative (here `extra_file: data/x.txt`) means the
    config's folder, whatever the shell's folder is, as the config's other paths do (before:
    run from elsewhere, the file was missing)."""
    proj = tmp_path / "proj"
    (proj / "data").mkdir(parents=True)
    (proj / "data" / "x.txt").write_text("extra\n")
    cfg = write_config(proj, extra_params="")
    source = 'module: "tests.fake_stages:SOURCE", params: {'
    cfg.write_text(cfg.read_text().replace(source + "}", source + "extra_file: data/x.txt}"))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert run(cfg, "run", "source") == 0
    assert (proj / "ws" / "demo" / "source" / "data.txt").read_text() == "value=1\nextra\n"
    monkeypatch.chdir(proj)  # the same fingerprint from the config's own folder
    assert run(cfg, "run", "source") == 0
    assert counter() == ["source"]


def test_a_plain_value_error_of_the_projects_own_code_is_an_input_error():
    """calibrate's "videos ['cam04'] have no camera of that name" is a plain ValueError raised by
    the project: it printed a traceback above the line, against the docs. One raised inside a
    library (numpy's shapes) is no input error: more likely a bug, traceback kept."""
    import numpy as np

    from gst.video import iter_frames
    from pipeline.errors import is_input_error

    with pytest.raises(ValueError) as own:
        next(iter_frames("x.mp4", stride=0))
    assert type(own.value) is ValueError and is_input_error(own.value)
    with pytest.raises(ValueError) as library:
        np.zeros(3).reshape(2)
    assert not is_input_error(library.value)

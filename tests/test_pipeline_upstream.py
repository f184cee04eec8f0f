"""`run X` never reruns an expensive upstream stage unasked: a stale upstream stage whose
outputs exist is kept (and the log says so, with how long it took last time); `--upstream`
reruns it; missing upstream outputs are always produced."""

from __future__ import annotations

from tests.test_pipeline_dag import run, write_config


def test_a_stale_upstream_stage_is_kept_unless_asked(tmp_path, counter):  # noqa: F811
    cfg = write_config(tmp_path)
    assert run(cfg, "run", "report") == 0
    assert counter() == ["source", "double", "report"]

    # a parameter edited in the file that changes the upstream stage (a --set of the command
    # itself asks for the rerun: tests/test_pipeline_staleness.py)
    cfg.write_text(cfg.read_text().replace("params: {}}", "params: {value: 2}}", 1))
    assert run(cfg, "run", "report", "--force") == 0
    assert counter()[3:] == ["report"]  # source and double kept, report forced
    logs = sorted((tmp_path / "ws/.pipeline/logs").glob("*.log"))
    text = logs[-1].read_text()
    assert "source is stale (param value: 1 -> 2); its last run took" in text, text
    assert "using its existing outputs. Run it, or pass --upstream" in text

    assert run(cfg, "run", "report", "--upstream") == 0
    assert counter()[4:] == ["source", "double", "report"]


def test_missing_upstream_outputs_are_always_produced(tmp_path, counter):  # noqa: F811
    """... and the log says so before they start (`run track` in a new workspace started a
    pretraining with no word of what was coming)."""
    cfg = write_config(tmp_path)
    assert run(cfg, "run", "double") == 0
    assert counter() == ["source", "double"]
    (log_file,) = (tmp_path / "ws/.pipeline/logs").glob("*.log")
    assert "running first what double needs: source (never run)" in log_file.read_text()


def test_run_all_runs_every_stale_stage(tmp_path, counter):  # noqa: F811
    cfg = write_config(tmp_path)
    assert run(cfg, "run", "all") == 0
    assert run(cfg, "run", "all", "--set", "source.value=3") == 0
    assert counter() == ["source", "double", "report"] * 2


def test_a_scene_setting_set_on_the_command_line_reruns_the_stages_that_read_it(
    tmp_path,
    counter,  # noqa: F811
):
    """`--set scenes.demo.fps=25` made every stage stale, yet only the target reran: the
    upstream stages were kept with the old value ("the value typed was dropped")."""
    cfg = write_config(tmp_path)
    assert run(cfg, "run", "report") == 0
    assert run(cfg, "run", "report", "--set", "scenes.demo.fps=25") == 0
    assert counter() == ["source", "double", "report"] * 2

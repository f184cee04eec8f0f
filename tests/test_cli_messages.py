"""What a new user's mistakes on the command line print: the culprit, and what was expected."""

from __future__ import annotations

from pathlib import Path

from pipeline.cli import main

REPO = Path(__file__).resolve().parents[1]


def test_a_missing_config_names_the_folder_it_was_looked_for_in(tmp_path, capsys, monkeypatch):
    """Run from another folder, "config file not found: pipeline.yaml" did not say where it was
    looked for; a folder given as --config was "not found" too."""
    monkeypatch.chdir(tmp_path)
    assert main(["status"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert f"config file not found: pipeline.yaml (looked for from {tmp_path};" in err
    assert main(["status", "--config", str(tmp_path)]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert f"config file {tmp_path} is a folder" in err
    assert f"--config {tmp_path / 'pipeline.yaml'}" in err


def test_a_yaml_error_names_the_file_and_a_tab_says_to_indent_with_spaces(tmp_path, capsys):
    """A syntax error was located `in "<unicode string>", line 7`, and a tab got only PyYAML's
    "found character '\\t' that cannot start any token"."""
    cfg = tmp_path / "pipeline.yaml"
    text = (REPO / "pipeline.yaml").read_text()
    cfg.write_text(text.replace("\n  kind: local", "\n\tkind: local", 1))
    assert main(["status", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert "<unicode string>" not in err
    assert f'in "{cfg}", line 7, column 1' in " ".join(err.split())
    assert "YAML indents with spaces, not tabs" in err


def test_a_bad_stage_value_names_the_config_file_given(tmp_path, capsys, monkeypatch):
    """Run from the project folder with `--config other/pipeline.yaml`, a stage parameter's error
    said "pipeline.yaml: scenes.lab.params...", the name of the file in the folder run from."""
    other = tmp_path / "other"
    other.mkdir()
    cfg = other / "pipeline.yaml"
    text = (REPO / "pipeline.yaml").read_text()
    cfg.write_text(text.replace("track: {detector: blazepose}", "track: {detector: blazepos}"))
    monkeypatch.chdir(tmp_path)
    assert main(["status", "--config", str(cfg), "--scene", "lab"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "error: other/pipeline.yaml: scenes.lab.params.track.detector: Input should be" in err
    monkeypatch.chdir(REPO)  # outside the folder run from: the whole path
    assert main(["status", "--config", str(cfg), "--scene", "lab"]) == 2
    assert f"error: {cfg}: scenes.lab.params.track" in " ".join(capsys.readouterr().err.split())


def test_a_typo_of_a_stage_or_a_scene_names_the_close_one(capsys, monkeypatch):
    """`run trian` and `--scene labb` listed every name, the typo'd one among them unmarked."""
    monkeypatch.chdir(REPO)
    assert main(["run", "trian", "--dry-run"]) == 2
    assert "unknown stage 'trian' (did you mean 'train'?) (stages:" in capsys.readouterr().err
    assert main(["status", "--scene", "labb"]) == 2
    err = capsys.readouterr().err
    assert "unknown scene(s) ['labb'] (did you mean 'lab'?) (scenes:" in err
    assert main(["run", "zzz", "--dry-run"]) == 2  # nothing close: the list alone
    assert "unknown stage 'zzz' (stages:" in capsys.readouterr().err


def test_a_set_value_that_is_not_yaml_does_not_say_unicode_string(capsys, monkeypatch):
    monkeypatch.chdir(REPO)
    assert main(["run", "train", "--set", "train.steps=[1,", "--dry-run"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "--set 'train.steps=[1,': value is not valid YAML" in err
    assert "<unicode string>" not in err and "at line 1, column 4" in err

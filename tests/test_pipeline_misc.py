"""CLI entry point, executors, config overrides and the library/orchestration boundary."""

from __future__ import annotations

import copy
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.config import apply_override, load_config, parse_override
from pipeline.errors import ConfigError
from pipeline.executors import LocalExecutor, chunks

REPO = Path(__file__).resolve().parents[1]
LIBRARIES = ["calibration", "gst", "synth"]


def _square(x: int) -> int:
    return x * x


def test_local_executor_keeps_item_order_across_processes():
    seen = []

    def progress(items, description="", total=None):
        for item in items:
            seen.append(description)
            yield item

    ex = LocalExecutor(workers=2, progress=progress)
    assert ex.map(_square, range(7), description="squares") == [x * x for x in range(7)]
    assert seen == ["squares"] * 7


def test_chunks_cover_sequence():
    assert chunks(list(range(5)), 2) == [[0, 1], [2, 3], [4]]


def test_chunks_of_no_items_each_are_refused_not_emptied():
    """A size of 0 gave [[], [], []] for three items: every item silently dropped."""
    with pytest.raises(ValueError, match="size must be >= 1, got 0"):
        chunks([1, 2, 3], 0)


def test_module_help_and_status_run():
    out = subprocess.run(
        [sys.executable, "-m", "pipeline", "--help"], cwd=REPO, capture_output=True, text=True
    )
    assert out.returncode == 0 and "run" in out.stdout and "status" in out.stdout
    out = subprocess.run(
        [sys.executable, "-m", "pipeline", "status"], cwd=REPO, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr


def test_stages_params_lists_defaults_and_the_pipeline_files_values(capsys, monkeypatch):
    # in this process (`main` as `python -m pipeline` calls it): three interpreters importing
    # every stage took 18 s of the suite; test_module_help_and_status_run runs the module
    from pipeline.cli import main

    monkeypatch.chdir(REPO)  # the pipeline file found as the command finds it

    def stages_params(*extra: str) -> tuple[int, list[str], str]:
        code = main(["stages", "--params", *extra])
        out = capsys.readouterr()
        return code, [line.strip() for line in out.out.splitlines()], out.err

    code, lines, err = stages_params()
    assert code == 0, err
    assert "fill_gaps_s: float = 0.1" in lines  # a fuse default pipeline.yaml leaves alone
    assert "overlay: bool = True  (pipeline file: True)" in lines  # one it sets
    assert "floor: Union[float, Literal['auto'], NoneType] = 'auto'" in lines
    # --scene was accepted and ignored: the lab's own params (blazepose, refine_rig 2) unshown
    _, lines, _ = stages_params("--scene", "lab")
    assert "refine_rig: int = 0  (scene lab: 2)" in lines
    assert any(line.startswith("person_model:") and "(scene lab: 'blazepose')" in line
               for line in lines)  # fmt: skip
    assert "max_groups: int | None = 16" in lines  # not Optional[Annotated[int, Gt(gt=0)]]
    # a value `run` refuses is refused here too (it was listed as the pipeline file's value)
    code, _, err = stages_params("--set", "train.lr=-1")
    assert code == 2 and "(set by --set train.lr=-1)" in err


def test_override_parsing():
    assert parse_override("train.lr=1e-4") == (["train", "lr"], 1e-4)
    raw = {"stages": {"train": {"params": {}}}}
    apply_override(raw, ["train", "loss", "lpips"], 0.01)
    apply_override(raw, ["executor", "workers"], 3)
    assert raw["stages"]["train"]["params"] == {"loss": {"lpips": 0.01}}
    assert raw["executor"] == {"workers": 3}
    with pytest.raises(ConfigError):
        parse_override("train.lr")


@pytest.mark.parametrize(
    "text, value",
    [("x.y=010", 10), ("x.y=12:30", "12:30"), ("x.y=yes", "yes"), ("x.y=true", True),
     ("x.d={a: 1e-3, b: [1e-4, 2]}", {"a": 0.001, "b": [0.0001, 2]}), ("x.y=0x1F", 31),
     ("x.y=-1e-3", -0.001), ("x.y=nan", "nan"), ("x.y=~", None),
     ("x.y=2024-06-01", "2024-06-01"), ("x.y==", "=")],
)  # fmt: skip
def test_set_values_read_as_yaml_1_2(text, value):
    """YAML 1.1 read `010` as octal 8, `12:30` as 750 (base 60) and `yes` as true, and left
    `1e-3` text inside a mapping (so `calibration.options` got the string '1e-3'); a bare
    `nan` became NaN; a date became a datetime.date (refused as `fuse.markers`) and `=` a
    constructor error."""
    assert parse_override(text)[1] == value


def test_repository_config_is_valid():
    cfg = load_config(REPO / "pipeline.yaml")
    assert cfg.default_scene in cfg.scenes
    assert cfg.workspace.is_absolute()


def test_ray_without_the_dist_extra_is_a_one_line_config_error(monkeypatch):
    """`--executor ray` where Ray is not installed: exit 2 with what to install (was a two-part
    traceback and exit 1, even with --dry-run)."""
    import builtins

    from pipeline.executors import make_executor

    real_import = builtins.__import__

    def no_ray(name, *args, **kwargs):
        if name == "ray" or name.startswith("ray.") or name == "pipeline.ray_executor":
            raise ImportError(f"No module named '{name}'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    with pytest.raises(ConfigError, match=r"dist") as err:
        make_executor("ray", 2)
    assert err.value.exit_code == 2


def _lab_like(folder: Path) -> Path:
    """A project in `folder`: two camera files matched by a relative glob, a scene value."""
    (folder / "cams").mkdir(parents=True)
    for name in ("cam01.mp4", "cam02.mp4"):
        (folder / "cams" / name).write_bytes(b"x")
    cfg = folder / "pipeline.yaml"
    cfg.write_text(
        "workspace: ws\ndefault_scene: lab\nscenes:\n"
        "  lab: {videos: cams/cam*.mp4, params: {fuse: {refine_rig: 2}}}\n"
        "stages:\n  fuse: {module: 'tests.fake_stages:SOURCE', params: {refine_rig: 1}}\n"
    )
    return cfg


def test_a_glob_under_a_folder_whose_name_is_a_pattern(tmp_path):
    """The config's folder was joined into the `videos` glob unescaped: in a project folder
    named 'take [2024]' the pattern matched nothing and the config was refused."""
    cfg = _lab_like(tmp_path / "take [2024]")
    files = load_config(cfg).scenes["lab"].video_files()
    assert [f.name for f in files] == ["cam01.mp4", "cam02.mp4"]


def test_a_path_from_the_home_folder_is_the_users_home(tmp_path, monkeypatch):
    """`workspace: ~/ws` and `videos: ~/cams/cam*.mp4` meant folders named `~` inside the
    config's folder (a `run` would have made one there, and `rm -rf ~` is how one cleans it)."""
    home = tmp_path / "home"
    (home / "cams").mkdir(parents=True)
    for name in ("cam01.mp4", "cam02.mp4"):
        (home / "cams" / name).write_bytes(b"")
    monkeypatch.setenv("HOME", str(home))
    cfg = tmp_path / "proj" / "pipeline.yaml"
    cfg.parent.mkdir()
    cfg.write_text(
        "workspace: ~/ws\ndefault_scene: lab\nscenes:\n  lab: {videos: ~/cams/cam*.mp4}\n"
        "stages:\n  fuse: {module: 'tests.fake_stages:SOURCE'}\n"
    )
    loaded = load_config(cfg)
    assert loaded.workspace == home / "ws"
    assert [f.parent for f in loaded.scenes["lab"].video_files()] == [home / "cams"] * 2
    from pipeline.runner import _absolute  # a Path-typed stage parameter (pretrain.reuse)

    assert _absolute({"reuse": Path("~/gst.pt")}, cfg.parent) == {"reuse": home / "gst.pt"}
    # a text that may name a file (fuse.markers, body_model) likewise
    assert _absolute("~/mk.json", cfg.parent, texts=True) == str(home / "mk.json")
    assert _absolute("smpl:female", cfg.parent, texts=True) == "smpl:female"


def test_the_long_form_of_set_overrides_a_scenes_value_as_the_short_one_does():
    """`--set stages.fuse.params.refine_rig=0` left the lab scene's own `refine_rig: 2` in
    place; only `--set fuse.refine_rig=0` removed it."""
    raw = {
        "stages": {"fuse": {"params": {"refine_rig": 1}}},
        "scenes": {"lab": {"params": {"fuse": {"refine_rig": 2}}}},
    }
    for parts in (["fuse", "refine_rig"], ["stages", "fuse", "params", "refine_rig"]):
        edited = copy.deepcopy(raw)
        apply_override(edited, parts, 0)
        assert edited["stages"]["fuse"]["params"]["refine_rig"] == 0
        assert "refine_rig" not in edited["scenes"]["lab"]["params"]["fuse"]


@pytest.mark.parametrize("stage_first", [True, False])
def test_set_stage_key_wins_over_a_scenes_set_in_either_order(stage_first):
    """Whichever came last won: `--set train.steps=10 --set scenes.demo.params.train.steps=5`
    trained 5 steps, though `--set STAGE.KEY` is documented to win over a scene's value."""
    sets = ["train.steps=10", "scenes.demo.params.train.steps=5"]
    cfg = load_config(REPO / "pipeline.yaml", sets if stage_first else sets[::-1])
    assert cfg.stages["train"].params["steps"] == 10
    assert "steps" not in cfg.scenes["demo"].params.get("train", {})


@pytest.mark.parametrize(
    "given", ["stages.train.params.steps=0", "train.steps=0", "scenes.demo.params.train.steps=0"]
)
def test_a_bad_value_from_either_form_of_set_is_blamed_on_the_set(given, capsys):
    """The long forms were recorded under keys the stage's validation never looks up: the error
    blamed pipeline.yaml, which says `steps: 200`."""
    from pipeline.cli import main

    config = str(Path(__file__).resolve().parents[1] / "pipeline.yaml")
    assert main(["run", "train", "--dry-run", "--config", config, "--set", given]) == 2
    assert f"(set by --set {given})" in capsys.readouterr().err


def test_config_mistakes_found_before_anything_runs(tmp_path, capsys):
    """A key given twice (the first block's settings silently dropped), a cycle among the needs
    (found at run time, after the run's log file was written), an infinite scene value, a
    `--ray-address` or `executor.ray_address` the local executor ignores: each is exit 2 with
    what is wrong, and no workspace file."""
    from pipeline.cli import main

    text = (REPO / "pipeline.yaml").read_text()
    (tmp_path / "pipeline.yaml").write_text(text)
    twice = tmp_path / "twice.yaml"
    twice.write_text(
        text.replace("stages:\n", "stages:\n  pretrain: {params: {lift_steps: 3}}\n", 1)
    )
    # a config of one's own with a scene and no stages: an empty status table and a `run all`
    # that did nothing, both exit 0
    scene_only = tmp_path / "mine.yaml"
    scene_only.write_text("scenes:\n  mine:\n    videos: cams/*.mp4\n")
    # a video scene pointing at its footage folder, or taking every file in it, and without
    # any calibration: read as cameras named after the folder or the notes, then a stage failure
    footage = tmp_path / "footage"
    footage.mkdir()
    for f in ("cam01.mp4", "cam02.mp4", "Calib.qca.txt", "SOURCE.md"):
        (footage / f).write_bytes(b"x")
    lab = tmp_path / "lab.yaml"
    lab.write_text(
        text.replace("scenes:\n", f"scenes:\n  mine:\n    videos: {footage}\n", 1).replace(
            "scenes:\n", f"scenes:\n  every:\n    videos: '{footage}/*'\n", 1
        )
    )
    runs = [
        (["run", "calibrate", "--scene", "mine", "--config", str(lab)], "is a folder, not a video"),
        (["run", "calibrate", "--scene", "mine", "--config", str(lab)], "exactly one of a calib"),
        (["run", "calibrate", "--scene", "every", "--config", str(lab)], "SOURCE.md are no videos"),
        (
            [
                "run",
                "calibrate",
                "--scene",
                "mine",
                "--config",
                str(lab),
                "--set",
                f"scenes.mine.videos=[{footage}/cam01.mp4, {footage}/cam01.mp4]",
            ],
            "listed twice",
        ),  # fmt: skip
        (["status", "--config", str(scene_only)], "copy the `stages:` block"),
        (["run", "all", "--config", str(scene_only)], "the file declares no stages"),
        (["status", "--config", str(twice)], "key 'pretrain' is given twice"),
        (["run", "synth", "--set", "stages.synth.needs=[bench]"], "stages form a cycle"),
        (["status", "--set", "scenes.demo.fps=.inf"], "scenes.demo.fps: Input should be a finite"),
        (["run", "synth", "--dry-run", "--ray-address", "x"], "--ray-address goes with"),
        (
            ["run", "synth", "--dry-run", "--set", "executor.ray_address=x"],
            "executor.ray_address ('x') goes with the Ray executor, but the executor is 'local'",
        ),
    ]
    for args, message in runs:
        config = [] if "--config" in args else ["--config", str(tmp_path / "pipeline.yaml")]
        assert main(args + config) == 2, args
        assert message in capsys.readouterr().err, args
    assert not (tmp_path / "workspace").exists()
    # the rig is an input only where the run reaches `calibrate` (`track` runs without one)
    own_dag = tmp_path / "own_dag.yaml"
    own_dag.write_text(f"scenes:\n  mine:\n    videos: {footage}/cam0*.mp4\n"
                       "stages:\n  track: {needs: []}\n  calibrate: {}\n")  # fmt: skip
    assert main(["run", "track", "--config", str(own_dag)]) == 1  # (no model to track with)
    err = capsys.readouterr().err
    assert "failed" in err and "exactly one of a calib" not in err
    assert main(["run", "calibrate", "--config", str(own_dag)]) == 2
    assert "exactly one of a calib" in capsys.readouterr().err


def test_an_error_is_blamed_on_the_set_that_gave_the_value_only(tmp_path, capsys):
    """The blame was a text search: `--set workspace=out` was named for an error at
    executor.workers, because 'workspace' occurs in the config's path (myworkspace/...)."""
    from pipeline.cli import main

    folder = tmp_path / "myworkspace"
    folder.mkdir()
    text = (REPO / "pipeline.yaml").read_text()
    (folder / "pipeline.yaml").write_text(text.replace("workers: 2", "workers: 0", 1))
    assert main(["status", "--config", str(folder / "pipeline.yaml"), "--set", "workspace=o"]) == 2
    err = capsys.readouterr().err
    assert "executor.workers" in err and "set by" not in err
    # a cross-field check's error (top level) is still blamed on the --set that caused it
    config = ["--config", str(REPO / "pipeline.yaml")]
    assert main(["status", *config, "--set", "default_scene=nope"]) == 2
    assert "(set by --set default_scene=nope)" in capsys.readouterr().err


def test_stages_quiet_still_lists_and_a_repeated_scene_is_one(capsys):
    """`stages -q` printed nothing (the listing is the command's output); `--scene demo
    --scene demo` showed the scene twice."""
    from pipeline.cli import main

    config = ["--config", str(REPO / "pipeline.yaml")]
    assert main(["stages", "-q", *config]) == 0
    assert "synth" in capsys.readouterr().out
    assert main(["status", "--scene", "demo", "--scene", "demo", *config]) == 0
    assert capsys.readouterr().out.count("scene 'demo'") == 1


def test_the_first_failing_item_ends_a_local_map_without_running_the_queue(tmp_path):
    """A failing item's error came only after every queued item had run (8 items on 2 workers:
    4.3 s and 7 items run, for an error known at 0.3 s)."""
    from tests.fake_stages import fail_first_item

    with pytest.raises(ValueError, match="item 0 is bad") as err:
        LocalExecutor(workers=2).map(fail_first_item, [(i, str(tmp_path)) for i in range(8)])
    assert any("item 0 ((0," in note for note in getattr(err.value, "__notes__", []))
    # the queue is cancelled and the running workers stopped: before, the map raised at once
    # but the workers ran every queued item on (and the interpreter waited for them at exit)
    time.sleep(2.5)
    assert len(list(tmp_path.glob("ran_*"))) <= 2


def test_an_error_that_cannot_be_rebuilt_in_the_parent_keeps_its_words():
    """An exception that pickles in the worker but not back (a custom two-argument
    `__init__`) broke the pool: "a worker process died (killed, or out of memory?)", and its
    message was lost."""
    from pipeline.errors import ItemFailed
    from tests.fake_stages import fail_with_two_arguments

    with pytest.raises(ItemFailed) as err:
        LocalExecutor(workers=2).map(fail_with_two_arguments, [0, 1, 2])
    text = str(err.value)
    assert "TwoArgumentError: cam01.mp4: the lens model is unknown" in text
    assert "died" not in text


def test_ctrl_c_during_a_local_map_stops_it_without_running_the_queue(tmp_path):
    """A Ctrl-C while the map waited for results skipped the cancel: every queued item ran
    before the interrupt reached the caller (8 items of 4 s on 2 workers: 12 s)."""
    import signal
    import subprocess
    import sys

    script = (
        "import signal, sys, time\n"
        # a job started in the background (CI under nohup &) inherits SIGINT ignored, and Python
        # then raises no KeyboardInterrupt: ask for it, as an interactive shell gives it
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "from pathlib import Path\n"
        "from pipeline.executors import LocalExecutor\n"
        "from tests.fake_stages import mark_and_sleep\n"
        "if __name__ == '__main__':\n"
        f"    LocalExecutor(workers=2).map(mark_and_sleep, [(i, {str(tmp_path)!r}) for i in "
        "range(8)])\n"
    )
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=root, stderr=subprocess.PIPE)
    deadline = time.time() + 60
    while len(list(tmp_path.glob("started_*"))) < 2 and time.time() < deadline:
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    time.sleep(1.0)
    assert proc.returncode != 0, err.decode()[-2000:]  # interrupted, not finished
    assert len(list(tmp_path.glob("started_*"))) <= 3  # those handed to the workers


def test_every_project_error_survives_a_trip_between_processes():
    """An error rebuilt in the parent from a worker: VideoTruncatedError (two arguments) could
    not be, so the pool broke and the user read "a worker process died ... item 1" for item 2's
    truncated video."""
    import importlib
    import inspect
    import pickle
    import pkgutil

    failures = []
    for package in ("gst", "calibration", "pipeline", "synth"):
        for info in pkgutil.walk_packages(importlib.import_module(package).__path__, f"{package}."):
            if info.name.endswith("__main__"):
                continue
            try:
                module = importlib.import_module(info.name)
            except ImportError:  # an optional extra (ray, gsplat) that is not installed
                continue
            for name, cls in inspect.getmembers(module, inspect.isclass):
                if cls.__module__ != module.__name__ or not issubclass(cls, BaseException):
                    continue
                params = [
                    p
                    for p in list(inspect.signature(cls.__init__).parameters.values())[1:]
                    if p.default is p.empty
                    and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
                ]
                error = cls(*(["x"] * len(params) if params else ["message"]))
                back = pickle.loads(pickle.dumps(error))
                if type(back) is not cls or str(back) != str(error):
                    failures.append(f"{info.name}.{name}")
    assert failures == []


def test_progress_in_a_log_file_writes_a_line_per_tenth_but_not_for_a_quick_step(caplog):
    """A 0.3 s step wrote ten progress lines into the log; a long one keeps its ten."""
    from pipeline.console import ProgressBars

    with caplog.at_level("INFO", logger="pipeline"):
        assert list(ProgressBars._logged(range(400), "quick", 400)) == list(range(400))
    assert [r.getMessage().split(" (")[0] for r in caplog.records] == ["quick: 400/400"]
    caplog.clear()
    with caplog.at_level("INFO", logger="pipeline"):
        list(ProgressBars._logged(range(100), "long", 100, min_interval_s=0.0))
    assert len(caplog.records) == 10


def test_a_key_error_names_its_block_and_a_close_key(tmp_path, capsys):
    """A review as a new user: an unknown key said only "unknown key" ('video' for 'videos'), a
    bad stage value named both the stage's block and the scene's whatever held it, and a check
    across keys was located at "(top level)" without the --set that gave one of them."""
    from pipeline.cli import main

    text = (REPO / "pipeline.yaml").read_text()
    typo = tmp_path / "typo.yaml"
    typo.write_text(text.replace("scenes:\n", "scenes:\n  mine:\n    video: x.mp4\n", 1))
    assert main(["status", "--config", str(typo)]) == 2
    assert "scenes.mine.video: unknown key (did you mean 'videos'?)" in capsys.readouterr().err
    # a scene whose name is a key of scenes (synthetic) is a scene, not that key's model
    typo.write_text(text.replace("scenes:\n", "scenes:\n  synthetic:\n    calibraton: x\n", 1))
    assert main(["status", "--config", str(typo)]) == 2
    assert "did you mean 'calibration'?" in capsys.readouterr().err
    own = tmp_path / "own.yaml"
    own.write_text(
        text.replace("  demo:  ", "  demo:\n    params: {track: {start_s: 5.0}}\n  #", 1)
    )
    config = ["--config", str(own), "--scene", "demo"]
    assert main(["status", *config, "--set", "track.batch_size=3x"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "stages.track.params.batch_size: Input should be a valid integer" in err
    assert "scenes.demo.params.track.batch_size" not in err  # not the block that holds it
    assert main(["status", *config, "--set", "track.end_s=1"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert (
        "stages.track.params.end_s / scenes.demo.params.track.start_s: end_s 1.0 must be after "
        "start_s 5.0 (set by --set track.end_s=1)"
    ) in err
    assert main(["status", *config, "--set", "track.batchsize=3"]) == 2
    assert "unknown key (did you mean 'batch_size'?)" in capsys.readouterr().err


def test_run_help_names_the_project_pipelines_stages():
    """`run --help` said only "stage name, or 'all'"; the names it lists are pipeline.yaml's."""
    import re

    from pipeline.cli import build_parser
    from pipeline.config import load_config

    parser = build_parser()
    run = next(
        a for a in parser._subparsers._group_actions[0].choices.values() if a.prog.endswith(" run")
    )
    text = " ".join(run.format_help().split())
    listed = re.search(r"declares ([a-z, ]+) \(", text).group(1).split(", ")
    assert listed == list(load_config(REPO / "pipeline.yaml").stages)


@pytest.mark.parametrize(
    "given, message",
    [
        ("train.lr=true", "stages.train.params.lr: Input should be a valid number"),
        ('train.steps="10"', "stages.train.params.steps: Input should be a valid integer"),
        ("calibrate.frame_step=true", "stages.calibrate.params.frame_step"),
        ('executor.workers="3"', "executor.workers"),
    ],
)
def test_values_of_the_wrong_type_are_refused_not_converted(given, message, capsys):
    """pydantic's lax mode took `train.lr=true` as a learning rate of 1.0 and `"10"` (text) as
    10, without a word; a config value must have its field's type (an integer still counts as
    a float, a list as a tuple, text as a path)."""
    from pipeline.cli import main

    assert main(["run", "calibrate", "--dry-run", "--set", given]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert message in err and f"--set {given}" in err


def test_a_stage_module_whose_own_import_fails_is_not_said_to_be_missing(tmp_path, monkeypatch):
    """`gait_stage` importing a helper that is not installed was reported as "module
    'gait_stage' does not exist" (the missing name 'gait' is a prefix of the module's)."""
    from pipeline.registry import load_stage

    (tmp_path / "gait_stage.py").write_text("import gait\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ConfigError, match="could not be imported: No module named 'gait'"):
        load_stage("gait", "gait_stage")
    with pytest.raises(ConfigError, match="module 'nowhere_stage' does not exist"):
        load_stage("gait", "nowhere_stage")
    with pytest.raises(ConfigError, match="module 'nowhere_pkg.stage' does not exist"):
        load_stage("gait", "nowhere_pkg.stage")


def _config_file(tmp_path: Path, scenes: str, top: str = "workspace: ws") -> Path:
    cfg = tmp_path / "pipeline.yaml"
    cfg.write_text(
        f"{top}\nscenes:\n{scenes}\nstages:\n  synth: {{}}\n  calibrate: {{needs: [synth]}}\n"
        "  extract: {needs: [calibrate]}\n  train: {needs: [extract]}\n  track: {}\n"
        "  pretrain: {}\n"
    )
    return cfg


@pytest.mark.parametrize("name", ["'..'", "'.'", "'/tmp/elsewhere'", "'a/b'", "'.pipeline'", "all"])
def test_a_scene_name_that_is_no_folder_of_the_workspace_is_refused(tmp_path, capsys, name):
    """A scene named '..' put its outputs beside the workspace (run synth replaced a folder
    there: with the project's pipeline.yaml, its own packages); '/tmp/x' and 'a/b' wrote
    elsewhere, '.pipeline' into the runner's state, 'all' could never be picked alone."""
    from pipeline.cli import main

    cfg = _config_file(tmp_path, f"  {name}: {{synthetic: {{preset: demo}}}}")
    assert main(["run", "synth", "--config", str(cfg), "--dry-run"]) == 2
    assert "cannot be a folder of the workspace" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="is not in the workspace"):
        load_config(_config_file(tmp_path, "  ok: {synthetic: {preset: demo}}")).scene_workspace(
            ".."
        )


def test_a_config_that_is_no_text_or_a_workspace_that_is_a_file_is_a_config_error(tmp_path):
    """A file that is not UTF-8 (a video given as --config) raised UnicodeDecodeError, and a
    workspace naming a file NotADirectoryError, each as a traceback."""
    latin = tmp_path / "latin.yaml"
    latin.write_bytes(b"\xff\xfe bad")
    with pytest.raises(ConfigError, match="latin.yaml: not a readable UTF-8 YAML file"):
        load_config(latin)
    (tmp_path / "notes.txt").write_text("x")
    cfg = _config_file(tmp_path, "  s: {synthetic: {preset: demo}}", "workspace: notes.txt/ws")
    with pytest.raises(ConfigError, match="notes.txt is a file"):
        load_config(cfg)


@pytest.mark.parametrize(
    "setting, said",
    [("extract.crop_size=8", "crop_size: Input should be greater than or equal to 16"),
     ("extract.scale=0.5", "scale: Input should be greater than or equal to 1"),
     ("extract.association={min_views: 1}", "min_views must be >= 2"),
     ("train.device=tpu", "device 'tpu' is not a device"),
     ("track.device=cuda:x", "device 'cuda:x' is not a device")],
)  # fmt: skip
def test_settings_the_stage_would_refuse_are_refused_before_anything_runs(
    tmp_path, capsys, setting, said
):
    """These passed the config check and failed inside their stage, after the stages before
    it had run."""
    from pipeline.cli import main

    cfg = _config_file(tmp_path, "  s: {synthetic: {preset: demo}}")
    assert main(["run", "synth", "--config", str(cfg), "--dry-run", "--set", setting]) == 2
    assert said in capsys.readouterr().err


@pytest.mark.parametrize(
    "board, said",
    [("squares_x: 2, squares_y: 5, square_size: 0.1", "at least 3 x 3 squares"),
     ("squares_x: 5, squares_y: 7, square_size: 0.1", "marker_size must be in (0, square_size"),
     ("squares_x: 5, squares_y: 7, square_size: 0.1, marker_size: 0.07, dictionary: DICT_NOPE",
      "'DICT_NOPE' is unknown"),
     ("squares_x: 20, squares_y: 20, square_size: 0.1, marker_size: 0.07, "
      "dictionary: DICT_4X4_50", "needs 200 markers")],
)  # fmt: skip
def test_a_board_that_cannot_be_made_is_a_config_error(tmp_path, capsys, board, said):
    """These boards passed the config check and failed in calibrate, every time."""
    from pipeline.cli import main

    video = tmp_path / "cam1.mp4"
    video.write_bytes(b"")
    cfg = _config_file(
        tmp_path, f"  s: {{videos: [{video}], board: {{videos: [{video}], {board}}}}}"
    )
    assert main(["run", "calibrate", "--config", str(cfg), "--dry-run"]) == 2
    assert said in capsys.readouterr().err


def test_a_synthetic_body_model_file_is_read_beside_the_config(tmp_path, monkeypatch):
    """`overrides: {body_model: my_smpl.pkl}` beside the config passed the check and was looked
    for in the shell's folder by the synth stage; a missing one failed there."""
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "my_smpl.pkl").write_bytes(b"")
    scenes = "  s: {synthetic: {preset: demo, overrides: {body_model: my_smpl.pkl}}}"
    cfg = _config_file(tmp_path / "cfg", scenes)
    monkeypatch.chdir(tmp_path)
    loaded = load_config(cfg).scenes["s"].synthetic.overrides["body_model"]
    assert loaded == str(tmp_path / "cfg" / "my_smpl.pkl")
    (tmp_path / "cfg" / "my_smpl.pkl").unlink()
    with pytest.raises(ConfigError, match=r"scenes.s.synthetic.overrides.body_model: .*my_smpl"):
        load_config(cfg)
    anny = _config_file(
        tmp_path / "cfg", "  s: {synthetic: {preset: demo, overrides: {body_model: anny}}}"
    )
    assert load_config(anny).scenes["s"].synthetic.overrides["body_model"] == "anny"


def test_a_set_of_a_scene_that_does_not_exist_names_the_scenes(tmp_path):
    """`--set scenes.nope.fps=3` (a typo'd scene) made a scene and was refused as one without
    footage; a new scene given its footage is still made."""
    cfg = _config_file(tmp_path, "  s: {synthetic: {preset: demo}}")
    with pytest.raises(ConfigError, match=r"no scene 'nope' \(scenes: \['s'\]\)"):
        load_config(cfg, ["scenes.nope.fps=3"])
    made = load_config(cfg, ["scenes.t.synthetic={preset: demo}"])
    assert sorted(made.scenes) == ["s", "t"]


@pytest.mark.parametrize("workers, n_items", [(1, 3), (2, 1)])
def test_a_failing_item_run_inline_is_named_as_the_pool_names_it(workers, n_items):
    """One worker (or one item) runs the map in this process: its error had no note naming the
    item, so `--workers 1` lost which camera or video failed."""
    from tests.fake_stages import fail_with_two_arguments

    items = [1] if n_items == 1 else [0, 1, 2]
    with pytest.raises(Exception, match="the lens model is unknown") as err:
        LocalExecutor(workers=workers).map(fail_with_two_arguments, items, "lens check")
    index = items.index(1)
    assert f"lens check: item {index} (1)" in getattr(err.value, "__notes__", [])

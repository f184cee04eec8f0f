"""Staleness decisions that were wrong: a fingerprint computed before an ancestor reran, a
scene edit reaching stages that never read the scene, files named by params, outputs declared
by an option, and variant names that collide."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import pytest

from pipeline.cli import main
from pipeline.runner import _safe_key
from tests.test_pipeline_dag import _chain_config, config_with, run, write_config


def test_a_stage_behind_a_kept_one_records_the_fingerprint_of_what_it_read(
    tmp_path, counter, capsys
):
    """source's outputs deleted, `run peek`: source runs again and writes the same bytes,
    constant (between them) is kept. peek's fingerprint was computed at planning time, from
    source's absent outputs: peek ran for nothing, recorded that fingerprint, and right
    afterwards `status` said 'stale' and the next run redid it. Now it is computed after
    source ran: peek is up to date."""
    cfg = _chain_config(tmp_path)
    assert run(cfg, "run", "all") == 0
    shutil.rmtree(tmp_path / "ws" / "demo" / "source")
    capsys.readouterr()
    assert main(["run", "peek", "--config", str(cfg)]) == 0  # not --quiet: the log is read
    assert counter()[4:] == ["source"]
    assert "constant is stale (upstream source will run first)" in capsys.readouterr().err
    assert main(["status", "--config", str(cfg)]) == 0
    table = capsys.readouterr().out
    assert "stale" not in table and "missing" not in table
    assert run(cfg, "run", "peek") == 0
    assert counter()[5:] == []


def test_a_kill_in_an_upstream_commit_does_not_leave_the_target_up_to_date(
    tmp_path, counter, monkeypatch
):
    """`run source --set source.value=5` killed in its commit, after its record went and
    before its new output came: the next `run peek` reran source (no record), kept constant,
    and said peek was up to date: its plan had read source's old outputs. peek kept the old
    value until the run after."""
    import pipeline.runner as runner

    cfg = _chain_config(tmp_path)
    assert run(cfg, "run", "all") == 0

    def killed(*_args, **_kw):
        raise KeyboardInterrupt  # as a kill -9 there: nothing after it runs

    with monkeypatch.context() as m:
        m.setattr(runner, "replace_path", killed)
        try:
            main(["run", "source", "-q", "--config", str(cfg), "--set", "source.value=5"])
        except KeyboardInterrupt:
            pass
    assert run(cfg, "run", "peek", "--set", "source.value=5") == 0
    assert (tmp_path / "ws" / "demo" / "peek" / "copy.txt").read_text() == "value=5\n"
    # constant reruns too: it lies between the stage the --set names and the target
    assert counter()[-3:] == ["source", "constant", "peek"]


def test_a_scene_edit_leaves_stages_that_do_not_read_the_scene_up_to_date(
    tmp_path, counter, capsys
):
    """Every stage hashed the scene's settings, so a new scene seed (or fps) made pretrain
    stale too, and `run all` trained it again."""
    cfg = config_with(
        tmp_path,
        """
        sceneless: {module: "tests.fake_stages:SCENELESS"}
        source: {module: "tests.fake_stages:SOURCE"}
        """,
    )
    assert run(cfg, "run", "all") == 0
    cfg.write_text(cfg.read_text().replace("preset: demo", "preset: demo, seed: 3"))
    capsys.readouterr()
    assert main(["status", "--config", str(cfg)]) == 0
    rows = {line.split("│")[1].strip(): line for line in capsys.readouterr().out.splitlines()
            if line.count("│") > 3}  # fmt: skip
    assert "up to date" in rows["sceneless"] and "scene synthetic.seed: 0 -> 3" in rows["source"]
    assert run(cfg, "run", "all") == 0
    assert counter() == ["sceneless", "source", "source"]


def test_a_file_named_by_a_param_is_an_input(tmp_path, counter, capsys):
    """A Path-valued param (track.boxes, train.hmr2_checkpoint) or a text param naming a file
    (fuse.body_model: my_smpl.pkl) was not hashed: editing the file left the stage 'up to
    date' with results from the old one. A text param is also resolved against the config's
    folder, as Path params are (it was the shell's)."""
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "x.txt").write_text("one\n")
    (tmp_path / "data" / "named.txt").write_text("a\n")
    cfg = config_with(
        tmp_path,
        """
        source: {module: "tests.fake_stages:SOURCE",
                 params: {extra_file: data/x.txt, input_file: data/named.txt}}
        """,
    )
    assert run(cfg, "run", "source") == 0
    (tmp_path / "data" / "x.txt").write_text("two\n")
    capsys.readouterr()
    assert main(["status", "--config", str(cfg)]) == 0
    assert "input changed: data/x.txt" in capsys.readouterr().out
    assert run(cfg, "run", "source") == 0
    out = tmp_path / "ws" / "demo" / "source" / "data.txt"
    assert out.read_text() == "value=1\na\ntwo\n"
    assert counter() == ["source", "source"]
    # an input outside the config's folder is shown by its own path, and not cut short
    outside = tmp_path.parent / f"{tmp_path.name}_elsewhere_with_a_rather_long_folder_name.txt"
    outside.write_text("a\n")
    cfg.write_text(cfg.read_text().replace("data/named.txt", str(outside)))
    assert run(cfg, "run", "source") == 0
    outside.write_text("b\n")
    capsys.readouterr()
    assert main(["status", "--config", str(cfg)]) == 0
    # (wrapped in the table's column: the cell's lines joined without the borders)
    table = "".join(c for c in capsys.readouterr().out if not c.isspace() and c not in "│┃")
    assert f"inputchanged:{outside}" in table


def test_a_plain_text_param_is_not_taken_for_a_file_of_that_name(tmp_path):
    """Every text param became an absolute path when a file of that name lay beside the
    config: `extract.method: median` with a file `median` there reached the stage as
    '/.../median' (refused after synth and calibrate had run), `pretrain.preset: tiny` likewise.
    Only params marked NAMES_FILE (body_model, markers) name files."""
    from pipeline.config import load_config
    from pipeline.registry import load_stages
    from pipeline.runner import Runner

    for name in ("median", "tiny", "data.txt"):
        (tmp_path / name).write_text("x\n")
    cfg = config_with(
        tmp_path,
        """
        source: {module: "tests.fake_stages:SOURCE", params: {input_file: data.txt}}
        extract: {module: "stages.extract:STAGE"}
        pretrain: {module: "stages.pretrain:STAGE"}
        """,
    )
    config = load_config(cfg)
    runner = Runner(config, "demo", load_stages(config))
    source = runner._validate_params("source")
    assert source.label == "median"
    assert source.input_file == str(tmp_path / "data.txt")  # marked: resolved against the folder
    assert runner._validate_params("extract").method == "median"
    assert runner._validate_params("pretrain").preset == "tiny"


def test_outputs_an_option_declares_are_made_when_absent(tmp_path, counter, capsys):
    """`run track --with-gaussians` after a plain run said 'up to date' and listed splat
    folders that did not exist: only the outputs recorded by the last run were checked."""
    cfg = config_with(tmp_path, 'extras: {module: "tests.fake_stages:EXTRAS"}\n')
    assert run(cfg, "run", "extras") == 0
    assert run(cfg, "run", "extras", "--with-gaussians") == 0
    assert (tmp_path / "ws" / "demo" / "extras" / "splats" / "one.ply").is_file()
    assert counter() == ["extras", "extras"]
    assert run(cfg, "run", "extras", "--with-gaussians") == 0
    assert counter() == ["extras", "extras"]
    # a plain run since (here forced; a new model in practice) leaves the old splats on disk
    # and records none: asked for again they were taken as made by that run ('up to date')
    assert run(cfg, "run", "extras", "--force") == 0
    assert (tmp_path / "ws" / "demo" / "extras" / "splats" / "one.ply").is_file()
    assert run(cfg, "run", "extras", "--with-gaussians") == 0
    assert counter() == ["extras"] * 4


def test_variant_keys_that_differ_only_in_odd_characters_keep_separate_records():
    """`track@a b` and `track@a_b` were both stored as track@a_b.json, each overwriting the
    other's record (so the first ran again though nothing had changed)."""
    assert _safe_key("track@a b") != _safe_key("track@a_b")
    assert _safe_key("track@a_b") == "track@a_b"  # plain keys keep their file names
    assert _safe_key("track@a b") == _safe_key("track@a b")


def test_extract_and_calibrate_declare_every_file_they_read(tmp_path):
    """extract reads the scene's `masks` folder and calibrate probes the camera videos (the rig
    is fitted to their frame size), but neither was an input: new masks, or a re-exported
    video, left them 'up to date'."""
    from pipeline.config import SceneConfig
    from pipeline.stage import StageContext
    from stages.calibrate import STAGE as CALIBRATE
    from stages.extract import STAGE as EXTRACT
    from stages.extract import Params as ExtractParams

    videos = [tmp_path / "cam01.mp4", tmp_path / "cam02.mp4"]
    (tmp_path / "masks").mkdir()
    calib = tmp_path / "Calib.qca.txt"
    scene = SceneConfig(
        videos=videos, masks=tmp_path / "masks", calibration={"file": calib, "format": "qualisys"}
    )

    def ctx(params) -> StageContext:
        return StageContext("x", "lab", scene, None, tmp_path / "ws", tmp_path / "st", params)

    assert set(EXTRACT.inputs(ctx(ExtractParams()))) >= {*videos, tmp_path / "masks"}
    assert set(CALIBRATE.inputs(ctx(None))) == {calib, *videos}


def test_the_bench_reads_the_trained_model_as_an_input(tmp_path):
    """bench scores models/gst.pt when it is there, but train is not among its needs and the
    model was no input: after a retraining `run bench` said 'up to date' and kept the table
    of the old model."""
    from pipeline.config import SceneConfig
    from pipeline.stage import StageContext
    from stages.bench import STAGE as BENCH

    scene = SceneConfig(synthetic={"preset": "demo", "seed": 0})
    ctx = StageContext("bench", "demo", scene, None, tmp_path / "ws", tmp_path / "st", None)
    params = BENCH.params_model()
    assert BENCH.inputs(replace(ctx, params=params)) == []  # nothing trained: no input
    model = ctx.path("models/gst.pt")
    model.parent.mkdir(parents=True)
    model.write_bytes(b"weights")
    assert BENCH.inputs(replace(ctx, params=params)) == [model]
    off = params.model_copy(update={"include_trained": False})
    assert BENCH.inputs(replace(ctx, params=off)) == []


def test_each_variant_stages_its_outputs_in_a_folder_of_its_own(tmp_path):
    """All variants of a stage shared `.pipeline/staging/<stage>`: starting `track --video
    b.mp4` deleted the resumable progress of an interrupted `track --video a.mp4` (another
    fingerprint in the same folder)."""
    from pipeline.config import load_config
    from pipeline.registry import load_stages
    from pipeline.runner import Runner

    cfg = load_config(config_with(tmp_path, 'per_video: {module: "tests.fake_stages:PER_VIDEO"}'))
    stages = load_stages(cfg)

    def staging(**options):
        return Runner(cfg, "demo", stages, options=options).context("per_video").staging

    a, b, plain = staging(video="a b"), staging(video="b"), staging()
    assert len({a, b, plain}) == 3 and a.parent == b.parent == plain.parent
    assert plain.name == "per_video" and b.name == "per_video@b"
    assert a.name == _safe_key("per_video@a b")


def test_a_variant_of_many_videos_runs_and_keeps_its_record(tmp_path):
    """`track --video` of 30 clips (GX010001.mp4 ...): the variant joins their names, and its
    state file name passed the file system's 255 bytes, an OSError traceback even with
    --dry-run. Long keys are cut, a hash keeping them apart."""
    from pipeline.config import load_config

    cfg = config_with(tmp_path, 'per_video: {module: "tests.fake_stages:PER_VIDEO"}')
    clips = []
    for k in range(1, 32):
        clips += ["--video", str(tmp_path / f"GX01{k:04d}.mp4")]
        (tmp_path / f"GX01{k:04d}.mp4").write_bytes(b"")
    assert run(cfg, "run", "per_video", *clips[:-2]) == 0
    assert run(cfg, "run", "per_video", *clips) == 0
    state = load_config(cfg).scene_workspace("demo") / ".pipeline" / "state"
    records = [p.name for p in state.iterdir() if p.name.startswith("per_video@")]
    assert len(records) == 2 and all(len(r.encode()) < 200 for r in records)
    assert run(cfg, "run", "per_video", *clips) == 0  # up to date: its record was found
    assert run(cfg, "status") == 0


def test_the_hash_cache_sees_a_same_size_file_copied_in_with_its_old_time(tmp_path):
    """Keyed by size and modification time, the cache served the old digest for a file of the
    same size copied in with the old file's time (cp -p, rsync -a, tar x do that): the stages
    reading it stayed 'up to date'."""
    import os

    from pipeline.fingerprint import HashCache

    f = tmp_path / "rig.json"
    f.write_text('{"fx": 1000.0}')
    cache = HashCache(tmp_path / "hashcache.json")
    old = cache.digest(f)
    cache.save()
    st = f.stat()
    new = tmp_path / "new.json"
    new.write_text('{"fx": 2000.0}')  # the same size
    os.utime(new, ns=(st.st_atime_ns, st.st_mtime_ns))
    os.replace(new, f)
    assert f.stat().st_size == st.st_size and f.stat().st_mtime_ns == st.st_mtime_ns
    cache = HashCache(tmp_path / "hashcache.json")
    assert cache.digest(f) != old
    cache.save()
    import pipeline.fingerprint as fingerprint

    hashed = []
    real = fingerprint._sha256_file
    fingerprint._sha256_file = lambda p: hashed.append(p) or real(p)
    try:
        HashCache(tmp_path / "hashcache.json").digest(f)  # an unchanged file: a hit
    finally:
        fingerprint._sha256_file = real
    assert hashed == []


def test_a_body_model_named_smpl_is_hashed_by_the_file_it_reads(tmp_path, monkeypatch):
    """`body_model: smpl` (or `smpl:female`, or `~/...`) named no file the runner could hash:
    a swapped SMPL file left fuse and train 'up to date' with bodies of the old one."""
    from gst.fuse.settings import FuseSettings
    from gst.train.scene_training import TrainSettings
    from pipeline.runner import _param_files

    body_dir = tmp_path / "body"
    body_dir.mkdir()
    neutral, female = body_dir / "SMPL_NEUTRAL.pkl", body_dir / "SMPL_FEMALE.pkl"
    neutral.write_bytes(b"neutral")
    female.write_bytes(b"female")
    monkeypatch.setenv("GST_BODY_DIR", str(body_dir))
    monkeypatch.setenv("HOME", str(tmp_path))
    assert _param_files(FuseSettings(body_model="smpl")) == [neutral]
    assert _param_files(TrainSettings(body_model="smpl:female")) == [female]
    assert _param_files(FuseSettings(body_model="~/body")) == [neutral]  # a folder under ~
    assert _param_files(FuseSettings(body_model="anny")) == []  # built in: nothing to hash
    assert _param_files(FuseSettings(body_model="smpl:male")) == []  # none there: load says so


def test_a_second_video_of_the_same_name_does_not_replace_the_firsts_tracks(
    tmp_path, monkeypatch, capsys
):
    """`run track --video day1/match.mp4`, then `--video day2/match.mp4` (another video): the
    second run replaced the first's tracks (tracks are named after the file name) with an INFO
    line only. Now refused before anything runs, unless --force; the same video moved is fine."""
    import gst.track.read as track_read
    from gst.video import content_digest

    cfg = config_with(tmp_path, 'per_video: {module: "tests.fake_stages:PER_VIDEO"}')
    day1, day2 = tmp_path / "day1" / "match.mp4", tmp_path / "day2" / "match.mp4"
    for path, content in ((day1, b"first match"), (day2, b"second match")):
        path.parent.mkdir()
        path.write_bytes(content)
    tracks = tmp_path / "ws" / "demo" / "tracks" / "video=match" / "tracks.parquet"
    tracks.parent.mkdir(parents=True)
    tracks.write_bytes(b"")
    kept = {"video": {"file": "match.mp4", "content_sha256": content_digest(day1)}}
    monkeypatch.setattr(track_read, "read_metadata", lambda path: kept)
    args = ["run", "per_video", "--config", str(cfg), "-q"]
    assert main([*args, "--video", str(day2)]) == 2
    err = capsys.readouterr().err
    assert "holds the tracks of another video called match.mp4" in err and "--force" in err
    assert not (tmp_path / "ws" / "demo" / "per_video").exists()  # nothing ran
    assert main([*args, "--video", str(day2), "--dry-run"]) == 0
    moved = tmp_path / "moved" / "match.mp4"
    moved.parent.mkdir()
    moved.write_bytes(day1.read_bytes())
    assert main([*args, "--video", str(moved)]) == 0
    assert main([*args, "--video", str(day2), "--force"]) == 0


def test_track_inputs_that_cannot_run_are_refused_before_any_stage_runs(tmp_path, capsys):
    """An unreadable --video, a folder, smoothing with chunking and --with-gaussians with
    chunking failed inside `track`, after the stages before it (minutes on the demo) had run."""
    cfg = config_with(tmp_path, "track: {}")
    text = tmp_path / "notes.mp4"
    text.write_text("not a video")
    args = ["run", "track", "--config", str(cfg), "-q"]
    assert main([*args, "--video", str(text)]) == 1  # a data error, as inside track
    assert "notes.mp4" in capsys.readouterr().err
    assert main([*args, "--video", str(tmp_path)]) == 2
    assert "a folder, not a video file" in capsys.readouterr().err
    video = tmp_path / "clip.mp4"
    _tiny_video(video)
    for extra, shown in (
        (["--set", "track.chunk_frames=50", "--set", "track.smoothing=true"], "smoothing"),
        (["--set", "track.chunk_frames=50", "--with-gaussians"], "--with-gaussians"),
    ):
        assert main([*args, "--video", str(video), *extra]) == 2
        assert shown in capsys.readouterr().err
    assert not (tmp_path / "ws" / "demo" / "tracks").exists()


def _tiny_video(path) -> None:
    import cv2
    import numpy as np

    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (32, 32))
    for _ in range(3):
        writer.write(np.zeros((32, 32, 3), np.uint8))
    writer.release()


def test_a_target_the_scene_does_not_need_runs_nothing_upstream(tmp_path, counter, capsys):
    """`run bench --scene lab` ran extract (minutes), then skipped bench, which does not apply
    to a scene without truth."""
    cfg = config_with(
        tmp_path,
        """
        source: {module: "tests.fake_stages:SOURCE"}
        real_only: {module: "tests.fake_stages:REAL_ONLY", needs: [source]}
        """,
    )
    assert main(["run", "real_only", "--config", str(cfg), "--dry-run"]) == 0
    plan = capsys.readouterr().out
    assert "only for real_only, which the scene does not need" in plan
    assert main(["run", "real_only", "--config", str(cfg), "-q"]) == 0
    assert counter() == []
    assert main(["run", "source", "--config", str(cfg), "-q"]) == 0
    assert counter() == ["source"]


def test_status_lists_variants_that_never_finished(tmp_path, capsys, monkeypatch):
    """A failed or killed `track --video x.mp4` left only its staging folder (and the error it
    stopped on): `status`, which lists recorded variants, never showed it."""
    cfg = config_with(tmp_path, 'per_video: {module: "tests.fake_stages:PER_VIDEO"}')
    staging = tmp_path / "ws" / "demo" / ".pipeline" / "staging"
    (staging / "per_video@empty").mkdir(parents=True)
    (staging / "per_video@empty" / ".failed").write_text("VideoError: empty.mp4: no frames")
    (staging / "per_video@killed").mkdir()
    (staging / "other@x").mkdir()  # no such stage: not listed
    monkeypatch.setenv("COLUMNS", "400")  # the table on one line a row
    assert main(["status", "--config", str(cfg)]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "per_video@empty" in out and "VideoError: empty.mp4: no frames" in out
    assert "per_video@killed" in out and "a run was interrupted" in out
    assert "other@x" not in out


def test_a_stale_reason_does_not_list_keys_that_are_none_on_one_side_and_absent_on_the_other():
    """A record written when the stage kept every scene key (None where unset) made `status`
    list "scene board: None -> '<unset>'; scene fps: None -> '<unset>'; ..." for a stage that
    reads nothing of the scene, hiding the real reason (its code changed)."""
    from pipeline.runner import _diff_params

    old = {"board": None, "fps": None, "masks": {"dir": None}, "seed": 1}
    assert _diff_params(old, {"masks": {}, "seed": 1}) == []
    assert _diff_params(old, {"seed": 2}) == ["masks: {'dir': None} -> '<unset>'", "seed: 1 -> 2"]
    assert _diff_params({}, {"fps": 30.0}) == ["fps: '<unset>' -> 30.0"]


def test_a_set_on_an_upstream_stage_reruns_it_and_quiet_still_warns(tmp_path, counter, capsys):
    """`run peek --set source.value=7`: source, stale by that very value, was kept (its old
    outputs used, value=1 copied) with a warning that --quiet hid: exit 0, nothing said, the
    value typed dropped. Now a stage a --set names reruns; a stage kept for another reason is
    still kept, and --quiet still shows the warning that says so."""
    cfg = _chain_config(tmp_path)
    assert run(cfg, "run", "all") == 0
    capsys.readouterr()
    assert run(cfg, "run", "peek", "--set", "source.value=7") == 0
    assert (tmp_path / "ws" / "demo" / "peek" / "copy.txt").read_text() == "value=7\n"
    assert counter()[-3:] == ["source", "constant", "peek"]
    text = cfg.read_text().replace("source: {module", "source: {params: {value: 9}, module")
    cfg.write_text(text)  # the file's edit (not --set): source is kept
    assert run(cfg, "run", "peek") == 0
    assert "source is stale" in capsys.readouterr().err


def test_a_set_reaches_the_target_through_the_stages_between(tmp_path, counter, capsys):
    """`run report --set source.value=2`: source reran but double, between it and report, was
    kept with value=1, and report was made from that: the typed value still did not arrive."""
    from tests.test_pipeline_dag import write_config

    cfg = write_config(tmp_path)
    assert run(cfg, "run", "report") == 0
    assert run(cfg, "run", "report", "--set", "source.value=2") == 0
    assert counter()[3:] == ["source", "double", "report"]
    assert (tmp_path / "ws/demo/double/result.txt").read_text() == "value=2\n" * 2
    # the long form names its stage too
    assert run(cfg, "run", "report", "--set", "stages.source.params.value=3") == 0
    assert counter()[6:] == ["source", "double", "report"]


def test_quiet_prints_a_failure_once_and_warnings_to_the_current_stderr(tmp_path, capsys):
    """The quiet handler printed an unexpected failure twice (its log line with the traceback,
    then the error line) and kept the stderr of the run that made it (a later test's logging
    met a closed file)."""
    import logging

    from tests.test_pipeline_dag import write_config

    cfg = write_config(tmp_path)
    with open(cfg, "a") as f:
        f.write('  fail: {module: "tests.fake_stages:FAIL", needs: [source]}\n')
    assert run(cfg, "run", "fail") == 1
    err = capsys.readouterr().err
    assert err.count("boom") == 1 and "Traceback" not in err
    logging.getLogger("pipeline").warning("after the run")  # stderr is another object now
    assert "after the run" in capsys.readouterr().err


@pytest.mark.parametrize(
    "content, said",
    [
        (b'{"stage": "dou', "JSONDecodeError"),  # cut short (a full disk, a kill)
        (b"\xff\xfe\x00 garbage", "UnicodeDecodeError"),  # not text
        (b"[]", "not a JSON object"),
    ],
)
def test_an_unreadable_state_record_is_said_and_the_stage_reruns(
    tmp_path, counter, capsys, monkeypatch, content, said
):
    """A record that is not text, or not a JSON object, crashed `status` and `run` with a
    traceback (UnicodeDecodeError, AttributeError); one cut short was said to be 'never run'.
    Now `status` names the record and why, and `run` redoes the stage."""
    monkeypatch.setenv("COLUMNS", "400")  # the reason on one line of the table
    cfg = write_config(tmp_path)
    assert run(cfg, "run", "all") == 0
    (tmp_path / "ws/demo/.pipeline/state/double.json").write_bytes(content)
    capsys.readouterr()
    assert main(["status", "--config", str(cfg)]) == 0
    table = " ".join(capsys.readouterr().out.split())
    assert "cannot be read" in table
    assert said.replace(" ", "") in table.replace(" ", "") and "never run" not in table
    assert run(cfg, "run", "all") == 0
    assert counter() == ["source", "double", "report", "double"]  # report: the same input
    assert main(["status", "--config", str(cfg)]) == 0
    assert "cannot be read" not in capsys.readouterr().out


@pytest.mark.parametrize("content", [b"\xff\xfe", b"[1, 2]", None])
def test_a_corrupt_hash_cache_costs_rehashing_not_a_crash(tmp_path, counter, content):
    """The cache said a corrupt file 'only costs re-hashing', but a file that was not text or
    not of its shape crashed every `status` and `run` (UnicodeDecodeError, TypeError)."""
    cfg = write_config(tmp_path)
    assert run(cfg, "run", "all") == 0
    if content is None:  # an entry of another shape, for a file the runner hashes
        data = (tmp_path / "ws/demo/source/data.txt").resolve()
        content = json.dumps({str(data): 5}).encode()
    (tmp_path / "ws/.pipeline/hashcache.json").write_bytes(content)
    assert run(cfg, "status") == 0
    assert run(cfg, "run", "all") == 0
    assert counter() == ["source", "double", "report"]


def test_old_outputs_parked_by_a_stopped_commit_are_deleted_by_the_next_run(tmp_path, monkeypatch):
    """A commit parks a stage's old outputs in `.pipeline/trash` and deletes them once the new
    ones are in place; a run stopped in between left them there for good (every later run kept
    them: a pretraining's old model, say)."""
    import gst.atomic

    cfg = write_config(tmp_path)
    assert run(cfg, "run", "all") == 0

    def stopped(_folder):
        raise KeyboardInterrupt  # after the new output went in, before the old one was deleted

    with monkeypatch.context() as m:
        m.setattr(gst.atomic, "fsync_dir", stopped)
        assert run(cfg, "run", "double", "--force") == 130
    trash = tmp_path / "ws/demo/.pipeline/trash"
    assert any(trash.rglob("result.txt"))
    assert run(cfg, "run", "all") == 0
    assert not any(trash.rglob("*"))
    assert (tmp_path / "ws/demo/double/result.txt").read_text() == "value=1\n" * 2


def test_a_synthetic_scenes_body_model_file_is_an_input_of_synth(tmp_path):
    """`synthetic.overrides.body_model` naming a file (or `smpl`: the file in $GST_BODY_DIR)
    was no input of synth: a swapped SMPL file left the render 'up to date', posed with the
    old body."""
    from pipeline.config import load_config
    from pipeline.registry import load_stages
    from pipeline.runner import Runner

    body = tmp_path / "body.npz"
    body.write_bytes(b"first body")
    cfg = config_with(tmp_path, "synth: {}")
    cfg.write_text(cfg.read_text().replace("preset: demo", "preset: demo, overrides: "
                                           "{body_model: body.npz}"))  # fmt: skip
    config = load_config(cfg)
    stages = load_stages(config)

    def fingerprint() -> str:
        return Runner(config, "demo", stages).status_of("synth", {}).fingerprint

    before = fingerprint()
    body.write_bytes(b"other body")
    assert fingerprint() != before


@pytest.mark.parametrize(
    ("stage", "scene"),
    [
        ("source", "{synthetic: {preset: demo, overrides: {rig: {fps: %s}}}}"),
        ("extract", "{synthetic: {preset: demo}, "
                    "params: {extract: {association: {merge_radius: %s}}}}"),
    ],
)  # fmt: skip
def test_an_integer_and_the_same_float_in_an_untyped_mapping_are_one_fingerprint(
    tmp_path, stage, scene
):
    """Untyped mappings (a synthetic scene's `overrides`, a calibration's `options`, extract's
    `association`) keep the type YAML gave: `fps: 30` edited to `fps: 30.0` made every stage
    that reads the scene stale, training included, with no reason given."""
    from pipeline.config import load_config
    from pipeline.registry import load_stages
    from pipeline.runner import Runner

    own = {"source": '{module: "tests.fake_stages:SOURCE"}'}
    cfg = config_with(tmp_path, f"{stage}: {own.get(stage, '{}')}")
    text = cfg.read_text()

    def fingerprint(number: str) -> str:
        cfg.write_text(text.replace("{synthetic: {preset: demo}}", scene % number))
        config = load_config(cfg)
        return Runner(config, "demo", load_stages(config)).status_of(stage, {}).fingerprint

    assert fingerprint("30") == fingerprint("30.0") != fingerprint("31")


def test_a_set_reaches_a_scene_whose_name_holds_a_dot(tmp_path, counter):
    """A scene may be named `take.1`, but `--set scenes.take.1.fps=25` (or `.params...`) said
    "no scene 'take'": the key was split at every dot. And a stale upstream stage the --set
    names is rerun for that scene, not kept."""
    from pipeline.config import load_config

    cfg = _chain_config(tmp_path)
    cfg.write_text(cfg.read_text().replace("default_scene: demo", "default_scene: take.1")
                   .replace("  demo: {synthetic", "  take.1: {synthetic"))  # fmt: skip
    config = load_config(cfg, ["scenes.take.1.fps=25", "scenes.take.1.params.source.value=5"])
    assert config.scenes["take.1"].fps == 25 and config.scenes["take.1"].params["source"]
    assert run(cfg, "run", "all") == 0
    assert run(cfg, "run", "peek", "--set", "scenes.take.1.params.source.value=7") == 0
    assert (tmp_path / "ws" / "take.1" / "peek" / "copy.txt").read_text() == "value=7\n"
    assert counter()[-3:] == ["source", "constant", "peek"]


def test_a_folder_digest_sees_the_files_of_a_linked_folder_in_it(tmp_path):
    """The walk did not enter linked folders: a scene's `masks` folder of links to each
    camera's masks kept its digest when a mask changed, and extract stayed 'up to date'. A link
    to a folder above it does not loop."""
    from pipeline.fingerprint import HashCache

    (tmp_path / "cam01").mkdir()
    mask = tmp_path / "cam01" / "000000.png"
    mask.write_bytes(b"mask one")
    masks = tmp_path / "masks"
    masks.mkdir()
    (masks / "cam01").symlink_to(tmp_path / "cam01")
    (masks / "loop").symlink_to(masks)
    before = HashCache(None).digest(masks)
    mask.write_bytes(b"mask two")
    assert HashCache(None).digest(masks) != before

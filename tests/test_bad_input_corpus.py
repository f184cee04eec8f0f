"""Bad inputs, as users bring them, through the real CLI: every case ends with the right exit
code (2 for config and argument errors, 1 for data errors), an `error:` line that names the
file, key or camera at fault, and no output recorded as complete.

Categories: config, calibration, video, checkpoint and `--video`. The scene is a small real one:
three 12-frame videos of a moving square and their rig.json, built once per module.
"""

from __future__ import annotations

import json
import re
import textwrap
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from calibration import Camera, Rig
from calibration.camera import look_at_rotation
from calibration.formats import write_rig
from pipeline.cli import main

W, H, N_FRAMES = 160, 120, 12
CAMERAS = ("c1", "c2", "c3")


def _video(path: Path, frames: int = N_FRAMES, size: tuple[int, int] = (W, H)) -> Path:
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, size)
    for k in range(frames):
        img = np.full((size[1], size[0], 3), 40, np.uint8)
        cv2.rectangle(img, (10 + 4 * k, 30), (40 + 4 * k, 90), (200, 180, 160), -1)
        out.write(img)
    out.release()
    return path


def _rig() -> Rig:
    cams = []
    for i, name in enumerate(CAMERAS):
        a = 2 * np.pi * i / len(CAMERAS)
        centre = np.array([4 * np.cos(a), 4 * np.sin(a), 2.0])
        R = look_at_rotation(centre, np.array([0.0, 0.0, 1.0]))
        K = [[150.0, 0, (W - 1) / 2], [0, 150.0, (H - 1) / 2], [0, 0, 1]]
        cams.append(Camera.create(name, K, [], R, -R @ centre, W, H))
    return Rig(tuple(cams))


@dataclass
class Scene:
    root: Path
    videos: Path  # folder of c1.mp4, c2.mp4, c3.mp4
    rig: Path  # rig.json
    checkpoint: Path  # a tiny, valid GST checkpoint


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Scene:
    from gst.body import BodyModel
    from gst.body.random_model import random_body_data
    from gst.model.checkpoint import save_checkpoint
    from gst.model.presets import get_preset
    from gst.train.recipe import build_network

    root = tmp_path_factory.mktemp("corpus")
    videos = root / "videos"
    videos.mkdir()
    for name in CAMERAS:
        _video(videos / f"{name}.mp4")
    write_rig(_rig(), root / "rig.json", "rig")
    data = random_body_data(num_vertices=400, with_posedirs=False)
    body_file = data.save_npz(root / "body.npz")
    net, ids, groups = build_network(get_preset("tiny", vertex_preset="full"), BodyModel(data))
    save_checkpoint(root / "gst.pt", net, str(body_file), ids, groups)
    return Scene(root, videos, root / "rig.json", root / "gst.pt")


def _config(tmp: Path, scene: Scene, *, videos: str | None = None, calibration: str | None = None,
            extra_scene: str = "", stages: str | None = None) -> Path:  # fmt: skip
    videos = videos or f"{scene.videos}/c*.mp4"
    calibration = calibration or f"{{file: {scene.rig}, format: rig}}"
    stages = stages or textwrap.dedent("""
          calibrate: {}
          extract: {needs: [calibrate], params: {crop_size: 64}}
          pretrain: {}
          track: {needs: [], params: {detector: background, overlay: false}}
    """)
    cfg = tmp / "my-config.yaml"
    cfg.write_text(
        textwrap.dedent(f"""
        workspace: ws
        executor: {{kind: local, workers: 1}}
        scenes:
          s:
            videos: {videos}
            calibration: {calibration}
            {extra_scene}
        stages:
        """)
        + textwrap.indent(textwrap.dedent(stages), "  ")
    )
    return cfg


def _cli(capsys, *argv: str) -> tuple[int, str]:
    """Exit code, and what was printed: status tables on stdout, errors and logs on stderr."""
    code = main([*argv, "--quiet"])
    printed = capsys.readouterr()
    return code, printed.out + printed.err


def _assert_failed(code: int, err: str, want_code: int, names: str, workspace: Path) -> None:
    assert code == want_code, err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert lines, f"no error: line in {err!r}"
    assert re.search(names, err), f"{names!r} not named in {err!r}"
    state = workspace / "s" / ".pipeline" / "state"
    # the stage that failed has no record: nothing it wrote is presented as complete
    done = sorted(p.stem for p in state.glob("*.json")) if state.is_dir() else []
    assert all(s in ("calibrate", "pretrain") for s in done), done


# -- config: exit 2 ---------------------------------------------------------------------------

CONFIG_CASES = {
    "unknown top-level key": ("extra_top", "bogus_key: 1\n", r"bogus_key: unknown key"),
    "unknown stage parameter": ("set", "extract.crop_sise=64", r"crop_sise: unknown key.*--set"),
    "wrong type by --set": (
        "set", "extract.crop_size=big",
        r"my-config.yaml: stages.extract.params.crop_size.*--set extract.crop_size=big",
    ),
    "videos pattern matches nothing": (
        "videos", "{videos}/nothing*.mp4",
        r"scenes.s.videos: the pattern .*nothing\*.mp4' matches no file",
    ),
    "listed video missing": (
        "videos", "[{videos}/c1.mp4, {videos}/gone.mp4]",
        r"scenes.s.videos: no such file: .*gone.mp4",
    ),
    "empty video list": ("videos", "[]", r"scenes.s.videos: the list is empty"),
    # a camera is named by its file's stem: the second file silently replaced the first
    "two videos of one stem": (
        "videos", "[{videos}/c1.mp4, {videos}/other/c1.mp4]",
        r"scenes.s.videos: 2 files would be camera 'c1'",
    ),
    "one video listed twice": (
        "videos", "[{videos}/c1.mp4, {videos}/c1.mp4]",
        r"scenes.s.videos: listed twice: .*c1.mp4; remove the duplicate",
    ),
    "association key typo": (
        "set", "extract.association.merge_radus=0.6",
        r"extract.*association.*merge_radus",
    ),
    "calibration format typo": (
        "calibration", "{{file: {rig}, format: qualysis}}",
        r"scenes.s.calibration.format: unknown format 'qualysis'",
    ),
    "calibration file missing": (
        "calibration", "{{file: {root}/nope.json, format: rig}}",
        r"scenes.s.calibration.file: no such file: .*nope.json",
    ),
    "unknown scene": ("argv", "--scene nope", r"--scene: unknown scene"),
    "unknown stage": ("argv", "run nostage", r"unknown stage 'nostage'"),
    # only track reads --video: `run extract --video x` ran the scene's extract, not a word
    "--video for another stage": (
        "argv", "run extract --video x.mp4", r"--video is not an option of .extract."
    ),
    "yaml syntax": ("raw", "scenes: [unclosed\n", r"not valid YAML"),
    "needs an unknown stage": (
        "stages", "a: {needs: [zz], module: 'tests.fake_stages:SOURCE'}\n",
        r"stages.a.needs: unknown stage 'zz'",
    ),
    "negative frame-size tolerance": (
        "extra_scene", "frame_size_tolerance: -1",
        r"scenes.s.frame_size_tolerance",
    ),
    # values that passed validation and reached the stage (a 'trained' model from 0 steps, a
    # NaN learning rate failing inside torch after the upstream stages had run)
    "infinite crop scale": ("set", "extract.scale=inf", r"stages.extract.params.scale"),
    "zero crop size": ("set", "extract.crop_size=0", r"stages.extract.params.crop_size"),
    "zero board frame step": ("set", "calibrate.frame_step=0", r"params.frame_step"),
    "zero track batch": ("set", "track.batch_size=0", r"stages.track.params.batch_size"),
    "zero pretraining steps": ("set", "pretrain.lift_steps=0", r"params.lift_steps"),
}  # fmt: skip


@pytest.mark.parametrize(
    "value", [{"steps": -5}, {"steps": 0}, {"lr": float("nan")}, {"body_lr": float("inf")},
              {"batch_size": 0}, {"threads": 0}, {"num_targets": 0}],
)  # fmt: skip
def test_train_settings_refuse_values_no_training_can_use(value):
    """`train.steps=-5` trained nothing and wrote the pretrained model as the trained one;
    `train.lr=nan` failed inside torch after every upstream stage had run (the demo's config
    has a train stage, the corpus's does not: the model is checked directly)."""
    from pydantic import ValidationError

    from gst.train.scene_training import TrainSettings

    with pytest.raises(ValidationError, match=next(iter(value))):
        TrainSettings(**value)


@pytest.mark.parametrize(
    "model, value",
    [("fuse", {"smoothness": float("nan")}), ("fuse", {"people_per_batch": 0}),
     ("fuse", {"iterations": -3}), ("fuse", {"refine_rig": -1}),
     ("evaluate", {"heldout_frames": float("inf")}), ("evaluate", {"render_size": 0}),
     ("evaluate", {"render_size": 24}), ("evaluate", {"render_size": 8, "lpips": False}),
     ("bench", {"render_size": 8}),
     ("bench", {"steps": 0}), ("bench", {"lr": -1.0}), ("bench", {"test_fraction": 1.0})],
)  # fmt: skip
def test_fuse_evaluate_and_bench_settings_refuse_values_they_cannot_use(model, value):
    """These three took NaN, infinity and counts of 0 or below: a NaN smoothness fitted NaN
    bodies that went on into training, and a bad evaluate or bench value failed only after
    the stages before it had run."""
    from pydantic import ValidationError

    from gst.eval.bench_scene import BenchSettings
    from gst.eval.scene import EvaluateSettings
    from gst.fuse.settings import FuseSettings

    settings = {"fuse": FuseSettings, "evaluate": EvaluateSettings, "bench": BenchSettings}
    with pytest.raises(ValidationError, match=next(iter(value))):
        settings[model](**value)


def test_every_stage_refuses_nan_and_unknown_parameters():
    import importlib
    import pkgutil

    import stages

    for info in pkgutil.iter_modules(stages.__path__):
        stage = getattr(importlib.import_module(f"stages.{info.name}"), "STAGE", None)
        if stage is None or stage.params_model is None:
            continue
        config = stage.params_model.model_config
        assert config.get("extra") == "forbid", info.name
        assert config.get("allow_inf_nan") is False, info.name


@pytest.mark.parametrize("case", sorted(CONFIG_CASES))
def test_config_errors(case, scene, tmp_path, capsys):
    kind, value, names = CONFIG_CASES[case]
    fmt = {"videos": scene.videos, "rig": scene.rig, "root": scene.root}
    argv = ["run", "extract"]
    if kind == "videos":
        cfg = _config(tmp_path, scene, videos=value.format(**fmt))
    elif kind == "calibration":
        cfg = _config(tmp_path, scene, calibration=value.format(**fmt))
    elif kind == "extra_scene":
        cfg = _config(tmp_path, scene, extra_scene=value)
    elif kind == "stages":
        cfg = _config(tmp_path, scene, stages=value)
    else:
        cfg = _config(tmp_path, scene)
    if kind == "extra_top":
        cfg.write_text(value + cfg.read_text())
    if kind == "raw":
        cfg.write_text(value)
    if kind == "set":
        argv += ["--set", value]
    if kind == "argv":
        parts = value.split()
        argv = parts if parts[0] == "run" else argv + parts
    code, err = _cli(capsys, *argv, "--config", str(cfg))
    _assert_failed(code, err, 2, names, tmp_path / "ws")


# -- calibration: exit 1 (the file is read by the calibrate stage) ----------------------------


def _rig_json(scene: Scene, tmp: Path, edit) -> Path:
    data = json.loads(scene.rig.read_text())
    edit(data)
    out = tmp / "bad_rig.json"
    out.write_text(json.dumps(data))
    return out


CALIBRATION_CASES = {
    "NaN focal length": (lambda d: d["cameras"][0]["K"][0].__setitem__(0, float("nan")), r"c1.*K"),
    "negative focal length": (lambda d: d["cameras"][1]["K"][1].__setitem__(1, -5.0), r"c2"),
    "rotation that is not one": (lambda d: d["cameras"][2]["R"][0].__setitem__(0, 3.0), r"c3.*R"),
    "camera missing for a video": (
        lambda d: d["cameras"].pop(2),
        r"videos \['c3'\] have no camera",
    ),
    "wrong shape of t": (lambda d: d["cameras"][0].__setitem__("t", [1.0, 2.0]), r"c1.*t"),
    "missing key": (lambda d: d["cameras"][0].pop("K"), r"missing key 'K'"),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(CALIBRATION_CASES))
def test_calibration_errors(case, scene, tmp_path, capsys):
    edit, names = CALIBRATION_CASES[case]
    bad = _rig_json(scene, tmp_path, edit)
    cfg = _config(tmp_path, scene, calibration=f"{{file: {bad}, format: rig}}")
    code, err = _cli(capsys, "run", "calibrate", "--config", str(cfg))
    _assert_failed(code, err, 1, names, tmp_path / "ws")


def test_calibration_that_is_not_json(scene, tmp_path, capsys):
    bad = tmp_path / "bad_rig.json"
    bad.write_text("{ this is not json")
    cfg = _config(tmp_path, scene, calibration=f"{{file: {bad}, format: rig}}")
    code, err = _cli(capsys, "run", "calibrate", "--config", str(cfg))
    _assert_failed(code, err, 1, r"bad_rig.json", tmp_path / "ws")


# -- video: exit 1 (read by the extract stage, after a good calibration) ----------------------


def _videos_with(scene: Scene, tmp: Path, name: str, make) -> Path:
    folder = tmp / "videos"
    folder.mkdir()
    for cam in CAMERAS:
        target = folder / f"{cam}.mp4"
        if cam == name:
            make(target)
        else:
            target.write_bytes((scene.videos / f"{cam}.mp4").read_bytes())
    return folder


VIDEO_CASES = {
    "random bytes": (
        "c2", lambda p: p.write_bytes(np.random.default_rng(0).bytes(5000)),
        r"c2.*c2.mp4",
    ),
    "empty file": ("c1", lambda p: p.write_bytes(b""), r"c1.*c1.mp4"),
    "text renamed .mp4": ("c3", lambda p: p.write_text("not a video\n"), r"c3.*c3.mp4"),
    "other frame count": ("c2", lambda p: _video(p, frames=7), r"different frame counts.*c2: 7"),
    "100 rows short of the calibration": (
        "c1", lambda p: _video(p, size=(W, H - 100)),
        r"camera 'c1'.*160x20.*160x120.*frame_size_tolerance",
    ),
    "larger than the calibration": (
        "c3", lambda p: _video(p, size=(W + 32, H)),
        r"camera 'c3'.*192x120.*160x120",
    ),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(VIDEO_CASES))
def test_video_errors(case, scene, tmp_path, capsys):
    name, make, names = VIDEO_CASES[case]
    folder = _videos_with(scene, tmp_path, name, make)
    cfg = _config(tmp_path, scene, videos=f"{folder}/c*.mp4")
    code, err = _cli(capsys, "run", "extract", "--config", str(cfg))
    _assert_failed(code, err, 1, names, tmp_path / "ws")


def test_every_broken_video_is_named_at_once(scene, tmp_path, capsys):
    """An empty c1 and a corrupt c2: only c1 was named, and the user fixed and reran once per
    broken file."""
    folder = _videos_with(scene, tmp_path, "c1", lambda p: p.write_bytes(b""))
    (folder / "c2.mp4").write_bytes(np.random.default_rng(0).bytes(5000))
    cfg = _config(tmp_path, scene, videos=f"{folder}/c*.mp4")
    code, err = _cli(capsys, "run", "extract", "--config", str(cfg))
    _assert_failed(
        code,
        err,
        1,
        r"(?s)2 videos cannot be read:.*c1\.mp4: the file is empty.*c2\.mp4: OpenCV cannot",
        tmp_path / "ws",
    )


def test_video_8_rows_short_is_encoder_padding(scene, tmp_path, capsys):
    """Frames 8 rows shorter than the calibration (1080 in a 1088 calibration) pass with a
    warning: the same check that refuses 100 rows accepts padding."""
    folder = _videos_with(scene, tmp_path, "c2", lambda p: _video(p, size=(W, H - 8)))
    stages = """
          calibrate: {}
          extract: {needs: [calibrate], params: {crop_size: 64}}
          fuse: {needs: [extract], params: {overlay: true}}
          pretrain: {}
          track: {needs: [], params: {detector: background, overlay: false}}
    """
    cfg = _config(tmp_path, scene, videos=f"{folder}/c*.mp4", stages=stages)
    code, err = _cli(capsys, "run", "fuse", "--config", str(cfg))
    assert code == 0, err
    assert (tmp_path / "ws/s/crops/crops.h5").is_file()
    assert (tmp_path / "ws/s/fused/bodies.parquet").is_file()
    report = (tmp_path / "ws/s/reports/calibrate/calibration.md").read_text()
    assert "camera 'c2': frames are 160x112, the calibration says 160x120" in report
    models = tmp_path / "ws/s/models"
    models.mkdir(parents=True)
    (models / "gst.pt").write_bytes(scene.checkpoint.read_bytes())
    code, err = _cli(capsys, "run", "track", "--config", str(cfg))
    assert code == 0, err
    assert (tmp_path / "ws/s/tracks/video=c2/tracks.parquet").is_file()


# -- checkpoints: exit 1 ----------------------------------------------------------------------


def _bad_checkpoints(scene: Scene, tmp: Path) -> dict[str, tuple[Path, str]]:
    tmp.mkdir(parents=True, exist_ok=True)
    out = {}
    (tmp / "random.pt").write_bytes(np.random.default_rng(1).bytes(3000))
    out["random bytes"] = (tmp / "random.pt", r"random.pt: cannot be read as a GST checkpoint")
    (tmp / "cut.pt").write_bytes(scene.checkpoint.read_bytes()[:5000])
    out["truncated"] = (tmp / "cut.pt", r"cut.pt: cannot be read")
    torch.save({"state_dict": {}}, tmp / "other.pt")
    out["another framework's file"] = (tmp / "other.pt", r"other.pt: not a GST checkpoint")
    torch.save({"format": "gst-checkpoint", "version": 999}, tmp / "future.pt")  # a newer writer
    out["unsupported version"] = (tmp / "future.pt", r"future.pt")

    class Evil:
        def __reduce__(self):
            return (print, ("code ran",))

    torch.save({"x": Evil()}, tmp / "evil.pt")
    out["pickled code"] = (tmp / "evil.pt", r"evil.pt: cannot be read")
    ckpt = torch.load(scene.checkpoint, weights_only=True)
    ckpt["model"] = {k: v[..., :1] for k, v in ckpt["model"].items()}
    torch.save(ckpt, tmp / "shapes.pt")
    out["weights of the wrong shape"] = (tmp / "shapes.pt", r"shapes.pt")
    ckpt = torch.load(scene.checkpoint, weights_only=True)
    ckpt["vertex_ids"] = ckpt["vertex_ids"][:1]  # every Gaussian went onto one vertex, silently
    torch.save(ckpt, tmp / "ids.pt")
    out["one vertex id for every Gaussian"] = (
        tmp / "ids.pt",
        r"ids.pt: vertex_ids and group_index must be 1-D integer tensors of one length",
    )
    return out


@pytest.mark.parametrize(
    "case",
    ["random bytes", "truncated", "another framework's file", "unsupported version",
     "pickled code", "weights of the wrong shape", "one vertex id for every Gaussian"],
)  # fmt: skip
def test_track_model_errors(case, scene, tmp_path, capsys):
    bad, names = _bad_checkpoints(scene, tmp_path / "ckpts")[case]
    cfg = _config(tmp_path, scene)
    models = tmp_path / "ws/s/models"
    models.mkdir(parents=True)
    (models / "gst.pt").write_bytes(bad.read_bytes())
    code, err = _cli(capsys, "run", "track", "--config", str(cfg))
    _assert_failed(code, err, 1, names.replace(bad.name, "gst.pt"), tmp_path / "ws")
    assert "code ran" not in capsys.readouterr().out


@pytest.mark.parametrize("case", ["random bytes", "another framework's file", "pickled code"])
def test_pretrain_reuse_errors(case, scene, tmp_path, capsys):
    bad, names = _bad_checkpoints(scene, tmp_path / "ckpts")[case]
    cfg = _config(tmp_path, scene)
    code, err = _cli(
        capsys, "run", "pretrain", "--config", str(cfg), "--set", f"pretrain.reuse={bad}"
    )
    assert code == 1, err
    assert re.search(names, err), err
    assert not (tmp_path / "ws/s/.pipeline/state/pretrain.json").exists()


# -- --video: exit 2 --------------------------------------------------------------------------

VIDEO_OPTION_CASES = {
    "no such file": (["{root}/nosuch.mp4"], r"--video: no such file: .*nosuch.mp4"),
    "a folder": (["{videos}"], r"--video: a folder, not a video file: .*videos"),
    "two files with one name": (["{root}/a/clip.mp4", "{root}/b/clip.mp4"], r"share one \('clip'"),
    "one missing among good ones": (["{videos}/c1.mp4", "{root}/gone.mp4"],
                                    r"gone.mp4 \(looked for from /"),
    "one file twice": (["{videos}/c1.mp4", "{videos}/c1.mp4"],
                       r"listed twice: .*c1.mp4; remove the duplicate"),
    # through a linked folder: taken for two files sharing a name ("rename or link one")
    "one file by two paths": (["{videos}/c1.mp4", "{root}/linked/c1.mp4"],
                              r"one file listed twice: .*c1.mp4.*linked/c1.mp4"),
    # 35 CJK characters (93 bytes) take 273 once percent-encoded: an OSError traceback
    "a name too long for its tracks folder": (
        ["{root}/a/" + "決勝戦ハイライト映像" * 3 + "_前半カメラ1.mp4"],
        r"too long for its tracks folder: percent-encoded it takes \d+ bytes"),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(VIDEO_OPTION_CASES))
def test_video_option_errors(case, scene, tmp_path, capsys):
    paths, names = VIDEO_OPTION_CASES[case]
    for sub in ("a", "b"):
        (scene.root / sub).mkdir(exist_ok=True)
        clip = scene.root / sub / "clip.mp4"
        if not clip.exists():
            clip.write_bytes((scene.videos / "c1.mp4").read_bytes())
    long_name = scene.root / "a" / ("決勝戦ハイライト映像" * 3 + "_前半カメラ1.mp4")
    if not long_name.exists():
        long_name.write_bytes((scene.videos / "c1.mp4").read_bytes())
    if not (scene.root / "linked").exists():
        (scene.root / "linked").symlink_to(scene.videos)
    fmt = {"root": scene.root, "videos": scene.videos}
    argv = ["run", "track", "--config", str(_config(tmp_path, scene))]
    for p in paths:
        argv += ["--video", p.format(**fmt)]
    code, err = _cli(capsys, *argv)
    _assert_failed(code, err, 2, names, tmp_path / "ws")


def test_a_corrupt_video_given_with_video_is_a_data_error(scene, tmp_path, capsys):
    bad = tmp_path / "match.mp4"
    bad.write_bytes(np.random.default_rng(2).bytes(4000))
    cfg = _config(tmp_path, scene)
    models = tmp_path / "ws/s/models"
    models.mkdir(parents=True)
    (models / "gst.pt").write_bytes(scene.checkpoint.read_bytes())
    code, err = _cli(capsys, "run", "track", "--config", str(cfg), "--video", str(bad))
    _assert_failed(code, err, 1, r"match.mp4", tmp_path / "ws")


def test_a_still_image_and_a_corrupt_video_are_named_at_once(scene, tmp_path, capsys):
    """A photo given as --video was tracked as a one-frame video at a made-up 25 frames/s
    ("nobody was tracked in 1 frame(s)"), by its content whatever its name; and only the first
    unreadable file was named, one per rerun."""
    import cv2

    photo = tmp_path / "photo.mp4"  # a PNG under a video's name
    cv2.imwrite(str(tmp_path / "photo.png"), np.zeros((48, 64, 3), np.uint8))
    photo.write_bytes((tmp_path / "photo.png").read_bytes())
    bad = tmp_path / "match.mp4"
    bad.write_bytes(np.random.default_rng(2).bytes(4000))
    cfg = _config(tmp_path, scene)
    code, err = _cli(capsys, "run", "track", "--config", str(cfg), "--video", str(photo),
                     "--video", str(bad))  # fmt: skip
    _assert_failed(code, err, 1, r"photo.mp4: a still image, not a video", tmp_path / "ws")
    assert "match.mp4: OpenCV cannot open it" in err


# -- the defects these cases came from ----------------------------------------------------------


def test_status_and_dry_run_show_the_table_when_a_listed_video_is_missing(scene, tmp_path, capsys):
    videos = f"[{scene.videos}/c1.mp4, {scene.videos}/c2.mp4, {tmp_path}/gone.mp4]"
    cfg = _config(tmp_path, scene, videos=videos)
    code, err = _cli(capsys, "status", "--config", str(cfg))
    assert code == 0 and "gone.mp4" in err and "extract" in err, err
    code = main(["run", "extract", "--config", str(cfg), "--dry-run"])
    err = capsys.readouterr().out
    assert code == 0 and "calibrate" in err and "gone.mp4" in err, err


def _track_a_copy(scene, tmp_path, capsys, name: str) -> tuple[Path, Path]:
    """`run track --video` on a copy of camera c1's video named `name`, with the scene's model;
    returns the clip and the config."""
    clip = tmp_path / name
    clip.write_bytes((scene.videos / "c1.mp4").read_bytes())
    cfg = _config(tmp_path, scene)
    models = tmp_path / "ws/s/models"
    models.mkdir(parents=True)
    (models / "gst.pt").write_bytes(scene.checkpoint.read_bytes())
    code, err = _cli(capsys, "run", "track", "--config", str(cfg), "--video", str(clip))
    assert code == 0, err
    return clip, cfg


def test_a_video_named_like_a_calibrated_camera_says_why_it_was_taken_for_it(
    scene, tmp_path, capsys
):
    """A user's portrait clip that happens to be called c2.mp4 is taken for the scene's camera
    c2; the size mismatch said "fix the camera's image size in the calibration file", wrong
    advice for a file that is not that camera."""
    clip = _video(tmp_path / "c2.mp4", size=(H, W))
    cfg = _config(tmp_path, scene)
    models = tmp_path / "ws/s/models"
    models.mkdir(parents=True)
    (models / "gst.pt").write_bytes(scene.checkpoint.read_bytes())
    assert _cli(capsys, "run", "calibrate", "--config", str(cfg))[0] == 0  # the rig imported
    code, err = _cli(capsys, "run", "track", "--config", str(cfg), "--video", str(clip))
    assert code == 1 and "taken for the scene's calibrated camera 'c2'" in err, err
    assert "rename it if it is another camera's" in err


def test_a_missing_boxes_file_names_the_setting(scene, tmp_path, capsys):
    """`--set track.boxes=/nope.csv` ended in a bare FileNotFoundError after the model loaded."""
    cfg = _config(tmp_path, scene)
    models = tmp_path / "ws/s/models"
    models.mkdir(parents=True)
    (models / "gst.pt").write_bytes(scene.checkpoint.read_bytes())
    clip, boxes = scene.videos / "c1.mp4", tmp_path / "nope.csv"
    code, err = _cli(capsys, "run", "track", "--config", str(cfg), "--video", str(clip),
                     "--set", f"track.boxes={boxes}")  # fmt: skip
    assert code == 1 and "track.boxes: no such file: " in err and "nope.csv" in err, err


def test_a_video_name_with_spaces_is_tracked(scene, tmp_path, capsys):
    clip, cfg = _track_a_copy(scene, tmp_path, capsys, "match cam2.mp4")
    assert (tmp_path / "ws/s/tracks/video=match%20cam2/tracks.parquet").is_file()
    code, err = _cli(capsys, "status", "--config", str(cfg))
    assert "track@match_cam2" in err.replace(" ", "") or "track@match" in err, err


def test_status_after_a_tracked_video_was_moved(scene, tmp_path, capsys):
    """A `--video` run is remembered; once its clip is moved away, `status` still prints the
    table (the variant shown as missing) instead of stopping with FileNotFoundError."""
    clip, cfg = _track_a_copy(scene, tmp_path, capsys, "clip.mp4")
    clip.rename(tmp_path / "elsewhere.mp4")
    code, err = _cli(capsys, "status", "--config", str(cfg))
    assert code == 0, err
    assert "track@clip" in err.replace(" ", "") and "missing" in err, err


def test_set_with_a_malformed_scene_names_the_scene(tmp_path, capsys):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(
        "workspace: ws\ndefault_scene: demo\nscenes: {demo: synthetic}\n"
        "stages: {source: {module: 'tests.fake_stages:SOURCE'}}\n"
    )
    code, err = _cli(capsys, "status", "--config", str(cfg), "--set", "source.value=2")
    assert code == 2 and "scenes.demo" in err and "Traceback" not in err, err


def test_missing_inputs_and_a_wrong_parameter_are_said_together(scene, tmp_path, capsys):
    """A wrong stage parameter was said only once the missing videos had been fixed (one round
    trip per kind of mistake)."""
    cfg = _config(tmp_path, scene, videos=f"{scene.videos}/nothing*.mp4")
    code, err = _cli(capsys, "run", "extract", "--set", "extract.frame_stp=2", "--config", str(cfg))
    assert code == 2
    assert re.search(r"scenes\.s\.videos", err) and "frame_stp" in err, err

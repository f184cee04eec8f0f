"""Scene folders: layout and tables, determinism, and the acceptance check that ground-truth
joints projected through the *written* calibration files land on the rendered people."""

import hashlib
import json

import cv2
import h5py
import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from pydantic import ValidationError
from synth_fixtures import CapsuleBody, read_panoptic, rig_io, small_scene_spec

from synth.io import read_masks
from synth.scene import PRESETS, SceneSpec, preset, render_scene

BODY = CapsuleBody()
WRITE_RIG, READ_RIG = rig_io()


def _tiny(**overrides) -> SceneSpec:
    base = dict(
        n_frames=6,
        rig__distortion="mild",
        board__n_frames=3,
        imaging__antialias=2,
        imaging__shadow_samples=2,
    )
    return small_scene_spec(**{**base, **overrides})


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene") / "tiny"
    summary = render_scene(_tiny(), out, body_model=BODY, rig_writer=WRITE_RIG)
    return out, summary


def _digest(folder):
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_scene_layout_and_tables(tiny_scene):
    out, summary = tiny_scene
    scene = json.loads((out / "scene.json").read_text())
    cams = scene["cameras"]
    assert summary.cameras == tuple(cams) and len(cams) == 2
    assert (
        scene["n_frames"] == 6 and scene["fps"] == 30.0 and scene["world"]["up"] == [0.0, 0.0, 1.0]
    )
    assert set(json.loads((out / "board.json").read_text())) == {
        "kind",
        "squares_x",
        "squares_y",
        "square_size",
        "marker_size",
        "dictionary",
    }
    for rel in (
        "calibration/rig.json",
        "calibration/calibration_synth.json",
        "calibration/cameras.h5",
        "preview/contact_sheet.png",
        "preview/truth_overlay.png",
        "preview/board_sheet.png",
        "truth/board_poses.parquet",
        "truth/board_views.parquet",
    ):
        assert (out / rel).is_file(), rel
    for cam in cams:
        for clip, n in (("videos", 6), ("board", 3)):
            cap = cv2.VideoCapture(str(out / clip / f"{cam}.mp4"))
            frames = 0
            while True:
                ok, img = cap.read()
                if not ok:
                    break
                assert img.shape == (72, 96, 3)
                frames += 1
            assert frames == n, f"{clip}/{cam}.mp4 has {frames} frames"
        masks, depth = read_masks(out / "truth" / "masks" / f"{cam}.h5")
        assert masks.shape == (6, 72, 96) and masks.dtype == np.uint8
        assert set(np.unique(masks)) <= {0, 1, 2} and masks.max() > 0
        assert np.all((depth > 0) == (masks > 0))
    people = pq.read_table(out / "truth" / "people.parquet")
    assert people.num_rows == 12
    assert people.schema.field("joints3d").type.list_size == 72
    meta = json.loads(people.schema.metadata[b"joint_names"])
    assert meta[0] == "pelvis" and len(meta) == 24
    views = pq.read_table(out / "truth" / "views.parquet").to_pydict()
    assert len(views["frame"]) == 6 * 2 * 2
    # A visible joint is on its own person's mask; a box encloses the mask.
    masks = {c: read_masks(out / "truth" / "masks" / f"{c}.h5")[0] for c in cams}
    for i in range(len(views["frame"])):
        m = masks[views["camera"][i]][views["frame"][i]]
        uv = np.asarray(views["joints2d"][i], float).reshape(24, 2)
        vis = np.asarray(views["visible"][i])
        px = np.rint(uv[vis]).astype(int)
        assert np.all(m[px[:, 1], px[:, 0]] == views["person_id"][i])
        own = m == views["person_id"][i]
        assert own.sum() == views["mask_area"][i]
        if own.any():
            rows, cols = np.nonzero(own)
            assert views["x0"][i] == cols.min() - 0.5 and views["y1"][i] == rows.max() + 0.5


def test_truth_parameters_reproduce_joints_through_the_body_model(tiny_scene):
    out, _ = tiny_scene
    t = pq.read_table(out / "truth" / "people.parquet").to_pydict()
    n = len(t["frame"])
    col = {
        k: torch.tensor(np.asarray(t[k], np.float32)) for k in ("betas", "global_orient", "transl")
    }
    pose = torch.tensor(np.asarray(t["body_pose"], np.float32).reshape(n, 23, 3))
    joints = BODY(
        betas=col["betas"], body_pose=pose, global_orient=col["global_orient"], transl=col["transl"]
    ).joints
    assert np.abs(joints.numpy().reshape(n, -1) - np.asarray(t["joints3d"])).max() < 1e-5
    assert (
        np.asarray(t["joints3d"]).reshape(n, 24, 3)[..., 2].min() > -0.01
    )  # nobody under the floor


def test_same_seed_gives_byte_identical_files(tiny_scene, tmp_path):
    out, _ = tiny_scene
    again = tmp_path / "again"
    render_scene(_tiny(), again, body_model=BODY, rig_writer=WRITE_RIG)
    assert _digest(out) == _digest(again)
    other = tmp_path / "other"
    render_scene(_tiny(seed=1), other, body_model=BODY, rig_writer=WRITE_RIG)
    changed = {k for k, v in _digest(other).items() if _digest(out).get(k) != v}
    assert "truth/people.parquet" in changed and "videos/00_00.mp4" in changed


def test_ground_truth_projects_onto_the_rendered_people_through_written_calibration(tmp_path):
    """Acceptance: >= 95% of in-image GT joints, projected with the calibration read back from
    the written files, land inside the GT mask (strong lens distortion on purpose)."""
    spec = _tiny(
        n_frames=8, rig=dict(kind="dome", n_cameras=3, width=200, height=150, distortion="strong")
    )
    out = tmp_path / "accept"
    render_scene(spec, out, body_model=BODY, rig_writer=WRITE_RIG)
    rigs = {"panoptic": read_panoptic(out / "calibration" / "calibration_synth.json")}
    for fmt, rel in (
        ("rig", "rig.json"),
        ("panoptic", "calibration_synth.json"),
        ("h36m", "cameras.h5"),
    ):
        rigs[f"read_rig:{fmt}"] = list(READ_RIG(out / "calibration" / rel, fmt))
    joints = np.asarray(
        pq.read_table(out / "truth" / "people.parquet").column("joints3d").to_pylist()
    ).reshape(-1, 24, 3)
    people = pq.read_table(out / "truth" / "people.parquet").to_pydict()
    for source, cameras in rigs.items():
        assert len(cameras) == 3, source
        on_person = on_own = total = 0
        for cam in cameras:
            masks, _ = read_masks(out / "truth" / "masks" / f"{cam.name}.h5")
            for row in range(len(people["frame"])):
                f, pid = people["frame"][row], people["person_id"][row]
                uv = cam.project(joints[row])
                z = cam.to_camera(joints[row])[:, 2]
                inside = (
                    (z > 0)
                    & (uv[:, 0] >= 0)
                    & (uv[:, 0] <= cam.width - 1)
                    & (uv[:, 1] >= 0)
                    & (uv[:, 1] <= cam.height - 1)
                )
                px = np.rint(uv[inside]).astype(int)
                hit = masks[f][px[:, 1], px[:, 0]]
                total += int(inside.sum())
                on_person += int((hit > 0).sum())
                on_own += int((hit == pid).sum())
        assert total > 200, source
        assert on_person / total >= 0.95, (
            f"{source}: only {on_person / total:.1%} of joints on a person"
        )
        assert on_own / total >= 0.9, (
            f"{source}: only {on_own / total:.1%} of joints on their own person"
        )


def test_failed_render_leaves_previous_scene_untouched(tiny_scene, tmp_path):
    out, _ = tiny_scene
    target = tmp_path / "scene"
    render_scene(_tiny(), target, body_model=BODY, rig_writer=WRITE_RIG)
    before = _digest(target)

    def broken_writer(rig, path, fmt):
        raise OSError(f"disk full while writing {fmt}")

    with pytest.raises(OSError, match="disk full"):
        render_scene(_tiny(seed=5), target, body_model=BODY, rig_writer=broken_writer)
    assert _digest(target) == before
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]  # no partial folders left behind


def test_presets_and_validation():
    assert set(PRESETS) == {"demo", "crowd", "small", "full"}
    demo = preset("demo")
    assert 4 <= demo.rig.n_cameras <= 6 and demo.rig.width * demo.rig.height <= 480 * 360
    assert 1 <= demo.n_people <= 2 and 30 <= demo.n_frames <= 60
    assert preset("demo", rig__width=320).rig.width == 320
    assert preset("demo", rig={"n_cameras": 4}).rig.n_cameras == 4
    assert preset("small", seed=3).seed == 3
    with pytest.raises(KeyError, match="unknown synth preset 'huge'"):
        preset("huge")
    with pytest.raises(ValidationError, match="n_cameras"):
        preset("demo", rig={"n_cameras": 0})
    with pytest.raises(ValidationError, match="motions has 1 programmes but n_people is 2"):
        preset("demo", motions=[["run"]])
    with pytest.raises(ValidationError, match="extra"):
        preset("demo", colour="red")
    with pytest.raises(ValidationError, match="marker_size"):
        preset("demo", board={"marker_size": 0.5})


@pytest.mark.parametrize(
    ("key", "said"),
    [("rig__width__x", "rig.width is 480"), ("name__x", "name is 'demo'"),
     ("rig.distortion.k1", "rig.distortion is 'mild'"), ("motions__0", "motions is")],
)  # fmt: skip
def test_an_override_into_a_field_that_holds_no_fields_names_the_key(key, said):
    """`rig__width__x` failed with "'int' object is not iterable" and `name__x` with
    "dictionary update sequence element #0 has length 1; 2 is required": neither named the
    key nor the field."""
    with pytest.raises(TypeError, match="not a group of fields") as err:
        preset("demo", **{key: 1})
    assert key.replace(".", "__") in str(err.value) and said in str(err.value)


def test_changing_a_presets_fields_leaves_the_preset_alone():
    """preset_fields returned the preset's own nested dicts and lists (those no override
    touched): setting fields["rig"]["n_cameras"] made every later preset("demo") a 2-camera
    scene, and appending to a programme changed the demo's motions."""
    from synth.spec import preset_fields

    before = preset("demo")
    fields = preset_fields("demo", board__n_frames=3)
    fields["rig"]["n_cameras"] = 2
    fields["motions"][0].append("walk")
    fields["board"]["squares_x"] = 9
    assert preset("demo") == before


def test_missing_body_model_api_is_reported(tmp_path):
    class NotABody:
        faces = np.zeros((1, 3), int)

    with pytest.raises(TypeError, match="lacks"):
        render_scene(_tiny(), tmp_path / "x", body_model=NotABody(), rig_writer=WRITE_RIG)


def test_masks_file_is_plain_hdf5(tiny_scene):
    out, _ = tiny_scene
    with h5py.File(out / "truth" / "masks" / "00_00.h5") as f:
        assert f.attrs["camera"] == "00_00"
        assert f["mask"].chunks == (1, 72, 96) and f["mask"].compression == "gzip"


def test_board_clip_starts_flat_on_the_floor_at_the_world_origin():
    from synth.board import FLOOR_BOARD_R, ChArUcoSpec, board_clip

    spec = ChArUcoSpec()
    poses = board_clip(spec, 200, (0, 0, 1.0), 1.5, np.random.default_rng(0), floor_frames=3)
    assert len(poses) == 200
    for p in poses[:3]:
        assert np.array_equal(p.R, FLOOR_BOARD_R) and np.allclose(p.t, [0, 0, 0.001])
        assert np.allclose(p.front_normal, [0, 0, 1])  # printed side up
    # Lifting and moving never puts a corner of the sheet under the floor, and moves smoothly.
    W, H = spec.size
    m = spec.margin
    outline = np.array([[-m, -m, 0], [W + m, -m, 0], [-m, H + m, 0], [W + m, H + m, 0]])
    assert min(p.to_world(outline)[:, 2].min() for p in poses) > 0
    centres = np.array([p.to_world(np.array([W / 2, H / 2, 0])) for p in poses])
    assert (
        np.linalg.norm(np.diff(centres, axis=0), axis=1).max() < 0.25
    )  # 200 frames: no teleporting


@pytest.mark.slow
def test_board_calibration_recovers_the_synthetic_rig(tmp_path):
    """End to end: calibration.solve on the rendered board clip finds synth's cameras in synth's
    world (the clip's first pose lies on the floor at the origin)."""
    solve = pytest.importorskip("calibration.solve")
    board_mod = pytest.importorskip("calibration.board")
    spec = preset("demo", n_frames=1, n_people=1, motions=[["idle"]])
    out = tmp_path / "scene"
    render_scene(spec, out, body_model=BODY, rig_writer=WRITE_RIG)
    board = board_mod.BoardSpec.from_dict(json.loads((out / "board.json").read_text()))
    result = solve.calibrate_from_board(
        {p.stem: p for p in sorted((out / "board").glob("*.mp4"))}, board
    )
    truth = READ_RIG(out / "calibration" / "rig.json", "rig")
    for cam in result.rig:
        true = truth[cam.name]
        assert np.linalg.norm(cam.center - true.center) < 0.08, cam.name
        assert abs(cam.fx / true.fx - 1) < 0.03, cam.name


@pytest.mark.parametrize("kind", ["dome", "h36m", "hall"])
def test_every_rig_kind_writes_the_same_cameras_in_every_format(kind, tmp_path):
    """Sampled distortion is radial only, so rig.json, Panoptic and H36M hold the cameras
    exactly."""
    from synth.rigs import make_rig

    spec = _tiny(
        n_frames=2,
        n_people=1,
        motions=[["idle"]],
        board={"n_frames": 1},
        rig=dict(kind=kind, n_cameras=2, width=64, height=48, distortion="strong"),
    )
    out = tmp_path / kind
    render_scene(spec, out, body_model=BODY, rig_writer=WRITE_RIG)
    truth = make_rig(kind, n_cameras=2, width=64, height=48, distortion="strong", seed=spec.seed)
    readers = {"panoptic": lambda: read_panoptic(out / "calibration" / "calibration_synth.json")}
    for fmt, rel in (
        ("rig", "rig.json"),
        ("panoptic", "calibration_synth.json"),
        ("h36m", "cameras.h5"),
    ):
        readers[f"read_rig:{fmt}"] = lambda fmt=fmt, rel=rel: list(
            READ_RIG(out / "calibration" / rel, fmt)
        )
    pts = np.random.default_rng(0).uniform([-1.5, -1.5, 0], [1.5, 1.5, 2], (50, 3))
    for source, read in readers.items():
        cams = {c.name: c for c in read()}
        assert set(cams) == set(truth.names), source
        for cam in truth.cameras:
            got = cams[cam.name]
            assert (got.width, got.height) == (64, 48), source
            assert np.abs(got.project(pts) - cam.project(pts)).max() < 1e-6, f"{source}: {cam.name}"
    assert json.loads((out / "scene.json").read_text())["calibration_notes"] == {}


def test_a_folder_that_is_no_scene_is_not_replaced(tmp_path):
    """render_scene replaces its output folder whole; pointed at a workspace (the package's
    own example said "workspace/demo") it deleted the user's models and calibration."""
    target = tmp_path / "workspace_demo"
    (target / "models").mkdir(parents=True)
    (target / "models" / "gst.pt").write_bytes(b"weights")
    with pytest.raises(ValueError, match="not a synthetic scene"):
        render_scene(_tiny(), target, body_model=BODY, rig_writer=WRITE_RIG)
    assert (target / "models" / "gst.pt").read_bytes() == b"weights"


def test_a_file_where_the_scene_goes_is_not_replaced(tmp_path):
    """A plain file at the output path was replaced by the scene folder without a word."""
    target = tmp_path / "notes.txt"
    target.write_text("precious\n")
    with pytest.raises(ValueError, match="is a file or a link"):
        render_scene(_tiny(), target, body_model=BODY, rig_writer=WRITE_RIG)
    assert target.read_text() == "precious\n"


def test_odd_image_sizes_are_refused(tmp_path):
    """The mp4v encoder drops an odd last column or row: a 97x73 rig gave 96x72 videos beside a
    calibration, masks and scene.json of 97x73 (the truth described pixels the video lacks)."""
    from synth.io import VideoOut

    with pytest.raises(ValidationError, match="multiple of 2"):
        preset("demo", rig={"width": 97})
    for size in ((97, 72), (64, 73), (8192, 64)):
        with pytest.raises(ValueError, match="must be even and at most 8190"):
            VideoOut(tmp_path / "v.mp4", 30.0, *size)
    assert not list(tmp_path.iterdir())


def test_preset_takes_a_scene_name_and_random_static_stands_alone():
    assert preset("demo", name="my_scene").name == "my_scene"  # was a TypeError
    with pytest.raises(ValueError, match="'random_static' must be the only motion"):
        preset("demo", n_people=2, motions=[["random_static", "run"], ["jump"]])


def test_a_crowd_that_cannot_keep_its_rules_says_so(caplog):
    from synth.crowd import place_crowd
    from synth.motions import generate_motion

    rng = np.random.default_rng(0)
    clips = [generate_motion(["idle"], 10, 30.0, np.random.default_rng(k)) for k in range(12)]
    with caplog.at_level("WARNING", logger="synth.crowd"):
        place_crowd(clips, rng, (0.0, 0.0, 0.0), 0.6)  # 12 people in a 0.6 m circle
    assert any("could not be placed within the rules" in m for m in caplog.messages)


@pytest.mark.parametrize(
    "block, said",
    [("{preset: demo, overrides: {seed: 3}}", "scenes.s.synthetic: overrides.seed: give the"),
     ("{preset: dmeo}", "scenes.s.synthetic: preset: unknown synth preset 'dmeo'"),
     ("{preset: demo, overrides: {n_frame: 4}}", "scenes.s.synthetic: overrides.n_frame: unknown"),
     ("{preset: demo, overrides: {rig: {widht: 9}}}", "overrides.rig.widht: unknown key"),
     # the nearest key, as everywhere else in the file
     ("{preset: demo, overrides: {n_fraems: 4}}", "overrides.n_fraems: unknown key (did you mean "
      "'n_frames'?)"),
     # text for numbers and flags was converted without a word (the rest of the file is strict)
     ("{preset: demo, overrides: {n_frames: '10'}}", "overrides.n_frames: Input should be a valid "
      "integer (got '10')"),
     ("{preset: demo, overrides: {rig: {fps: '30'}}}", "overrides.rig.fps: Input should be a "),
     # every problem, each with its value (only the first was said, without the value)
     ("{preset: demo, overrides: {n_people: 0, rig: {width: 3}}}", "overrides.n_people: Input "
      "should be greater than or equal to 1 (got 0); overrides.rig.width: Input should be a "
      "multiple of 2 (got 3)"),
     ("{preset: demo, overrides: {n_frames__x: 5}}", "overrides: ['n_frames__x']: "),
     ("{preset: demo, seed: -1}", "scenes.s.synthetic.seed: Input should be greater than"),
     ("{preset: demo, overrides: {rig: {width: 97}}}", "overrides.rig.width: Input should be a "
      "multiple of 2"),
     ("{preset: demo, overrides: {motions: [[runn], [jump]]}}", "unknown motions ['runn']"),
     ("{preset: demo, overrides: {board: {dictionary: DICT_4X4_5O}}}", "unknown ArUco"),
     ("{preset: demo, overrides: {board: {squares_x: 12, squares_y: 10}}}", "needs 60 markers"),
     ("{preset: demo, overrides: {rig: {distortion: [0.1, 0.2, 0.0]}}}", "4 or 5 finite")],
)  # fmt: skip
def test_a_synthetic_block_that_makes_no_scene_is_refused_before_anything_runs(
    tmp_path, capsys, block, said
):
    """`overrides: {seed: 3}` gave "TypeError: preset() got multiple values for keyword
    argument 'seed'", and a misspelt preset or override key failed in the synth stage with a
    traceback: they are config errors (exit 2), naming the key, before any stage runs."""
    from pipeline.cli import main

    cfg = tmp_path / "pipeline.yaml"
    cfg.write_text(f"workspace: ws\nscenes:\n  s: {{synthetic: {block}}}\nstages:\n  synth: {{}}\n")
    assert main(["run", "synth", "--config", str(cfg), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert said in err and "Traceback" not in err
    assert not (tmp_path / "ws").exists()


@pytest.mark.parametrize(
    ("rel", "column"),
    [("truth/people.parquet", "frame"), ("truth/people.parquet", "betas"),
     ("truth/views.parquet", "camera"), ("truth/views.parquet", "mask_area")],
)  # fmt: skip
def test_truth_tables_missing_a_column_name_the_file(tiny_scene, tmp_path, rel, column):
    """A truth table without `frame`, `betas`, `camera` or `mask_area` raised a bare KeyError
    ('Field "frame" does not exist in schema') naming no file."""
    from synth.truth import read_scene_truth, read_truth_views

    src, _ = tiny_scene
    table = pq.read_table(src / rel)
    (tmp_path / "truth").mkdir()
    pq.write_table(table.drop_columns([column]), tmp_path / rel)
    read = read_scene_truth if rel.endswith("people.parquet") else read_truth_views
    with pytest.raises(ValueError, match=rf"{rel}: columns \['{column}'\] are missing"):
        read(tmp_path)


def test_a_scene_without_a_board_clip_lists_only_the_files_it_wrote(tmp_path):
    """scene.json listed board videos and board truth tables that a scene rendered with
    board.n_frames 0 never wrote; calibrating from that board failed with "no camera sources
    given", a message that named neither the scene nor the way out."""
    from calibration.board import BoardSpec
    from calibration.scene import BoardFootage, calibrate_scene

    out = tmp_path / "noboard"
    render_scene(
        small_scene_spec(n_frames=1, n_people=1, motions=None, board__n_frames=0),
        out,
        body_model=BODY,
        rig_writer=WRITE_RIG,
    )
    scene = json.loads((out / "scene.json").read_text())
    listed = [v for v in scene["files"].values() if isinstance(v, str)]
    for rel in listed:
        for cam in scene["cameras"]:
            assert (out / rel.replace("<camera>", cam)).exists(), rel
    assert "board_videos" not in scene["files"] and "videos" in scene["files"]
    board = BoardSpec.from_dict(json.loads((out / "board.json").read_text()))
    with pytest.raises(ValueError, match="no board footage.*synthetic_source"):
        calibrate_scene(
            {}, tmp_path / "rig.json", tmp_path / "reports", footage=BoardFootage({}, board)
        )


def test_board_truth_lists_no_corner_the_room_hides(tmp_path):
    """A large board in the H36M room reaches through the ceiling, which hides that part of it
    in the board videos; board_views.parquet still listed those corners as seen (37 of 2298 on
    this rig), so a calibration scored against the truth counted corners no image shows."""
    import pyarrow.parquet as pq

    from synth.shares import SceneSetup

    spec = small_scene_spec(
        n_frames=1,
        n_people=1,
        motions=None,
        rig__kind="h36m",
        rig__n_cameras=4,
        rig__fov_deg=100.0,
        board__n_frames=30,
        board__squares_x=8,
        board__squares_y=6,
        board__square_size=0.45,
        board__marker_size=0.3,
    )
    out = tmp_path / "bigboard"
    render_scene(spec, out, body_model=BODY, rig_writer=WRITE_RIG)
    setup = SceneSetup.build(spec)  # the same rig, room and board path as the render's
    cams = {c.name: c for c in setup.rig.cameras}
    listed = 0
    for row in pq.read_table(out / "truth" / "board_views.parquet").to_pylist():
        cam, pose = cams[row["camera"]], setup.board_poses[row["frame"]]
        corners = pose.to_world(setup.board.corners[row["corner_ids"]])
        ray = corners - cam.center
        dist = np.linalg.norm(ray, axis=1)
        room_t, _, _ = setup.stage.intersect(cam.center, ray / np.maximum(dist, 1e-12)[:, None])
        # the renderer shows the board where its ray meets it before the room's surface
        assert np.all(dist < room_t), (row["frame"], row["camera"])
        listed += len(corners)
    assert listed > 1000

"""Truth mapped onto crops of a rendered tiny scene agrees with synth's own truth crops, and the
report files exist and are well formed."""

from __future__ import annotations

import csv
import json
import shutil

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from synth_fixtures import CapsuleBody, rig_io, small_scene_spec
from test_evaluate_metrics import JOINTS
from test_train_recipe import crop_set

import gst.train.scene_truth as scene_truth
from calibration.formats import read_rig
from gst.body import BodyModel
from gst.body.random_model import random_body_data
from gst.eval.evaluate import EvalConfig, evaluate_model
from gst.eval.report import write_report
from gst.model.presets import get_preset
from gst.train.losses import LossWeights
from gst.train.recipe import build_network, make_task
from gst.train.scene_truth import attach_scene_truth
from gst.train.synthetic_crops import crops_from_synth_scene
from gst.video import iter_frames
from synth.scene import render_scene
from synth.truth import has_scene_truth, read_scene_truth, truth_mask_file

BODY = CapsuleBody()


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene") / "tiny"
    render_scene(small_scene_spec(), out, body_model=BODY, rig_writer=rig_io()[0])
    return out


def test_attached_truth_matches_synth_truth_crops(tiny_scene):
    crops = crops_from_synth_scene(tiny_scene, crop_size=64, min_mask_area=20, min_visible_joints=1)
    reference = {k: v.clone() for k, v in crops.truth.items()}
    views = pq.read_table(tiny_scene / "truth" / "views.parquet").to_pydict()
    key = {
        (f, p, c): i
        for i, (f, p, c) in enumerate(
            zip(views["frame"], views["person_id"], views["camera"], strict=True)
        )
    }
    # undistorted rig: the extracted person box is the truth box (pixel-centre edges -> edges)
    boxes = np.array(
        [
            [
                views[k][key[(int(f), int(p), crops.camera_names[int(c)])]] + 0.5
                for k in ("full_x0", "full_y0", "full_x1", "full_y1")
            ]
            for f, p, c in zip(crops.frame, reference["person_truth_id"], crops.camera, strict=True)
        ]
    )
    crops.truth = {}
    truth = attach_scene_truth(crops, boxes, tiny_scene)
    assert bool(crops.truth["has_truth"].all())
    t = crops.truth
    assert (truth.person_id[t["truth_row"].numpy()] == reference["person_truth_id"].numpy()).all()
    for k in ("joints_world", "joints_cam", "joints2d", "visible", "betas"):
        assert torch.allclose(t[k].float(), reference[k].float(), atol=1e-4), k
    assert torch.allclose(t["rotmats_cam"], reference["rotmats_cam"], atol=1e-5)
    assert set(truth.motion) <= {"run", "squat"}
    # truth meshes posed from the written parameters reproduce the written joints
    out = BODY(
        betas=torch.from_numpy(truth.betas),
        body_pose=torch.from_numpy(truth.body_pose),
        global_orient=torch.from_numpy(truth.global_orient),
        transl=torch.from_numpy(truth.transl),
    )
    assert np.abs(out.joints.numpy()[:, :24] - truth.joints_world).max() < 1e-4
    # a crop that shows nobody of the truth carries zeros and the rest pose, as documented
    # (its betas and rotations were truth row 0's)
    import gst.train.scene_truth as scene_truth

    matched = scene_truth.match_truth_views(crops, boxes, tiny_scene)
    matched[0] = -1
    crops.truth = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(scene_truth, "match_truth_views", lambda *args: matched)
        attach_scene_truth(crops, boxes, tiny_scene)
    t = crops.truth
    assert not bool(t["has_truth"][0]) and bool(t["has_truth"][1:].all())
    assert not t["betas"][0].any() and not t["joints_world"][0].any()
    assert torch.equal(t["rotmats_cam"][0], torch.eye(3).expand(24, 3, 3))
    assert torch.allclose(t["betas"][1:].float(), reference["betas"][1:].float(), atol=1e-4)


def test_a_crop_is_matched_to_the_person_its_mask_shows_not_its_box(tiny_scene):
    """Matched by box overlap alone, a person behind someone took the front person's truth (their
    box overlaps the other's full box more): 9.4 % of crowd_7001's crops were scored against
    another body. Here every crop gets the box of another person in its frame and camera: the
    masks still say who is who."""
    crops = crops_from_synth_scene(tiny_scene, crop_size=64, min_mask_area=20, min_visible_joints=1)
    people = crops.truth["person_truth_id"].numpy()
    views = pq.read_table(tiny_scene / "truth" / "views.parquet").to_pydict()
    key = {
        (f, p, c): i
        for i, (f, p, c) in enumerate(
            zip(views["frame"], views["person_id"], views["camera"], strict=True)
        )
    }

    def box(i: int) -> list[float]:
        k = key[(int(crops.frame[i]), int(people[i]), crops.camera_names[int(crops.camera[i])])]
        return [views[c][k] + 0.5 for c in ("full_x0", "full_y0", "full_x1", "full_y1")]

    swapped, boxes = 0, []
    for i in range(len(crops)):
        same = [
            j for j in range(len(crops))
            if j != i and crops.frame[j] == crops.frame[i] and crops.camera[j] == crops.camera[i]
        ]  # fmt: skip
        boxes.append(box(same[0]) if same else box(i))
        swapped += bool(same)
    assert swapped >= 10
    crops.truth = {}
    truth = attach_scene_truth(crops, np.array(boxes), tiny_scene)
    assert bool(crops.truth["has_truth"].all())
    np.testing.assert_array_equal(truth.person_id[crops.truth["truth_row"].numpy()], people)


def test_a_crop_spilling_onto_the_person_in_front_keeps_its_own_person(tiny_scene, tmp_path):
    """Per (frame, camera) crops and truth people are paired one-to-one: a crop whose mask lands
    mostly on the person in front of it (its own person hidden behind them) is not scored
    against that person when they have a crop of their own. By majority alone the demo's crop
    370 was scored against the person in front (371 mm; 252 against its own)."""
    import h5py

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    crops = crops_from_synth_scene(scene, crop_size=64, min_mask_area=20, min_visible_joints=1)
    people = crops.truth["person_truth_id"].numpy()
    pairs = [
        (i, j)
        for i in range(len(crops))
        for j in range(len(crops))
        if i != j and crops.frame[i] == crops.frame[j] and crops.camera[i] == crops.camera[j]
    ]
    # the crop with the largest mask in its pair is the one whose person is painted over
    a, b = max(pairs, key=lambda ij: float(crops.masks[ij[0]].sum() - crops.masks[ij[1]].sum()))
    frame, camera = int(crops.frame[a]), crops.camera_names[int(crops.camera[a])]
    with h5py.File(truth_mask_file(scene, camera), "r+") as f:
        ids = f["mask"][frame]
        vv, uu = np.nonzero(ids == people[a])
        top = vv < np.quantile(vv, 0.65)  # the upper 65 % of a's pixels now show b in front
        ids[vv[top], uu[top]] = people[b]
        f["mask"][frame] = ids
    rig = read_rig(scene / "calibration" / "rig.json", "rig")
    hits = scene_truth.mask_hits(crops, scene, rig)
    assert hits[a][people[b]] > 0.5 * hits[a].sum() > 0  # a's majority is now b
    shown = scene_truth.mask_truth_ids(crops, scene, rig)
    assert shown[a] == people[a] and shown[b] == people[b]


def test_a_duplicate_crop_is_scored_against_the_person_it_shows():
    """More crops than people in a (frame, camera): the one left without a partner keeps the
    person most of its mask shows; crops of other frames or cameras are paired apart."""
    hits = [np.array([0, 40, 2]), np.array([0, 90, 0]), np.array([0, 3, 50]), np.array([0, 9])]
    keys = [(0, 0), (0, 0), (0, 0), (1, 0)]
    np.testing.assert_array_equal(scene_truth.shown_ids(keys, hits), [1, 1, 2, 1])
    # a crop whose partner holds under `min_partner_share` of its hits and has no majority
    spill = [np.array([0, 10, 12, 11]), np.array([0, 0, 50, 0]), np.array([0, 60, 0, 0])]
    np.testing.assert_array_equal(scene_truth.shown_ids([(0, 0)] * 3, spill, 0.5, 0.4), [0, 2, 1])
    assert scene_truth.shown_ids([(0, 0)], [np.zeros(0, np.int64)]).tolist() == [0]


def test_truth_views_past_a_cut_video_are_left_out_with_a_word(tiny_scene, tmp_path, caplog):
    """A scene whose video was cut short (a copy interrupted) lost its last frames' crops
    without a word."""
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    video = sorted((scene / "videos").glob("*.mp4"))[0]
    frames = [f.image for f in iter_frames(video)]
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (w, h))
    for f in frames[:2]:
        writer.write(f)
    writer.release()
    with caplog.at_level("WARNING", logger="gst.train"):
        crops = crops_from_synth_scene(scene, crop_size=64, min_mask_area=20,
                                       min_visible_joints=1)  # fmt: skip
    said = [m for m in caplog.messages if "past the video's end are left out" in m]
    assert len(said) == 1 and f"camera {video.stem}'s video holds 2 frames" in said[0]
    cam = crops.camera_names.index(video.stem)
    assert int(crops.frame[crops.camera == cam].max()) == 1


def test_no_truth_is_reported(tmp_path):
    assert not has_scene_truth(tmp_path)
    with pytest.raises(FileNotFoundError, match="no truth"):
        read_scene_truth(tmp_path)


def test_report_files_are_well_formed(tmp_path):
    body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
    cfg = get_preset("tiny", vertex_preset="full")
    net, ids, _ = build_network(cfg, body)
    task = make_task(body, ids, cfg, 64, LossWeights(lpips=0.0))
    crops = crop_set(n_frames=3, n_cams=3)
    res = evaluate_model(
        net, task, crops, EvalConfig(heldout_cameras=("c2",), render_size=32), joint_names=JOINTS
    )
    doc = write_report(
        tmp_path, {"gst": res}, crops, {"scene": "test", "models": {"gst": "random"}}
    )
    names = {p.name for p in tmp_path.iterdir()}
    assert {
        "summary.json",
        "report.md",
        "per_crop.csv",
        "per_view.csv",
        "per_camera.png",
        "per_part.png",
        "per_motion.png",
        "side_by_side.png",
    } <= names
    loaded = json.loads((tmp_path / "summary.json").read_text())
    assert loaded == json.loads(json.dumps(doc, default=float))
    assert loaded["format"] == "gst-capture/evaluation"
    with open(tmp_path / "per_crop.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(crops)
    mean = np.mean([float(r["mpjpe_mm"]) for r in rows])
    assert loaded["models"]["gst"]["pose"]["overall"]["mpjpe_mm"] == pytest.approx(mean, abs=1e-2)
    md = (tmp_path / "report.md").read_text()
    assert "| MPJPE (mm) |" in md and "![side by side](side_by_side.png)" in md
    # no truth mesh: the box is the joints' (it was always called the truth body's, 5 cm)
    assert loaded["models"]["gst"]["counts"]["sherf_box"] == "joints"
    assert "reference joints (15 cm margin" in md and "(5 cm margin)" not in md
    for png in ("per_camera.png", "side_by_side.png"):
        img = cv2.imread(str(tmp_path / png))
        assert img is not None and img.shape[0] > 10


def test_a_side_by_side_input_whose_prediction_is_not_finite_leaves_the_report(
    tmp_path, monkeypatch
):
    """The first inputs' pairs are kept for the side-by-side figure before they are predicted;
    one whose prediction was not finite has no render, and the figure failed with KeyError
    after the whole evaluation, leaving no report at all."""
    import gst.eval.evaluator as evaluator
    from gst.body.model import NonFiniteBatch

    body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
    cfg = get_preset("tiny", vertex_preset="full")
    torch.manual_seed(0)
    net, ids, _ = build_network(cfg, body)
    task = make_task(body, ids, cfg, 64, LossWeights(lpips=0.0))
    crops = crop_set(n_frames=2, n_cams=3)
    bad, predict = crops.images[0].clone(), evaluator.predict

    def predict_but_crop_0(model, task, images, *args, **kwargs):
        hit = [i for i in range(len(images)) if torch.equal(images[i], bad)]
        if hit:
            raise NonFiniteBatch("betas", hit)
        return predict(model, task, images, *args, **kwargs)

    monkeypatch.setattr(evaluator, "predict", predict_but_crop_0)
    config = EvalConfig(heldout_cameras=("c2",), render_size=32)
    res = evaluate_model(net, task, crops, config, joint_names=JOINTS)
    assert res.summary.pose.overall["n_not_finite"] == 1
    assert any(k not in res.views.images for k in res.side_by_side)  # the case at hand
    write_report(tmp_path, {"gst": res}, crops, {"scene": "test"})
    assert (tmp_path / "summary.json").is_file() and (tmp_path / "side_by_side.png").is_file()


def test_the_report_names_its_reference_and_an_empty_held_out_camera(tmp_path):
    """On a real scene report.md said "Evaluation against the synthetic truth" above the note
    that the reference is the rig's fused bodies; a held-out camera where no scored person was
    seen dropped the novel-view rows without a word."""
    body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
    cfg = get_preset("tiny", vertex_preset="full")
    net, ids, _ = build_network(cfg, body)
    task = make_task(body, ids, cfg, 64, LossWeights(lpips=0.0))
    crops = crop_set(n_frames=2, n_cams=3)
    crops.truth["has_truth"] = crops.camera != 2  # the held-out camera never saw the person
    res = evaluate_model(
        net, task, crops, EvalConfig(heldout_cameras=("c2",), render_size=32), joint_names=JOINTS
    )
    ref = "the rig's fused bodies (agreement, not error)"
    write_report(tmp_path, {"gst": res}, crops, {"scene": "lab", "reference": ref})
    md = (tmp_path / "report.md").read_text()
    assert md.startswith("# Evaluation against the rig's fused bodies")
    assert "synthetic truth" not in md and "crops with a fused body" in md
    assert "No novel-view pair has its target in a held-out camera (c2)" in md


def test_crops_left_out_of_the_errors_are_counted_in_the_headline():
    """A model whose prediction was NaN on 4 of 10 crops was averaged over the other 6 and
    could win the headline; report.md never said so."""
    from gst.eval.report import _markdown

    def summary(mpjpe, bad):
        overall = {"n": 10, "n_not_finite": bad, "mpjpe_mm": mpjpe, "pa_mpjpe_mm": mpjpe / 2}
        return {
            "counts": {"pose_crops": 10, "view_pairs": 0, "render_size": 32, "heldout_cameras": []},
            "pose": {"overall": overall, "per_camera": {}, "per_part": {}, "per_motion": {}},
        }

    md = _markdown({"pretrained": summary(100.0, 0), "gst": summary(80.0, 4)}, {}, [], False)
    row = next(line for line in md.splitlines() if "not finite" in line)
    assert row.endswith("| 0 of 10 | 4 of 10 |")
    clean = _markdown({"gst": summary(80.0, 0)}, {}, [], False)
    assert "not finite" not in clean


def test_the_per_motion_table_counts_crops_and_held_out_pairs_apart():
    """The image columns average held-out view pairs, not the motion's crops: the table's
    single `n` was the crop count (the demo's 144 crops beside 24 pairs)."""
    from gst.eval.report import _markdown

    overall = {"n": 3, "n_not_finite": 0, "mpjpe_mm": 90.0, "pa_mpjpe_mm": 60.0}
    summary = {
        "counts": {"pose_crops": 3, "view_pairs": 2, "render_size": 32, "heldout_cameras": ["c2"]},
        "pose": {
            "overall": overall,
            "per_camera": {},
            "per_part": {},
            "per_motion": {"run": overall, "squat": {**overall, "n": 5}},
        },
        "novel_view": {
            "heldout": {"n": 2, "psnr": 20.0},
            "trained_views": {},
            "per_target_camera": {},
            "per_motion": {"run": {"n": 2, "psnr": 20.0, "lpips": 0.2}},
        },
    }
    md = _markdown({"gst": summary}, {}, [], False)
    assert "| motion | crops | MPJPE | PA-MPJPE | held-out pairs |" in md
    assert "| run | 3 | 90.0 | 60.0 | 2 | 20.00 | 0.200 |" in md
    assert "| squat | 5 | 90.0 | 60.0 | 0 | n/a | n/a |" in md

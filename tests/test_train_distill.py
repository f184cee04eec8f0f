"""Distillation from the rig (gst.train.distill): targets are never drawn from held-out cameras
or frames, they follow the fused bodies where they are drawn, and the loss terms behave."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from gst.fuse import FitOptions, FuseOptions, fuse_scene
from gst.fuse.tables import read_fused_bodies
from gst.lift.teacher import RigTeacher
from gst.model.assemble import BodyPrediction
from gst.train.distill import (
    distill_targets,
    distill_terms,
    training_rows,
)
from gst.train.views import heldout_frame_start, load_cropset
from tests.fuse_fixtures import capture_in_store

OPTS = FuseOptions(fit=FitOptions(iterations=40), overlay=False)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    torch.set_num_threads(1)
    tmp = tmp_path_factory.mktemp("distill")
    cap, landmarks = capture_in_store(tmp, n_people=2, n_frames=6, n_cams=4, seed=3)
    # the fuse stage's output: every camera and frame
    fuse_scene(tmp / "crops.h5", cap.rig, tmp / "fused", tmp / "report", fps=30.0,
               options=OPTS, landmarks=landmarks)  # fmt: skip
    crops, _ = load_cropset(tmp / "crops.h5")
    return tmp, cap, landmarks, crops, read_fused_bodies(tmp / "fused" / "bodies.parquet")


def test_heldout_frames_are_the_last_share_of_the_frames():
    frames = torch.tensor([0, 0, 1, 2, 3, 3, 5, 6, 7, 9])  # 8 distinct frames
    assert heldout_frame_start(frames, 0.25) == 7  # the last 2 distinct frames: 7 and 9
    assert heldout_frame_start(frames, 0.5) == 5  # 5, 6, 7, 9
    assert heldout_frame_start(frames, 0.0) is None
    assert heldout_frame_start(frames, 0.01) == 9  # at least one frame
    # a share that rounds to every frame is refused, naming the setting (training then failed
    # on "no training samples", blaming the cameras)
    with pytest.raises(ValueError, match="heldout_frames=0.92 holds out all 6 frames"):
        heldout_frame_start(torch.arange(6), 0.92)
    assert heldout_frame_start(torch.arange(6), 0.9) == 1
    with pytest.raises(ValueError, match=r"\[0, 1\)"):
        heldout_frame_start(frames, 1.0)


def test_targets_are_never_drawn_from_heldout_cameras_or_frames(scene, tmp_path):
    tmp, cap, landmarks, crops, fused = scene
    cut = heldout_frame_start(crops.frame, 1 / 3)
    assert cut == 4
    allowed = training_rows(crops, {3}, cut)  # camera 3 and frames 4-5 held out
    assert allowed.sum() == 2 * 4 * 3  # 2 people x 4 frames x 3 cameras
    teacher = RigTeacher(tmp / "fused" / "bodies.parquet", tmp / "crops.h5", cap.rig)
    a = teacher(landmarks, allowed.numpy(), tmp_path / "a")
    # anything at all in the held-out cameras and frames: the same teacher, the same targets
    rng = np.random.default_rng(1)
    garbage = landmarks.copy()
    garbage[~allowed.numpy()] = rng.random(garbage[~allowed.numpy()].shape) * 300
    b = teacher(garbage, allowed.numpy(), tmp_path / "b")
    ta, tb = distill_targets(crops, a, allowed), distill_targets(crops, b, allowed)
    for name in ("joints_world", "joint_weight", "global_orient", "body_pose", "betas", "weight"):
        assert torch.equal(getattr(ta, name), getattr(tb, name)), name
    # held-out crops carry no target; training crops do, close to the true joints
    assert (ta.weight[~allowed] == 0).all() and (ta.joint_weight[~allowed] == 0).all()
    assert (ta.weight[allowed] == 1).all()
    truth = torch.as_tensor(cap.joints)[crops.person - 1, crops.frame].float()
    err = (ta.joints_world - truth).norm(dim=-1).mean(1)[allowed]
    assert err.max() < 0.1  # a 40-iteration fit of 3 cameras: a few centimetres
    # the refit is not the fuse stage's fit (which saw the held-out views)...
    first = np.flatnonzero((fused.frame == 0) & (fused.person_id == 1))[0]
    second = np.flatnonzero((a.frame == 0) & (a.person_id == 1))[0]
    assert not np.array_equal(fused.joints[first], a.joints[second])
    # ...and with nothing held out the fuse stage's bodies are taken as they are
    every = teacher(landmarks, np.ones(len(crops), bool), tmp_path / "c")
    assert np.array_equal(every.joints, fused.joints) and not (tmp_path / "c").exists()
    # ... unless the landmarks were changed (un-mirrored): then they are fitted again (they
    # were not, and training on everything lost the un-mirroring's better teacher)
    again = teacher(landmarks, np.ones(len(crops), bool), tmp_path / "d", refit=True)
    assert (tmp_path / "d" / "fused").exists() and len(again.joints) == len(fused.joints)


def test_the_teacher_fuses_only_the_allowed_crops(scene, tmp_path, monkeypatch):
    """The teacher's fusion is given a store of the training crops alone, so no part of the
    fusion (the crowded crops read again from their pixels, the silhouettes that vote) can see
    a held-out crop: until 2026-11-30 it got the whole store, and the second reading of crowded
    crops gave the held-out crops their landmarks back."""
    import gst.lift.teacher as teacher_module
    from gst.data.store import CropStore

    tmp, cap, landmarks, crops, fused = scene
    allowed = training_rows(crops, {3}, heldout_frame_start(crops.frame, 1 / 3)).numpy()
    seen = {}

    def fake_fuse(store_path, rig, out, report, **kw):
        store = CropStore(store_path)
        seen["store"] = store.read(np.arange(len(store)))
        seen["landmarks"] = kw["landmarks"]
        return fuse_scene(store_path, rig, out, report, **kw)

    monkeypatch.setattr(teacher_module, "fuse_scene", fake_fuse)
    RigTeacher(tmp / "fused" / "bodies.parquet", tmp / "crops.h5", cap.rig)(
        landmarks, allowed, tmp_path
    )
    want = CropStore(tmp / "crops.h5").read(np.flatnonzero(allowed))
    got = seen["store"]
    assert len(got) == allowed.sum()
    for name in ("images", "masks", "frame", "camera", "person_id", "K_crop"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    assert np.array_equal(seen["landmarks"], landmarks[allowed])


def test_joint_weights_follow_the_views(scene):
    _, _, _, crops, fused = scene
    fused = dataclasses.replace(
        fused, joint_views=fused.joint_views.copy(), gap_filled=fused.gap_filled.copy()
    )
    fused.joint_views[0] = 4
    fused.joint_views[0, [1, 2]] = 2
    fused.gap_filled[0] = False
    fused.gap_filled[0, 4] = True
    fused.joint_views[0, 4] = 1
    row = int(np.flatnonzero(
        (crops.frame.numpy() == fused.frame[0]) & (crops.person.numpy() == fused.person_id[0])
    )[0])  # fmt: skip
    t = distill_targets(crops, fused, torch.ones(len(crops), dtype=torch.bool))
    w = t.joint_weight[row]
    assert w[7] == 1 and abs(float(w[1]) - 2 / 3) < 1e-6 and abs(float(w[4]) - 0.1) < 1e-6
    assert 0 < w[3] < 1  # spine1 has no landmark: its frame's mean


def test_the_root_and_parameters_of_a_guessed_frame_weigh_as_guessed_joints(scene):
    """A frame whose pelvis, or whole torso, the fit had to fill (fewer than 2 views) kept full
    weight in the root and parameters terms: only the joints term followed the evidence."""
    _, _, _, crops, fused = scene
    fused = dataclasses.replace(fused, gap_filled=fused.gap_filled.copy())
    fused.gap_filled[:2] = False
    fused.gap_filled[0, 0] = True  # the pelvis guessed
    fused.gap_filled[1, [1, 2, 16, 17]] = True  # every torso joint guessed

    def row(k):
        hit = (crops.frame.numpy() == fused.frame[k]) & (crops.person.numpy() == fused.person_id[k])
        return int(np.flatnonzero(hit)[0])

    t = distill_targets(crops, fused, torch.ones(len(crops), dtype=torch.bool))
    assert float(t.root_weight[row(0)]) == pytest.approx(0.1)
    assert float(t.params_weight[row(0)]) == 1.0
    assert float(t.params_weight[row(1)]) == pytest.approx(0.1)
    assert float(t.root_weight[row(1)]) == 1.0
    # ... and the terms use them: a root error only in the guessed row weighs a tenth
    rows = torch.tensor([row(0), row(2)])
    sub = t.take(rows)
    pred, joints = _prediction(sub, crops.R[rows])
    pred.joints_world = (
        joints + torch.tensor([[0.1, 0, 0]]) * torch.tensor([[1.0], [0.0]])[:, :, None]
    )
    root = float(distill_terms(pred, crops.R[rows], sub)["distill_root"].detach())
    assert root == pytest.approx(0.1 * 0.1 / 1.1, rel=1e-4)


def _prediction(t, R):
    """A prediction that equals the targets, seen through cameras R."""
    joints = t.joints_world.clone().requires_grad_(True)
    go = R @ t.global_orient
    rot = torch.cat([go[:, None], t.body_pose], 1).clone().requires_grad_(True)
    n = len(t)
    return BodyPrediction(rot, t.betas.clone(), torch.zeros(n, 3), joints, None, joints), joints


def test_distill_terms_vanish_at_the_target_and_skip_unweighted_rows(scene):
    _, _, _, crops, fused = scene
    t = distill_targets(crops, fused, torch.ones(len(crops), dtype=torch.bool)).take(
        torch.arange(6)
    )
    pred, joints = _prediction(t, crops.R[:6])
    terms = distill_terms(pred, crops.R[:6], t)
    assert all(float(v.detach()) < 1e-6 for v in terms.values())
    t.weight[:3] = 0
    pred.joints_world = (
        joints + torch.randn_like(joints) * 0.05 * (torch.arange(6) < 3).float()[:, None, None]
    )
    terms = distill_terms(pred, crops.R[:6], t)
    assert float(terms["distill_joints"].detach()) < 1e-6  # only the unweighted rows were moved
    sum(terms.values()).backward()
    assert torch.isfinite(joints.grad).all()


def test_no_teacher_fit_sees_the_heldout_crops(scene, tmp_path):
    """Both of training's teacher fits, the one that says which training crops are mirrored
    and the one that gives the targets, are of the training crops only (the first used the fuse
    stage's bodies, fitted on every crop, until 2026-11-30)."""
    from gst.train.scene_training import TrainSettings, prepare_crops

    tmp, cap, landmarks, crops, fused = scene
    calls = []

    def teacher(lm, allowed, work, refit=False):
        calls.append(np.asarray(allowed, bool).copy())
        return fused

    p = TrainSettings(heldout_frames=1 / 3, distill=True, unmirror_landmarks=True)
    prepare_crops(p, tmp / "crops.h5", None, teacher=teacher, work=tmp_path)
    want = training_rows(crops, {3}, heldout_frame_start(crops.frame, 1 / 3)).numpy()
    assert len(calls) == 2
    assert all(np.array_equal(c, want) for c in calls)


def test_bodies_of_another_body_model_are_refused(scene):
    """Fused with the open default, trained with SMPL (the README's switch, fuse.body_model left
    as it was): the targets' pose and shape are another body's, so it is an error that names
    both settings."""
    _, _, _, crops, fused = scene
    allowed = torch.ones(len(crops), dtype=torch.bool)
    distill_targets(crops, fused, allowed, body_model=fused.body_model)
    with pytest.raises(ValueError, match="fuse.body_model.*train.body_model"):
        distill_targets(crops, fused, allowed, body_model="smpl")


def test_landmarks_projected_from_the_rig_reach_no_target(scene, tmp_path):
    """Rows whose landmarks the extraction projected from the rig's skeleton (triangulated from
    every camera, the held-out one included): the teacher gets them with no confidence, as the
    fuse stage fuses them, and the keypoint targets come from the landmark model's own reading
    (training rows kept the projection, at confidence 0.5, in both)."""
    import shutil

    import h5py

    from gst.detect.crops import detect_crop_landmarks
    from gst.train.scene_training import TrainSettings, prepare_crops

    tmp, cap, landmarks, crops, fused = scene
    store = tmp_path / "crops.h5"
    shutil.copy(tmp / "crops.h5", store)
    shutil.copy(tmp / "crops.index.parquet", tmp_path / "crops.index.parquet")
    projected = np.zeros(len(crops), bool)
    projected[[0, 5]] = True  # training rows (frames 0-1, cameras 0-2)
    with h5py.File(store, "r+") as f:
        if "landmarks_projected" in f:
            del f["landmarks_projected"]
        f.create_dataset("landmarks_projected", data=projected)
    seen = []

    def teacher(lm, allowed, work, refit=False):
        seen.append(np.asarray(lm).copy())
        return fused

    p = TrainSettings(heldout_frames=1 / 3, distill=True, keypoints=True, unmirror_landmarks=False)
    prepared = prepare_crops(p, store, None, teacher=teacher, work=tmp_path / "w")
    assert len(seen) == 1 and (seen[0][projected, :, 2] == 0).all()
    assert (seen[0][~projected, :, 2] > 0).any()
    own = detect_crop_landmarks(crops.images[[0]].numpy(), rgb=True).landmarks[0]
    np.testing.assert_allclose(seen[0][0, :, :2], own[:, :2], atol=1e-4)
    assert prepared.crops.keypoints is not None


def test_distillation_without_a_work_folder_says_so(scene):
    """The teacher writes a subset store into `work`: without one, a clear error (it was a
    TypeError from Path(None) inside the teacher)."""
    from gst.train.scene_training import TrainSettings, prepare_crops

    tmp, _, _, _, fused = scene
    p = TrainSettings(heldout_frames=1 / 3, distill=True)
    with pytest.raises(ValueError, match="work"):
        prepare_crops(p, tmp / "crops.h5", None, teacher=lambda lm, allowed, work, **kw: fused)


def test_a_crop_that_shows_the_other_person_gets_no_target(scene):
    """The targets were matched by the store's (frame, person): a crop whose extraction id had
    switched (it shows the other person; the fusion's regrouping moved it there) trained towards
    the wrong body at full weight (a review: 24 such crops on the demo, 854 mm median pelvis
    error). The crop's own torso landmarks now say whose body it shows."""
    _, _, landmarks, crops, fused = scene
    allowed = torch.ones(len(crops), dtype=torch.bool)
    lm = torch.as_tensor(landmarks)
    before = distill_targets(crops, fused, allowed, landmarks=lm)
    assert (before.weight > 0).sum() > 0
    # one camera's crops of the first frames given the other person's id
    switched = crops.person.clone()
    sel = (crops.camera == 0) & (crops.frame < 3)
    switched[sel] = 3 - switched[sel]
    moved = dataclasses.replace(crops, person=switched)
    blind = distill_targets(moved, fused, allowed)  # without landmarks: as before
    after = distill_targets(moved, fused, allowed, landmarks=lm)
    hit = sel & (blind.weight > 0)
    assert hit.sum() >= 4
    assert (after.weight[hit] == 0).all()
    keep = ~sel & (before.weight > 0)
    assert torch.equal(after.weight[keep], before.weight[keep])


def test_bodies_that_name_no_joint_with_landmarks_are_refused_not_nan(scene):
    """Joints without a landmark take the mean weight of the joints with one: bodies whose file
    names no joint a landmark observes (no 'joint_landmarks' in its 'gst.fused' metadata, or
    joint names it does not map) gave every joint the mean of an empty slice, NaN, and so a NaN
    distillation loss."""
    _, _, _, crops, fused = scene
    blind = dataclasses.replace(fused, has_landmarks=np.zeros(24, bool))
    with pytest.raises(ValueError, match="no joint.*landmark.*joint_landmarks"):
        distill_targets(crops, blind, torch.ones(len(crops), dtype=torch.bool))


def test_landmarks_none_read_are_no_unmirroring(scene, tmp_path):
    """Whether the rig un-mirrored a landmark was `not torch.equal(read, unmirrored)`, and a
    crop where the landmark model found nobody holds NaN, which equals nothing: with nothing
    held out every such scene refitted the teacher (the demo: minutes) and logged landmarks
    'un-mirrored' that were not. NaN where it was NaN is no change."""
    from gst.data.store import CropStore, CropStoreWriter
    from gst.train.scene_training import TrainSettings, prepare_crops

    tmp, cap, landmarks, crops, fused = scene
    source = CropStore(tmp / "crops.h5")
    rows = source.read(np.arange(len(source)))
    read = landmarks.copy()
    read[7] = np.nan  # a crop where the landmark model found nobody
    done = sorted(set(zip(rows.frame.tolist(), rows.camera.tolist(), strict=True)))
    with CropStoreWriter(tmp_path / "crops.h5", source.camera_names, source.crop_size,
                         landmarks=True) as w:  # fmt: skip
        w.commit(dataclasses.replace(rows, landmarks=read), done)
        w.finalize({"n_frames": int(rows.frame.max()) + 1})
    calls = []

    def teacher(lm, allowed, work, refit=False):
        calls.append((bool(np.all(allowed)), refit))
        return fused

    p = TrainSettings(heldout_cameras=[], heldout_frames=0, distill=True, keypoints=False,
                      unmirror_landmarks=True, anchor=False, ignore_occluders=False)  # fmt: skip
    prepared = prepare_crops(p, tmp_path / "crops.h5", None, teacher=teacher,
                             work=tmp_path / "w", feed_landmarks=True)  # fmt: skip
    assert torch.isnan(prepared.crops.landmarks[7]).all()
    assert calls == [(True, False), (True, False)]  # nothing held out, nothing un-mirrored


def test_one_training_camera_left_is_refused_before_the_teacher(scene, tmp_path):
    """Every camera but one held out: multi-view training has no second view to render into.
    The teacher fused the one camera's crops (minutes on a real scene) and the landmarks were
    read before the trainer said 'no training samples'; now prepare_crops says so first,
    naming the held-out cameras and the one left."""
    from gst.train.scene_training import TrainSettings, prepare_crops

    tmp, _, _, _, fused = scene
    calls = []

    def teacher(lm, allowed, work, refit=False):
        calls.append(allowed)
        return fused

    held = ["cam1", "cam2", "cam3"]
    p = TrainSettings(heldout_cameras=held, heldout_frames=1 / 3, distill=True)
    with pytest.raises(ValueError, match=r"heldout_cameras \['cam1', 'cam2', 'cam3'\].*'cam0'"):
        prepare_crops(p, tmp / "crops.h5", None, teacher=teacher, work=tmp_path)
    assert calls == []
    # the 2d/3d baselines train on single crops: one camera is enough there
    p = TrainSettings(heldout_cameras=held, supervision="3d", distill=False)
    with pytest.raises(ValueError, match="truth joints"):  # a real scene: no truth, as before
        prepare_crops(p, tmp / "crops.h5", None)

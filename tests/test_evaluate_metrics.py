"""The evaluator's numbers against hand computations: per-joint errors, pairs, splits, summaries,
and novel-view scores recomputed from the kept images (PSNR full crop and inside the hand-
projected SHERF box)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
from test_train_recipe import crop_set

from gst.body import BodyModel
from gst.body.random_model import random_body_data
from gst.eval.evaluate import EvalConfig, evaluate_model
from gst.eval.evaluator import PoseRecords, evaluate_views, per_joint_errors, view_pairs
from gst.eval.split import frame_split
from gst.eval.summary import JOINT_GROUPS, joint_group_indices, pose_summary
from gst.model.presets import get_preset
from gst.train.evaluation import pose_metrics
from gst.train.losses import LossWeights
from gst.train.recipe import build_network, make_task

JOINTS = tuple(n for group in JOINT_GROUPS.values() for n in group)  # 24 names, any order


def test_perfect_prediction_has_zero_error():
    gt = torch.randn(3, 24, 3, dtype=torch.float64)
    e, pa = per_joint_errors(gt.clone(), gt)
    assert e.abs().max() < 1e-12 and pa.abs().max() < 1e-6


def test_known_offsets_give_known_errors():
    gt = torch.randn(2, 24, 3, dtype=torch.float64)
    shifted = gt + torch.tensor(
        [0.3, -0.2, 1.0], dtype=torch.float64
    )  # a global translation: root-aligned away
    e, _ = per_joint_errors(shifted, gt)
    assert e.abs().max() < 1e-12
    moved = gt.clone()
    moved[:, 5] += torch.tensor([0.0, 0.03, 0.04], dtype=torch.float64)  # one joint 5 cm off
    e, _ = per_joint_errors(moved, gt)
    assert e[:, 5].tolist() == pytest.approx([0.05, 0.05])
    assert e.mean(1).tolist() == pytest.approx([0.05 / 24, 0.05 / 24])
    # a similarity transform of the prediction is fully excused by Procrustes
    c, s = math.cos(0.7), math.sin(0.7)
    rot = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float64)
    _, pa = per_joint_errors(1.3 * gt @ rot.T + 2.0, gt)
    assert pa.abs().max() < 1e-9


def test_pose_summary_groups_and_breakdowns_by_hand():
    err = np.arange(2 * 24, dtype=np.float64).reshape(2, 24) / 1000  # metres
    rec = PoseRecords(
        rows=np.array([0, 1]),
        camera=np.array([0, 1]),
        frame=np.array([0, 0]),
        joint_error=err,
        joint_error_pa=err / 2,
    )
    s = pose_summary(rec, ["a", "b"], np.array(["run", "jump"], dtype=object), JOINTS)
    assert s.overall["mpjpe_mm"] == pytest.approx(err.mean() * 1000)
    assert s.per_camera["b"]["mpjpe_mm"] == pytest.approx(err[1].mean() * 1000)
    assert s.per_motion["run"]["n"] == 1 and s.per_motion["run"]["mpjpe_mm"] == pytest.approx(11.5)
    idx = joint_group_indices(JOINTS)["hands"]
    assert s.per_part["hands"]["pa_mpjpe_mm"] == pytest.approx(err[:, idx].mean() * 500)
    with pytest.raises(ValueError, match="lack"):
        joint_group_indices(JOINTS[:-1])


def test_summary_counts_say_how_many_records_each_mean_is_over():
    """ "n" counted every record while the means left out the NaN ones: 4 held-out pairs, 3 of
    them without a SHERF box, read as a box PSNR over 4; a diverged pose, as no record at all."""
    from gst.eval.evaluator import ViewRecords
    from gst.eval.summary import view_summary

    nan, n = float("nan"), 4
    rec = ViewRecords(
        inputs=np.arange(n), targets=np.arange(n), camera=np.zeros(n, int),
        heldout=np.ones(n, bool), psnr=np.array([20.0, 20, 20, 22]), ssim=np.full(n, 0.8),
        lpips=np.full(n, 0.2), silhouette_iou=np.full(n, 0.5),
        box_psnr=np.array([10.0, nan, nan, nan]), box_ssim=np.full(n, 0.7),
        box_lpips=np.full(n, 0.3), psnr_unoccluded=np.full(n, 21.0),
        silhouette_iou_unoccluded=np.full(n, 0.6),
    )  # fmt: skip
    held = view_summary(rec, ["c0"], np.full(n, "all", object)).heldout
    assert held["n"] == 4 and held["box_psnr"] == 10.0 and held["n_box_psnr"] == 1
    assert "n_psnr" not in held  # every one finite
    err = np.zeros((2, 24))
    err[1, 3] = nan
    pose = PoseRecords(
        rows=np.array([0, 1]), camera=np.array([0, 0]), frame=np.array([0, 0]),
        joint_error=err, joint_error_pa=err,
    )  # fmt: skip
    s = pose_summary(pose, ["a"], np.array(["run", "run"], dtype=object), JOINTS)
    assert s.overall["n"] == 2 and s.overall["n_not_finite"] == 1


def test_view_pairs_cover_every_other_view_and_never_input_heldout():
    crops = crop_set(n_frames=4, n_cams=3)
    pairs = view_pairs(crops, heldout={2})
    assert len(pairs.inputs) == 4 * 2  # 4 groups of 3 views: one input, two targets each
    assert not torch.isin(crops.camera[pairs.inputs], torch.tensor([2])).any()
    assert (crops.frame[pairs.inputs] == crops.frame[pairs.targets]).all()
    assert (pairs.inputs != pairs.targets).all()
    assert len(view_pairs(crops, heldout={2}, max_groups=1).inputs) == 2


def test_frame_split_by_hand():
    crops = crop_set(n_frames=8, n_cams=3)
    crops.truth["has_truth"] = torch.ones(len(crops), dtype=torch.bool)
    split = frame_split(crops, ("c2",), test_fraction=0.25)
    assert split.test_frames == (6, 8)
    rows = split.train_rows
    assert len(rows) == 6 * 2 and (crops.frame[rows] < 6).all() and (crops.camera[rows] != 2).all()
    with pytest.raises(ValueError, match="held-out cameras"):
        frame_split(crops, ("nope",))


@pytest.fixture(scope="module")
def tiny_model():
    body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
    body.joint_names = JOINTS
    cfg = get_preset("tiny", vertex_preset="full")
    net, ids, _ = build_network(cfg, body)
    return net.eval(), make_task(body, ids, cfg, 64, LossWeights(lpips=0.0)), body


def test_evaluate_model_matches_the_training_validation(tiny_model):
    net, task, _ = tiny_model
    crops = crop_set(n_frames=4, n_cams=3)
    res = evaluate_model(
        net, task, crops, EvalConfig(heldout_cameras=("c2",), render_size=32), joint_names=JOINTS
    )
    ref = pose_metrics(net, task, crops, torch.arange(len(crops)))  # gst.train's own implementation
    assert res.summary.pose.overall["mpjpe_mm"] == pytest.approx(ref.mpjpe_mm, rel=1e-4)
    assert res.summary.pose.overall["pa_mpjpe_mm"] == pytest.approx(ref.pa_mpjpe_mm, rel=1e-4)
    nv = res.summary.novel_view
    assert nv.heldout["n"] == 4 and nv.trained_views["n"] == 4
    assert nv.per_target_camera["c2"]["heldout"] and not nv.per_target_camera["c0"]["heldout"]


def test_view_scores_recomputed_from_kept_images(tiny_model):
    net, task, _ = tiny_model
    crops = crop_set(n_frames=3, n_cams=3)
    size = 48
    pairs = view_pairs(crops, heldout={2})
    keep = set(range(len(pairs.inputs)))
    rec = evaluate_views(net, task, crops, pairs, {2}, size=size, keep_images=keep, box_margin=0.05)
    scale = size / crops.crop_size
    checked = 0
    for k in keep:
        render, target = (x.astype(np.float64) / 255 for x in rec.images[k])
        mse = ((render - target) ** 2).mean()
        assert rec.psnr[k] == pytest.approx(10 * math.log10(1 / mse), abs=0.05)
        # SHERF box by hand: the joints' box padded by 0.15 m, corners projected, convex hull filled
        j = crops.truth["joints_world"][int(pairs.targets[k])].numpy().astype(np.float64)
        lo, hi = j.min(0) - 0.15, j.max(0) + 0.15
        corners = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        t = int(pairs.targets[k])
        cam = corners @ crops.R[t].numpy().T + crops.t[t].numpy()
        K = crops.K[t].numpy().astype(np.float64)
        fx, fy = K[0, 0] * scale, K[1, 1] * scale
        cx, cy = (K[0, 2] + 0.5) * scale - 0.5, (K[1, 2] + 0.5) * scale - 0.5
        uv = np.stack([fx * cam[:, 0] / cam[:, 2] + cx, fy * cam[:, 1] / cam[:, 2] + cy], 1)
        mask = np.zeros((size, size), np.uint8)
        cv2.fillConvexPoly(
            mask, cv2.convexHull(np.round(uv * 256).astype(np.int32)), 1, cv2.LINE_8, 8
        )
        m = mask.astype(bool)
        if m.sum() < 20:
            continue
        box_mse = ((render - target) ** 2)[m].mean()
        assert rec.box_psnr[k] == pytest.approx(10 * math.log10(1 / box_mse), abs=0.3)
        checked += 1
    assert checked >= len(keep) // 2


def test_a_prediction_that_is_not_finite_is_counted_not_fatal(tiny_model, monkeypatch):
    """One NaN skeleton made the Procrustes SVD fail the whole evaluation, and a NaN network
    output failed in the body model: `n_not_finite` could never be non-zero, and one diverged
    bench variant ended the sweep. Now such a crop's errors and view scores are NaN, counted,
    and the other crops score exactly as before."""
    import gst.eval.evaluator as ev

    net, task, _ = tiny_model
    crops = crop_set(n_frames=4, n_cams=3)
    cfg = EvalConfig(heldout_cameras=("c2",), render_size=32)
    before = evaluate_model(net, task, crops, cfg, joint_names=JOINTS)
    real = ev.predict
    victim = int(before.views.inputs[0])  # a crop that is also a view pair's input
    poisoned = crops.images[victim].clone()

    def predict(model, task, images, *args, **kwargs):
        hit = (images == poisoned).flatten(1).all(1)
        # as a diverged network's pose for that crop: the body model refuses it
        if bool(hit.any()):
            pose = torch.zeros(len(images), 23, 3)
            pose[hit] = float("nan")
            task.body(None, pose, torch.zeros(len(images), 3))
        return real(model, task, images, *args, **kwargs)

    monkeypatch.setattr(ev, "predict", predict)
    after = evaluate_model(net, task, crops, cfg, joint_names=JOINTS)
    assert after.summary.pose.overall["n_not_finite"] == 1
    finite = np.isfinite(after.pose.mpjpe)
    assert finite.sum() == len(crops) - 1 and not finite[list(after.pose.rows).index(victim)]
    assert np.allclose(after.pose.mpjpe[finite], before.pose.mpjpe[finite], atol=1e-6)
    views = after.views
    bad = views.inputs == victim
    assert bad.any() and np.isnan(views.psnr[bad]).all() and np.isfinite(views.psnr[~bad]).all()
    assert np.allclose(views.psnr[~bad], before.views.psnr[~bad], atol=1e-4)

    # the SVD with a NaN skeleton, directly
    gt = torch.randn(3, 24, 3)
    pred = gt + 0.01 * torch.randn(3, 24, 3)
    pred[1] = float("nan")
    e, pa = per_joint_errors(pred, gt)
    assert torch.isnan(pa[1]).all() and torch.isfinite(pa[[0, 2]]).all()


def test_other_peoples_pixels_are_left_out_of_the_unoccluded_view_scores(tiny_model):
    """A target's mask stops where someone in front starts, so a render of the whole body was
    scored wrong there (PSNR and IoU); the `_unoccluded` scores leave those pixels out, as
    training does, and equal the plain ones where nobody covers anyone."""
    from gst.train.views import resize_images, target_views

    net, task, _ = tiny_model
    crops = crop_set(n_frames=3, n_cams=3)
    size, pairs = 48, view_pairs(crops, heldout={2})
    keep = set(range(len(pairs.inputs)))
    crops.occluders = torch.zeros(len(crops), crops.crop_size, crops.crop_size)
    plain = evaluate_views(net, task, crops, pairs, {2}, size=size, keep_images=keep)
    np.testing.assert_allclose(plain.psnr_unoccluded, plain.psnr, rtol=1e-6)
    np.testing.assert_allclose(plain.silhouette_iou_unoccluded, plain.silhouette_iou, rtol=1e-6)
    crops.occluders[:, :, crops.crop_size // 2 :] = 1.0  # someone covers every right half
    rec = evaluate_views(net, task, crops, pairs, {2}, size=size, keep_images=keep)
    np.testing.assert_allclose(rec.psnr, plain.psnr, rtol=1e-6)  # the plain scores as they were
    for k in keep:
        t = pairs.targets[k : k + 1]
        _, _, _, mask = target_views(crops, t, size)
        occ = resize_images(crops.occluders[t][..., None], size)[..., 0]
        weight = (1 - occ * (1 - mask))[0].numpy().astype(np.float64)  # own pixels always count
        render, target = (x.astype(np.float64) / 255 for x in rec.images[k])
        mse = (((render - target) ** 2).mean(-1) * weight).sum() / weight.sum()
        assert rec.psnr_unoccluded[k] == pytest.approx(10 * math.log10(1 / mse), abs=0.05)
    assert not np.allclose(rec.psnr_unoccluded, rec.psnr)

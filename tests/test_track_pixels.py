"""Crops the network will not read are not cut: `GSTPredictor.needs_pixels` says which, and
handing those crops in blank changes no prediction; `prepare_detection(pixels=False)` keeps the
camera, the landmarks and (nearly) the appearance of the full crop."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from calibration import Camera
from gst.body import load_body_model
from gst.data.camera_view import TrackingView
from gst.model.checkpoint import save_checkpoint
from gst.model.inference import GSTPredictor
from gst.model.presets import get_preset
from gst.track.appearance import box_histogram, colour_histogram
from gst.track.detection import Detection
from gst.track.frames import prepare_detection
from gst.train.recipe import build_network


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    torch.manual_seed(0)
    net, ids, groups = build_network(get_preset("tiny", landmark_tokens=True), load_body_model())
    with torch.no_grad():
        net.smpl_head.transformer.smpl_image_gate.fill_(0.01)  # the image's share: negligible
    path = tmp_path_factory.mktemp("ckpt") / "gst.pt"
    save_checkpoint(path, net, "anny", ids, groups)
    return path


def _inputs(n=6, seed=0):
    g = np.random.default_rng(seed)
    crops = g.integers(0, 255, (n, 256, 256, 3), dtype=np.uint8)
    K = np.tile(np.array([[400.0, 0, 128], [0, 400, 128], [0, 0, 1]]), (n, 1, 1))
    lm = np.concatenate([g.uniform(20, 236, (n, 33, 2)), g.uniform(0.2, 1, (n, 33, 1))], -1)
    lm[1] = np.nan  # no landmarks
    lm[3, :, 2] = 0.0  # landmarks, none confident: nothing the network may use
    lm[4, :25] = np.nan  # knees, ankles and feet left: enough for any landmark set
    lm[5, 11:] = np.nan  # the face alone: not for a network that takes the 12 limb landmarks
    return crops, K, lm.astype(np.float32)


def test_blank_crops_where_pixels_are_not_needed_change_nothing(checkpoint):
    path = checkpoint
    pred = GSTPredictor(path)
    assert pred.pose_from_landmarks
    crops, K, lm = _inputs()
    needs = pred.needs_pixels(lm)
    face_only_needs = pred.network.cfg.num_landmarks == 12
    assert needs.tolist() == [False, True, False, True, False, face_only_needs]
    blank = crops.copy()
    blank[~needs] = 0
    a, b = pred(crops, K, landmarks=lm), pred(blank, K, landmarks=lm)
    for key in ("rotmats", "betas", "transl_cam", "joints_cam"):
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    # every crop is read when the image path always runs, or for Gaussians
    assert GSTPredictor(path, image_path="always").needs_pixels(lm).all()
    assert GSTPredictor(path, with_gaussians=True).needs_pixels(lm).all()


def test_a_detection_without_pixels_keeps_camera_landmarks_and_appearance():
    w, h = 640, 480
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    cam = Camera.create("c", K, [-0.2, 0.05, 0, 0, 0], np.eye(3), np.zeros(3), w, h)
    view = TrackingView.for_video(w, h, cam)
    frame = np.zeros((h, w, 3), np.uint8)
    frame[:] = (40, 120, 40)  # grass
    frame[150:400, 280:360] = (200, 30, 30)  # a blue shirt (BGR)
    frame[150:220, 300:340] = (90, 160, 230)  # a face
    lm = np.concatenate([np.random.default_rng(1).uniform(290, 350, (33, 2)), np.ones((33, 1))], 1)
    det = Detection(box=np.array([270.0, 140, 370, 410]), score=0.9, landmarks=lm)
    full = prepare_detection(view, frame, det, 256)
    fast = prepare_detection(view, frame, det, 256, pixels=False)
    np.testing.assert_array_equal(fast.K_crop, full.K_crop)
    np.testing.assert_array_equal(fast.landmarks_crop, full.landmarks_crop)
    assert fast.crop_rgb.shape == full.crop_rgb.shape and not fast.crop_rgb.any()
    # the histogram comes from the frame, whether or not the crop is cut
    np.testing.assert_array_equal(fast.appearance, full.appearance)
    other = colour_histogram(np.full((64, 64, 3), (200, 30, 30), np.uint8))  # RGB: red
    assert np.abs(fast.appearance - other).sum() > 1.0  # and still tells a red shirt apart


def test_the_frame_sampled_histogram_is_the_core_of_the_box_or_its_mask():
    """`box_histogram` reads every few pixels of the box's core: about the histogram of all
    of them; with a mask, only the person's pixels of the whole box count."""
    rng = np.random.default_rng(0)
    frame = np.zeros((1088, 1920, 3), np.uint8)
    frame[:] = (40, 120, 40)  # grass
    box = np.array([700.0, 100, 1100, 1000])  # x0, y0, x1, y1
    frame[100:1000, 700:1100] = rng.choice(
        [(200, 30, 30), (30, 30, 200), (230, 230, 230)], (900, 400)
    )
    core = frame[190:910, 800:1000, ::-1]  # shrunk 25 % in x and 10 % in y, RGB
    exact = colour_histogram(core)
    sampled = box_histogram(frame, box)
    assert np.abs(sampled - exact).sum() < 0.05  # L1 of unit-sum histograms (at most 2)
    mask = np.zeros(frame.shape[:2], bool)
    mask[100:1000, 700:1100] = True
    frame[100:1000, 1000:1100] = (40, 120, 40)  # grass inside the box, outside the mask
    mask[:, 1000:] = False
    with_mask = box_histogram(frame, box, mask)
    want = colour_histogram(frame[100:1000, 700:1000, ::-1])
    assert np.abs(with_mask - want).sum() < 0.05
    grass = colour_histogram(np.full((8, 8, 3), (40, 120, 40), np.uint8))
    assert (with_mask * grass).sum() < 1e-3  # no grass counted

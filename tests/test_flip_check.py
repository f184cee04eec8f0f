"""The learned check for BlazePose's left/right flips (gst.model.flip_check and
gst.train.flip_check)."""

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.body.markers import BLAZEPOSE_MIRROR
from gst.metrics.flips import unmirror
from gst.model.checkpoint import add_checkpoint_extra, load_checkpoint, save_checkpoint
from gst.model.flip_check import (
    INPUT_SIZE,
    LEFT_IDS,
    FlipCheck,
    FlipCheckNet,
    check_input,
    decidable,
    exchange_sides,
    flip_check_of,
)
from gst.train.flip_check import FlipCheckSettings, _hflip, train_flip_check

S = 96  # crop size of these tests


def _landmarks(rng, n):
    """People seen from the front or the back: hips and shoulders read, other landmarks not
    detected. A person's left side is on the image's right when they face the camera."""
    lm = np.full((n, 33, 3), np.nan, np.float32)
    centre = rng.uniform(35, S - 35, (n, 2))
    facing = np.where(rng.random(n) < 0.5, 1.0, -1.0)  # +1: towards the camera
    half = rng.uniform(8, 14, n) * facing
    for (left, right), dy in (((11, 12), -12.0), ((23, 24), 12.0)):
        lm[:, left, 0], lm[:, right, 0] = centre[:, 0] + half, centre[:, 0] - half
        lm[:, [left, right], 1] = (centre[:, 1] + dy)[:, None]
        lm[:, [left, right], 2] = 1.0
    return lm


def _painted(lm):
    """Crops of the correctly read landmarks: a grey torso, and a bright face above the
    shoulders of the people who face the camera (their left shoulder on the image's right)."""
    imgs = np.full((len(lm), S, S, 3), 30, np.uint8)
    for i in range(len(lm)):
        x = lm[i, [11, 12, 23, 24], 0]
        y = lm[i, [11, 12, 23, 24], 1]
        x0, x1, y0, y1 = (int(round(v)) for v in (x.min(), x.max(), y.min(), y.max()))
        imgs[i, y0 : y1 + 1, x0 : x1 + 1] = 120
        if lm[i, 11, 0] > lm[i, 12, 0]:  # facing the camera
            cx = (x0 + x1) // 2
            imgs[i, y0 - 12 : y0 - 2, cx - 5 : cx + 5] = (250, 200, 160)
    return imgs


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 1000))
def test_the_score_is_antisymmetric_in_the_sides(seed):
    torch.manual_seed(seed)
    net = FlipCheckNet(8).eval()
    x = torch.rand(3, 5, INPUT_SIZE, INPUT_SIZE)
    with torch.no_grad():
        assert torch.allclose(net.score(exchange_sides(x)), -net.score(x), atol=1e-5)


def test_blobs_sit_at_the_landmarks_at_the_check_size():
    lm = np.full((1, 33, 3), np.nan, np.float32)
    lm[0, 11] = (47.0, 23.0, 1.0)  # a left landmark in a 96 px crop (pixel centres at integers)
    x = check_input(np.zeros((1, S, S, 3), np.uint8), lm)
    assert x.shape == (1, 5, INPUT_SIZE, INPUT_SIZE)
    scale = INPUT_SIZE / S
    v, u = np.unravel_index(int(x[0, 3].argmax()), (INPUT_SIZE, INPUT_SIZE))
    assert abs(u - ((47 + 0.5) * scale - 0.5)) <= 0.5 and abs(v - ((23 + 0.5) * scale - 0.5)) <= 0.5
    assert float(x[0, 4].max()) == 0.0  # no right landmark: an empty channel


def test_a_horizontally_flipped_crop_is_a_valid_reading_of_the_mirror_image():
    lm = torch.as_tensor(_landmarks(np.random.default_rng(0), 6))
    imgs = torch.as_tensor(_painted(lm.numpy()))
    fimgs, flm = _hflip(imgs, lm)
    # who faced the camera still does (left shoulder on the image's right), in the same pixels
    assert torch.equal(flm[:, 11, 0] > flm[:, 12, 0], lm[:, 11, 0] > lm[:, 12, 0])
    assert torch.allclose(flm[:, LEFT_IDS[5], 0], S - 1 - lm[:, BLAZEPOSE_MIRROR[LEFT_IDS[5]], 0])
    back_imgs, back_lm = _hflip(fimgs, flm)
    assert torch.equal(back_imgs, imgs) and torch.allclose(back_lm, lm, equal_nan=True)


def test_crops_without_readable_hips_and_shoulders_are_never_exchanged():
    check = FlipCheck(FlipCheckNet(8).eval(), temperature=1.0, prior_log_odds=50.0)  # always yes
    lm = _landmarks(np.random.default_rng(1), 3)
    lm[1, 23, 2] = np.nan
    lm[2, 12, 2] = 0.3
    assert decidable(lm).tolist() == [True, False, False]
    out, flags = check.correct(_painted(lm), lm)
    assert flags.tolist() == [True, False, False]
    assert np.array_equal(out[0], lm[0][BLAZEPOSE_MIRROR], equal_nan=True)
    assert np.array_equal(out[1:], lm[1:], equal_nan=True)


def test_the_check_learns_the_sides_from_the_pixels_and_keeps_to_its_validation():
    rng = np.random.default_rng(2)
    n = 160
    lm = _landmarks(rng, n)
    imgs = torch.as_tensor(_painted(lm))
    mirrored = rng.random(n) < 0.2
    read = unmirror(lm, mirrored)  # what the "detector" gave: some crops mirrored
    sides = np.where(mirrored, -1, 1).astype(np.int8)
    sides[:5] = 0  # unlabelled rows take no part
    frames = np.arange(n) // 2
    cfg = FlipCheckSettings(max_steps=80, validate_every=20, min_steps=40, width=8, min_crops=20)
    check, report = train_flip_check(imgs, torch.as_tensor(read), sides, frames, cfg)
    assert report.labelled_crops == n - 5 and report.mirrored_crops == int(mirrored[5:].sum())
    assert report.validation_crops > 0 and 0 < report.best_step <= report.steps <= 80
    # new crops of the same kind: the check finds the mirrored ones and leaves the others
    lm2 = _landmarks(np.random.default_rng(3), 60)
    flips = np.arange(60) % 3 == 0
    called = check.mirrored(_painted(lm2), unmirror(lm2, flips))
    assert (called == flips).mean() >= 0.9


def test_too_few_labelled_crops_train_no_check():
    lm = _landmarks(np.random.default_rng(4), 10)
    check, report = train_flip_check(
        torch.as_tensor(_painted(lm)), torch.as_tensor(lm), np.ones(10, np.int8), np.arange(10),
        FlipCheckSettings(min_crops=20),
    )  # fmt: skip
    assert check is None and report is None


def test_the_check_travels_in_the_checkpoint_and_the_predictor_applies_it(tmp_path):
    from gst.body import BodyModel
    from gst.body.random_model import random_body_data
    from gst.model.inference import GSTPredictor
    from gst.model.presets import get_preset
    from gst.train.recipe import build_network

    data = random_body_data(num_vertices=400, with_posedirs=False)
    body_path = data.save_npz(tmp_path / "body.npz")
    cfg = get_preset("tiny", vertex_preset="full", landmark_tokens=True, num_landmarks=33)
    net, ids, groups = build_network(cfg, BodyModel(data))
    path = tmp_path / "m.pt"
    save_checkpoint(path, net, str(body_path), ids, groups)
    assert flip_check_of(load_checkpoint(path).extra) is None
    torch.manual_seed(5)
    check = FlipCheck(FlipCheckNet(8).eval(), temperature=2.0, prior_log_odds=-3.0)
    add_checkpoint_extra(path, flip_check=check.to_state())
    loaded = flip_check_of(load_checkpoint(path).extra)  # weights_only loading
    lm = _landmarks(np.random.default_rng(6), 4)
    imgs = _painted(lm)
    assert np.allclose(loaded.log_odds(imgs, lm), check.log_odds(imgs, lm))
    # the predictor reads every crop's pixels (the check needs them) and exchanges the sides of
    # what its check calls mirrored; with flip_check=False it leaves them as read
    yes = FlipCheck(FlipCheckNet(8).eval(), temperature=1.0, prior_log_odds=50.0)
    add_checkpoint_extra(path, flip_check=yes.to_state())
    pred = GSTPredictor(path)
    assert pred.needs_pixels(lm).all()
    out, flags = pred.correct_landmarks(imgs, lm)
    assert flags.all() and np.array_equal(out, lm[:, BLAZEPOSE_MIRROR], equal_nan=True)
    off = GSTPredictor(path, flip_check=False)
    out, flags = off.correct_landmarks(imgs, lm)
    assert not flags.any() and out is lm

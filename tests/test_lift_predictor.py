"""GSTPredictor with landmarks: what the track loop passes (N, 33, 3 crop px + confidence, NaN
where none) reaches a landmark checkpoint's tokens; rows without landmarks take the image-only
path exactly; image-only checkpoints say they take none."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gst.body import BodyModel
from gst.body.random_model import random_body_data
from gst.model.checkpoint import save_checkpoint
from gst.model.inference import GSTPredictor
from gst.model.landmarks import LIMB_LANDMARK_IDS, LandmarkInput
from gst.model.presets import get_preset
from gst.train.recipe import build_network


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pred")
    data = random_body_data(num_vertices=400, with_posedirs=False)
    body_path = data.save_npz(tmp / "body.npz")
    body = BodyModel(data)
    out = {}
    for name, kw in (
        ("plain", {}),
        ("all33", {"landmark_tokens": True, "num_landmarks": 33}),
        ("limbs", {"landmark_tokens": True, "num_landmarks": 12}),
    ):
        net, ids, groups = build_network(get_preset("tiny", vertex_preset="full", **kw), body)
        save_checkpoint(tmp / f"{name}.pt", net, str(body_path), ids, groups)
        out[name] = tmp / f"{name}.pt"
    return out


def _inputs(n=5, seed=0):
    rng = np.random.default_rng(seed)
    crops = rng.integers(0, 255, (n, 64, 64, 3), dtype=np.uint8)
    K = np.tile(np.array([[80.0, 0, 31.5], [0, 80.0, 31.5], [0, 0, 1]], np.float32), (n, 1, 1))
    lm = np.concatenate([rng.random((n, 33, 2)) * 64, rng.random((n, 33, 1))], -1)
    return crops, K, lm.astype(np.float32)


def test_landmark_checkpoints_use_the_landmarks_and_nan_rows_take_the_image_path(checkpoints):
    crops, K, lm = _inputs()
    for name in ("all33", "limbs"):
        pred = GSTPredictor(checkpoints[name], batch_size=2)
        assert pred.accepts_landmarks
        bare = pred(crops, K)
        with_lm = pred(crops, K, landmarks=lm)
        assert set(with_lm) == {"rotmats", "betas", "transl_cam", "joints_cam"}
        assert not np.allclose(bare["rotmats"], with_lm["rotmats"])
        lm_none = lm.copy()
        lm_none[[1, 3]] = np.nan  # the detector found nobody in crops 1 and 3
        mixed = pred(crops, K, landmarks=lm_none)
        for key in bare:
            assert np.array_equal(mixed[key][[1, 3]], bare[key][[1, 3]]), key
            assert np.array_equal(mixed[key][[0, 2, 4]], with_lm[key][[0, 2, 4]]), key
        with pytest.raises(ValueError, match="landmark rows"):
            pred.predict(crops, K, landmarks=lm[:2])


def test_the_limb_network_reads_the_limb_landmarks_only(checkpoints):
    crops, K, lm = _inputs(3, seed=1)
    pred = GSTPredictor(checkpoints["limbs"])
    other = lm.copy()
    face = [i for i in range(33) if i not in LIMB_LANDMARK_IDS]
    other[:, face] += 17.0  # landmarks the 12-landmark network does not take
    assert np.array_equal(pred(crops, K, landmarks=lm)["joints_cam"],
                          pred(crops, K, landmarks=other)["joints_cam"])  # fmt: skip
    inp = LandmarkInput.from_detections(lm, K, 64, 12)
    assert inp.points.shape == (3, 12, 3) and inp.mask.all()


def test_image_only_checkpoints_take_no_landmarks(checkpoints):
    crops, K, lm = _inputs(2)
    pred = GSTPredictor(checkpoints["plain"])
    assert not pred.accepts_landmarks
    assert np.array_equal(pred(crops, K)["joints_cam"], pred(crops, K, landmarks=lm)["joints_cam"])
    assert torch.is_tensor(pred.predict(crops, K).joints_cam)


def test_a_body_override_must_be_the_checkpoints_body(checkpoints, tmp_path):
    """GSTPredictor(ckpt, body_model=another body) posed the network's coefficients on that body:
    plausible joints up to 0.4 m off, without a word."""
    own = checkpoints["plain"].parent / "body.npz"
    copy = tmp_path / "same_body_elsewhere.npz"
    copy.write_bytes(own.read_bytes())
    crops, K, _ = _inputs(2)
    same = GSTPredictor(checkpoints["plain"], body_model=str(copy))
    np.testing.assert_array_equal(
        same(crops, K)["joints_cam"], GSTPredictor(checkpoints["plain"])(crops, K)["joints_cam"]
    )
    other = random_body_data(num_vertices=400, with_posedirs=False, seed=7)
    other_path = other.save_npz(tmp_path / "other.npz")
    with pytest.raises(ValueError, match="not the body the network was trained with"):
        GSTPredictor(checkpoints["plain"], body_model=str(other_path))


def test_a_body_file_replaced_under_the_checkpoints_path_is_refused(tmp_path):
    """The checkpoint names its body by spec or path, resolved on the machine that loads it:
    another body of as many vertices under that path gave joints about 0.1 m off without a
    word. A refiner network holds its training skeleton, which the loaded body must match."""
    data = random_body_data(num_vertices=400, with_posedirs=False)
    body_path = data.save_npz(tmp_path / "body.npz")
    cfg = get_preset("tiny", vertex_preset="full", landmark_tokens=True, landmark_refine=2)
    net, ids, groups = build_network(cfg, BodyModel(data))
    save_checkpoint(tmp_path / "lm.pt", net, str(body_path), ids, groups)
    assert GSTPredictor(tmp_path / "lm.pt").network.refiner is not None  # loads as it is
    random_body_data(num_vertices=400, with_posedirs=False, seed=7).save_npz(body_path)
    with pytest.raises(ValueError, match="skeleton lies up to .* mm from the one the network"):
        GSTPredictor(tmp_path / "lm.pt")


def test_far_off_landmarks_are_no_reading_and_unbatched_poses_are_named(checkpoints):
    """A landmark at 1e30 crop px (a damaged cache) became inf inside the lifting and failed the
    whole batch (NonFiniteBatch); one (3, 3) R for a batch failed deep in the assembly."""
    pred = GSTPredictor(checkpoints["all33"])
    crops, K, lm = _inputs(3)
    far = lm.copy()
    far[0, 11, 0] = 1e30
    masked = lm.copy()
    masked[0, 11] = np.nan  # no reading: the same as far off
    got, want = pred(crops, K, landmarks=far), pred(crops, K, landmarks=masked)
    assert np.isfinite(got["joints_cam"]).all()
    np.testing.assert_array_equal(got["joints_cam"], want["joints_cam"])
    with pytest.raises(ValueError, match=r"R must be \(3, 3, 3\): one per crop, got \(3, 3\)"):
        pred.predict(crops, K, R=np.eye(3), t=np.zeros((3, 3)))


def test_empty_batches_and_nan_crops_are_named(checkpoints):
    """predict on no crops failed in the body model ("body_pose has an empty batch") or in a
    reshape; NaN float crops passed the range check (NaN > 1 is False) and were blamed on
    body_pose."""
    pred = GSTPredictor(checkpoints["all33"])
    crops, K, lm = _inputs(3)
    with pytest.raises(ValueError, match="an empty batch of crops"):
        pred.predict(crops[:0], K[:0], landmarks=lm[:0])
    assert pred(crops[:0], K[:0], landmarks=lm[:0])["joints_cam"].shape == (0, 24, 3)
    bad = crops.astype(np.float32) / 255
    bad[1, 5, 5, 0] = np.nan
    with pytest.raises(ValueError, match=r"float crops hold NaN or Inf \(crops \[1\]\)"):
        pred.predict(bad, K, landmarks=lm)

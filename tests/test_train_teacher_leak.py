"""Nothing of a held-out camera or frame reaches what training sees of its own crops: two crop
stores that differ only in the held-out rows (their pixels, masks and landmarks) give, through
`prepare_crops` and the real rig teacher (two fusions: the un-mirroring's and the targets'),
the same training rows in every field a batch reads: inputs, landmarks, keypoints, occluders,
anchors and every distillation target. The sampler's side (only training rows are drawn) is
tests/test_train_heldout.py."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from gst.body import load_body_model
from gst.data.store import CropStore, CropStoreWriter
from gst.fuse import FitOptions, FuseOptions, fuse_scene
from gst.lift.teacher import RigTeacher
from gst.train.distill import training_rows
from gst.train.scene_training import TrainSettings, prepare_crops
from tests.fuse_fixtures import make_capture, write_store

FIELDS = ("images", "masks", "K", "R", "t", "landmarks", "keypoints", "occluders", "anchors")


def _write(path, source: CropStore, rows) -> None:
    with CropStoreWriter(path, source.camera_names, source.crop_size, landmarks=True) as w:
        w.commit(rows, sorted(set(zip(rows.frame.tolist(), rows.camera.tolist(), strict=True))))
        w.finalize({"n_frames": int(rows.frame.max()) + 1})


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    return bool(torch.equal(torch.isnan(a), torch.isnan(b))) and torch.equal(
        torch.nan_to_num(a), torch.nan_to_num(b)
    )


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    torch.set_num_threads(1)
    tmp = tmp_path_factory.mktemp("leak")
    cap = make_capture(load_body_model("anny"), n_people=2, n_frames=6, n_cams=4, seed=3)
    write_store(tmp / "base.h5", cap, with_landmarks=True)
    base = CropStore(tmp / "base.h5")
    rows = base.read(np.arange(len(base)))
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[: base.crop_size, : base.crop_size]
    masks = np.stack(
        [
            ((xx - 10 - i % 7) ** 2 + (yy - 16) ** 2 < 80).astype(np.uint8) * 255
            for i in range(len(rows))
        ]
    )  # two people per camera and frame overlap: occluders and crowded crops read again
    images = rng.integers(0, 255, rows.images.shape, dtype=np.uint8)
    clean = dataclasses.replace(rows, images=images, masks=masks)
    _write(tmp / "clean.h5", base, clean)
    held = (rows.camera == 3) | (rows.frame >= 4)  # cam3 and the last third of the frames
    lm, im, mk = rows.landmarks.copy(), images.copy(), masks.copy()
    lm[held] = rng.random(lm[held].shape).astype(np.float32) * 300
    im[held] = rng.integers(0, 255, im[held].shape, dtype=np.uint8)
    mk[held] = 255 - mk[held]
    _write(tmp / "other.h5", base, dataclasses.replace(rows, images=im, masks=mk, landmarks=lm))
    # the fuse stage's bodies (it sees every camera and frame: only the settings are used)
    fuse_scene(tmp / "clean.h5", cap.rig, tmp / "fused", tmp / "report", fps=30.0,
               options=FuseOptions(fit=FitOptions(iterations=40), overlay=False))  # fmt: skip
    p = TrainSettings(heldout_frames=1 / 3, heldout_cameras=["cam3"])
    out = {}
    for name in ("clean", "other"):
        teacher = RigTeacher(tmp / "fused" / "bodies.parquet", tmp / f"{name}.h5", cap.rig)
        out[name] = prepare_crops(p, tmp / f"{name}.h5", None, feed_landmarks=True,
                                  teacher=teacher, work=tmp / f"work_{name}")  # fmt: skip
    return out["clean"], out["other"], torch.as_tensor(~held)


def test_heldout_rows_change_nothing_training_sees(stores):
    a, b, train = stores
    assert a.first_heldout_frame == 4 and a.heldout_cameras == ["cam3"]
    allowed = training_rows(a.crops, {3}, a.first_heldout_frame)
    assert torch.equal(allowed, train)
    # not vacuous: the held-out rows do differ, and training rows have targets
    assert not torch.equal(a.crops.images[~train], b.crops.images[~train])
    assert (a.crops.distill.weight[train] > 0).sum() >= 20
    for name in FIELDS:
        assert _same(getattr(a.crops, name)[train], getattr(b.crops, name)[train]), name
    for f in dataclasses.fields(a.crops.distill):
        x, y = getattr(a.crops.distill, f.name), getattr(b.crops.distill, f.name)
        assert _same(x[train], y[train]), f"distill.{f.name}"
    # held-out rows carry no target at all
    for prepared in (a, b):
        assert (prepared.crops.distill.weight[~train] == 0).all()

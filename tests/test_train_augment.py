"""Crop jitter keeps the camera exact (K, 2D truth and pixels move together), and corpora concat."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.train.augment import CropJitter, jitter_batch, similarity, warp_crops
from gst.train.steps import SupervisedBatch
from gst.train.views import CropSet, concat_crop_sets

SIZE = 96


def _blob_batch(points_cam: torch.Tensor, K: torch.Tensor) -> SupervisedBatch:
    """One white Gaussian blob per image at the projection of its 3D point."""
    uv = (points_cam[:, :2] / points_cam[:, 2:]) * K[:, [0, 1], [0, 1]] + K[:, :2, 2]
    ys, xs = torch.meshgrid(
        torch.arange(SIZE, dtype=torch.float64),
        torch.arange(SIZE, dtype=torch.float64),
        indexing="ij",
    )
    d2 = (xs[None] - uv[:, 0, None, None]) ** 2 + (ys[None] - uv[:, 1, None, None]) ** 2
    img = (255 * torch.exp(-d2 / (2 * 2.0**2))).round().to(torch.uint8)
    joints = points_cam[:, None].repeat(1, 24, 1).float()
    return SupervisedBatch(
        images=img[..., None].repeat(1, 1, 1, 3),
        K=K.float(),
        joints_cam=joints,
        joints2d=uv[:, None].repeat(1, 24, 1).float(),
        visible=torch.ones(len(K), 24),
    )


def _centroid(images: torch.Tensor) -> torch.Tensor:
    w = images[..., 0].double()
    ys, xs = torch.meshgrid(
        torch.arange(SIZE, dtype=torch.float64),
        torch.arange(SIZE, dtype=torch.float64),
        indexing="ij",
    )
    return torch.stack(
        [(w * xs).sum((1, 2)) / w.sum((1, 2)), (w * ys).sum((1, 2)) / w.sum((1, 2))], -1
    )


def _K(n: int) -> torch.Tensor:
    K = torch.zeros(n, 3, 3, dtype=torch.float64)
    K[:, 0, 0] = K[:, 1, 1] = 150.0
    K[:, 0, 2] = K[:, 1, 2] = (SIZE - 1) / 2
    K[:, 2, 2] = 1
    return K


def test_jitter_moves_pixels_k_and_2d_truth_together():
    gen = torch.Generator().manual_seed(0)
    pts = torch.tensor(
        [[0.05, -0.03, 3.0], [-0.1, 0.08, 4.0], [0.0, 0.0, 2.5], [0.12, 0.1, 5.0]],
        dtype=torch.float64,
    )
    batch = _blob_batch(pts, _K(len(pts)))
    out = jitter_batch(
        batch, CropJitter(zoom=0.3, shift=0.1, brightness=0, contrast=0, saturation=0), gen
    )
    K2 = out.K.double()
    uv_new_k = (pts[:, :2] / pts[:, 2:]) * K2[:, [0, 1], [0, 1]] + K2[:, :2, 2]
    # the 2D truth is the projection with the new K, and the warped blob sits there (< 0.15 px)
    assert torch.allclose(out.joints2d[:, 0].double(), uv_new_k, atol=1e-3)
    assert (_centroid(out.images) - uv_new_k).norm(dim=-1).max() < 0.15
    assert not torch.allclose(K2, batch.K.double())  # it did move
    assert torch.equal(out.joints_cam, batch.joints_cam)  # 3D truth: the same camera, unchanged


def test_zero_jitter_is_identity_and_draws_are_reproducible():
    pts = torch.tensor([[0.05, -0.03, 3.0], [-0.1, 0.08, 4.0]], dtype=torch.float64)
    batch = _blob_batch(pts, _K(2))
    none = CropJitter(zoom=0, shift=0, brightness=0, contrast=0, saturation=0)
    out = jitter_batch(batch, none, torch.Generator().manual_seed(3))
    assert torch.equal(out.images, batch.images) and torch.allclose(out.K, batch.K)
    a = jitter_batch(batch, CropJitter(), torch.Generator().manual_seed(5))
    b = jitter_batch(batch, CropJitter(), torch.Generator().manual_seed(5))
    assert torch.equal(a.images, b.images) and torch.equal(a.K, b.K)


def test_joints_pushed_off_the_crop_are_not_visible():
    pts = torch.tensor([[0.28, 0.0, 1.0]], dtype=torch.float64)  # near the right edge
    batch = _blob_batch(pts, _K(1))
    gen = torch.Generator().manual_seed(0)
    seen = []
    for _ in range(30):
        out = jitter_batch(batch, CropJitter(zoom=0.5, shift=0.3), gen)
        inside = bool(
            (out.joints2d[0, 0] <= SIZE - 0.5).all() and (out.joints2d[0, 0] >= -0.5).all()
        )
        assert bool(out.visible[0, 0]) == inside
        seen.append(inside)
    assert any(seen) and not all(seen)


@settings(max_examples=50, deadline=None)
@given(zoom=st.floats(0.5, 2.0), sx=st.floats(-20, 20), sy=st.floats(-20, 20))
def test_similarity_fixes_the_centre_up_to_the_shift(zoom, sx, sy):
    A = similarity(
        torch.tensor([zoom], dtype=torch.float64),
        torch.tensor([[sx, sy]], dtype=torch.float64),
        SIZE,
    )
    c = (SIZE - 1) / 2
    moved = A[0] @ torch.tensor([c, c, 1.0], dtype=torch.float64)
    assert np.allclose(moved[:2].numpy(), [c + sx, c + sy])
    assert np.isclose(float(A[0, 0, 0]), zoom) and np.isclose(float(A[0, 1, 1]), zoom)


def test_warp_by_identity_keeps_the_image():
    img = torch.randint(0, 256, (2, SIZE, SIZE, 3), dtype=torch.uint8)
    A = similarity(torch.ones(2, dtype=torch.float64), torch.zeros(2, 2, dtype=torch.float64), SIZE)
    assert torch.equal(warp_crops(img, A), img)


@pytest.mark.parametrize("bad", [{"zoom": -0.1}, {"shift": 1.0}, {"contrast": 1.5}])
def test_jitter_ranges_are_checked(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        CropJitter(**bad)


def _set(n_frames: int, cams: list[str], truth_keys=("joints_world",)) -> CropSet:
    rows = [(f, c, p) for f in range(n_frames) for c in range(len(cams)) for p in (1, 2)]
    n = len(rows)
    return CropSet(
        images=torch.zeros(n, 8, 8, 3, dtype=torch.uint8),
        masks=torch.zeros(n, 8, 8),
        K=torch.eye(3).repeat(n, 1, 1),
        R=torch.eye(3).repeat(n, 1, 1),
        t=torch.zeros(n, 3),
        camera=torch.tensor([r[1] for r in rows]),
        frame=torch.tensor([r[0] for r in rows]),
        person=torch.tensor([r[2] for r in rows]),
        camera_names=cams,
        truth={k: torch.zeros(n, 24, 3) for k in truth_keys},
    )


def test_concat_keeps_worlds_apart():
    a, b = _set(3, ["c0", "c1"]), _set(2, ["c0", "c1", "c2"])
    both = concat_crop_sets([a, b], ["w0", "w1"])
    assert both.camera_names == ["w0/c0", "w0/c1", "w1/c0", "w1/c1", "w1/c2"]
    assert len(both) == len(a) + len(b)
    groups = both.groups(min_views=1)
    assert len(groups) == 3 * 2 + 2 * 2  # (frame, person) groups never merge across worlds
    for g in groups:
        names = {both.camera_names[int(c)].split("/")[0] for c in both.camera[g]}
        assert len(names) == 1
    with pytest.raises(ValueError, match="truth keys"):
        concat_crop_sets([a, _set(1, ["c0"], truth_keys=("betas",))], ["w0", "w1"])


def test_concat_carries_occluders_and_anchors_or_refuses_to_drop_them():
    a, b = _set(1, ["c0"]), _set(1, ["c0"])
    a.anchors, b.anchors = torch.zeros(len(a), 3), torch.ones(len(b), 3)
    both = concat_crop_sets([a, b], ["w0", "w1"])
    assert torch.equal(both.anchors, torch.cat([a.anchors, b.anchors])) and both.occluders is None
    b.anchors = None
    with pytest.raises(ValueError, match="anchors"):
        concat_crop_sets([a, b], ["w0", "w1"])


@pytest.mark.parametrize(
    "name, row_shape",
    [("landmarks", (33, 3)), ("keypoints", (24, 3)), ("anchors", (3,)), ("occluders", (8, 8))],
)
def test_optional_fields_with_another_row_count_are_refused(name, row_shape):
    """Only the required fields' rows were counted: landmarks, keypoints, anchors, occluders or
    distillation targets of another crop count were taken, at construction or assigned later,
    and training indexed them by crop row (rows of other crops, or an IndexError mid-run)."""
    import dataclasses

    from gst.train.distill_targets import DistillTargets

    a = _set(1, ["c0", "c1"])
    n = len(a)
    setattr(a, name, torch.zeros(n, *row_shape))  # the right count, and None, are taken
    setattr(a, name, None)
    a.distill = DistillTargets.empty(n)
    for wrong in (torch.zeros(n + 1, *row_shape), torch.zeros(n - 1, *row_shape)):
        with pytest.raises(ValueError, match=rf"CropSet\.{name} has {len(wrong)} rows.* {n}"):
            setattr(a, name, wrong)
        with pytest.raises(ValueError, match=rf"CropSet\.{name} has {len(wrong)} rows"):
            dataclasses.replace(a, **{name: wrong})
    assert getattr(a, name) is None
    with pytest.raises(ValueError, match=rf"CropSet\.distill has {n + 1} rows"):
        a.distill = DistillTargets.empty(n + 1)
    with pytest.raises(ValueError, match=rf"CropSet\.distill has {n - 1} rows"):
        dataclasses.replace(a, distill=DistillTargets.empty(n - 1))


def test_concatenating_no_distillation_targets_is_a_clear_error():
    """DistillTargets.concat([]) failed with a bare IndexError (parts[0])."""
    from gst.train.distill_targets import DistillTargets

    with pytest.raises(ValueError, match="at least one"):
        DistillTargets.concat([])
    both = DistillTargets.concat([DistillTargets.empty(2), DistillTargets.empty(3)])
    assert len(both) == 5

"""Background models, mask clean-up, association pieces and external mask/box files."""

import json

import cv2
import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from gst.data.association import PersonTracker
from gst.data.background import (
    BackgroundConfig,
    build_background,
    hysteresis,
    temporal_median,
    temporal_medians,
)
from gst.data.evaluate import CropTruth, association_accuracy, match_truth
from gst.data.external import ExternalError, IdMaskFile, boxes_to_labels, read_external
from gst.data.masks import MaskConfig, clean_mask, fill_small_holes


def _textured(h=120, w=160, seed=0):
    rng = np.random.default_rng(seed)
    base = cv2.resize(
        rng.integers(40, 220, (h // 8, w // 8, 3), dtype=np.uint8),
        (w, h),
        interpolation=cv2.INTER_CUBIC,
    )
    return base


def _scene_frames(n=25):
    """A static textured background with a moving red rectangle and a static cast shadow."""
    bg = _textured()
    frames, truths = [], []
    for i in range(n):
        f = bg.copy()
        x = 5 + 5 * i
        f[40:100, x : x + 20] = (30, 30, 200)
        truth = np.zeros(bg.shape[:2], bool)
        truth[40:100, x : x + 20] = True
        frames.append(f)
        truths.append(truth)
    return bg, np.stack(frames), truths


@pytest.mark.parametrize("method", ["median", "mog2", "knn"])
def test_background_models_find_a_moving_object(method):
    bg, frames, truths = _scene_frames()
    model = build_background(frames, BackgroundConfig(method=method))
    ious = []
    for f, t in zip(frames, truths, strict=True):
        fg = model.foreground(f)
        ious.append((fg & t).sum() / (fg | t).sum())
    assert np.mean(ious) > 0.85, (method, np.mean(ious))


@pytest.mark.parametrize("method", ["median", "mog2", "knn"])
@pytest.mark.parametrize("n", [3, 10])
def test_background_models_learn_from_few_samples(method, n):
    # A short clean plate (or clip) gives fewer samples than KNN keeps per pixel (20): trained
    # on them once, KNN called the whole frame foreground, the empty scene included.
    bg = _textured()
    rng = np.random.default_rng(1)
    plate = np.stack([np.clip(bg + rng.integers(-3, 4, bg.shape), 0, 255) for _ in range(n)])
    model = build_background(plate.astype(np.uint8), BackgroundConfig(method=method))
    empty = model.foreground(bg)
    assert empty.mean() < 0.01, (method, n, empty.mean())
    person = bg.copy()
    person[10:50, 100:120] = (20, 200, 20)
    assert model.foreground(person)[14:46, 104:116].mean() > 0.9


def test_median_background_ignores_shadows_and_recovers_the_empty_scene():
    bg, frames, _ = _scene_frames()
    model = build_background(frames, BackgroundConfig())
    assert np.abs(model.background - bg.astype(np.float32)).max() <= 1
    shadowed = bg.astype(np.float32)
    shadowed[10:30, 10:60] *= 0.6  # same colour, darker: a cast shadow
    assert not model.foreground(shadowed.astype(np.uint8))[10:30, 10:60].any()
    person = bg.copy()
    person[10:30, 10:60] = (20, 200, 20)
    assert model.foreground(person)[12:28, 12:58].all()


def test_temporal_median_matches_numpy():
    x = np.random.default_rng(0).integers(0, 255, (9, 7, 5, 3), dtype=np.uint8)
    assert np.array_equal(temporal_median(x), np.median(x, axis=0).astype(np.uint8))


@pytest.mark.parametrize("n", [1, 2, 9, 60])
def test_one_partial_sort_gives_both_medians(n):
    """`temporal_medians`: the lower middle of `temporal_median` and numpy's median (the mean
    of the two middles for an even count), bit for bit."""
    x = np.random.default_rng(n).integers(0, 255, (n, 7, 5, 3), dtype=np.uint8)
    lower, middle = temporal_medians(x)
    assert np.array_equal(lower, temporal_median(x))
    assert np.array_equal(middle, np.median(x, axis=0))
    assert np.array_equal(middle.astype(np.uint8), np.median(x, axis=0).astype(np.uint8))


def test_hysteresis_keeps_weak_pixels_connected_to_strong_ones():
    weak = np.zeros((10, 10), bool)
    weak[1:4, 1:4] = True
    weak[6:9, 6:9] = True
    strong = np.zeros_like(weak)
    strong[2, 2] = True
    out = hysteresis(strong, weak)
    assert out[1:4, 1:4].all() and not out[6:9, 6:9].any()


def test_clean_mask_removes_speckle_fills_holes_and_filters_shapes():
    m = np.zeros((200, 200), bool)
    m[40:160, 80:120] = True  # a person-sized blob
    m[90:94, 95:99] = False  # a small hole
    m[10, 10] = True  # speckle
    m[180:183, 0:200] = True  # a long thin line (implausible shape)
    labels, blobs = clean_mask(m, MaskConfig())
    assert len(blobs) == 1
    assert labels[92, 96] == 1  # hole filled
    assert labels[10, 10] == 0 and labels[181, 100] == 0
    b = blobs[0]
    assert b.box == (80, 40, 40, 120)


def test_fill_small_holes_keeps_big_holes_and_border_regions():
    m = np.ones((50, 50), bool)
    m[10:40, 10:40] = False  # big hole (900 px)
    m[2:4, 2:4] = False  # small hole
    out = fill_small_holes(m, 100)
    assert out[3, 3] and not out[20, 20]


def test_match_truth_and_association_accuracy():
    truth = np.zeros((10, 10), np.uint8)
    truth[:, :5] = 1
    truth[:, 5:] = 2
    pred = np.zeros((10, 10), bool)
    pred[:, :4] = True
    tid, iou = match_truth(pred, truth)
    assert tid == 1 and iou == pytest.approx(0.8)
    assert match_truth(np.zeros_like(pred), truth) == (0, 0.0)
    rows = [
        CropTruth(0, "a", 5, 1, 1.0),
        CropTruth(0, "b", 5, 1, 1.0),
        CropTruth(0, "c", 6, 2, 1.0),
        CropTruth(1, "a", 5, 1, 1.0),
        CropTruth(1, "b", 5, 2, 1.0),
    ]  # frame 1: one id spans two people
    acc, n = association_accuracy(rows)
    assert n == 5 and acc == pytest.approx(4 / 5)


def test_tracker_keeps_ids_and_gates_by_speed():
    from gst.data.association import Person3D

    def person(x, y):
        return Person3D(
            np.zeros(1, int), np.zeros(1, int), np.zeros(3), np.array([x, y], float), 1.7
        )

    tr = PersonTracker(max_speed=5.0, step_seconds=0.1, slack=0.1)
    assert tr.update([person(0, 0), person(3, 0)]) == [1, 2]
    assert tr.update([person(3.2, 0), person(0.3, 0)]) == [2, 1]  # order swapped, ids follow
    assert tr.update([person(2.0, 0)]) == [3]  # 1.2 m in 0.1 s is too fast for either track


def test_external_folder_masks_boxes_and_errors(tmp_path):
    root = tmp_path / "ext"
    root.mkdir()
    masks = np.zeros((3, 20, 30), np.uint8)
    masks[1, 5:10, 5:10] = 4
    np.savez_compressed(root / "camA.npz", masks=masks, frames=np.array([0, 2, 4]))
    with h5py.File(root / "camB.h5", "w") as f:
        f["masks"] = masks
    pq.write_table(
        pa.table(
            {
                "frame": [0, 0],
                "camera": ["camC", "camC"],
                "x0": [1.0, 10.0],
                "y0": [1.0, 2.0],
                "x1": [8.0, 20.0],
                "y1": [9.0, 12.0],
                "person_id": [3, 4],
            }
        ),
        root / "boxes.parquet",
    )
    (root / "meta.json").write_text(json.dumps({"global_ids": True}))
    ext = read_external(root, ["camA", "camB", "camC"])
    assert ext.global_ids and set(ext.mask_files) == {"camA", "camB"}
    a = ext.masks("camA")
    assert a.get(2)[7, 7] == 4 and a.get(1) is None and a.frames == [0, 2, 4]
    assert ext.masks("camB").get(1)[7, 7] == 4
    assert [pid for pid, _ in ext.camera_boxes("camC")[0]] == [3, 4]
    ext.validate({"camA": (30, 20), "camB": (30, 20), "camC": (30, 20)}, n_frames=5)
    with pytest.raises(ExternalError, match="camera 'camA'.*30x20.*64x48"):
        ext.validate({"camA": (64, 48), "camB": (30, 20), "camC": (30, 20)}, n_frames=5)
    with pytest.raises(ExternalError, match=r"frames \[4\] outside"):
        ext.validate({"camA": (30, 20), "camB": (30, 20), "camC": (30, 20)}, n_frames=3)
    # Boxes become labels: foreground inside the box, or the whole box when little is seen.
    fg = np.zeros((20, 30), np.uint8)
    fg[2:9, 2:6] = 1
    lab = boxes_to_labels(fg, ext.camera_boxes("camC")[0], (30, 20), (1.0, 1.0))
    # Box edges are in pixel-centre coordinates: (10, 2, 20, 12) covers columns 10..20, rows 2..12.
    assert (lab[2:13, 10:21] == 1).all() and not lab[:, 21:].any() and not lab[13:, 10:].any()
    assert (lab[2:9, 2:6] == 2).all()  # the first box: its foreground only
    assert np.count_nonzero(lab == 2) == 4 * 7


def test_external_bad_files_are_named(tmp_path):
    root = tmp_path / "ext"
    root.mkdir()
    with pytest.raises(ExternalError, match="no mask files"):
        read_external(root, ["cam0"])
    np.savez(root / "cam0.npz", masks=np.zeros((2, 4, 4), np.float32))
    with pytest.raises(ExternalError, match=r"cam0.*float32, expected uint8"):
        IdMaskFile(root / "cam0.npz", "cam0")
    np.savez(root / "cam0.npz", a=np.zeros((2, 4, 4), np.uint8), b=np.zeros((2, 4, 4), np.uint8))
    with pytest.raises(ExternalError, match="expected a dataset 'masks'"):
        IdMaskFile(root / "cam0.npz", "cam0")
    (root / "meta.json").write_text("{bad json")
    with pytest.raises(ExternalError, match="meta.json: invalid JSON"):
        read_external(root, ["cam0"])
    (root / "meta.json").write_text(json.dumps({"global_ids": True, "extra": 1}))
    with pytest.raises(ExternalError, match="optional key 'global_ids'"):
        read_external(root, ["cam0"])
    (root / "meta.json").unlink()
    pq.write_table(
        pa.table(
            {"frame": [0], "camera": ["cam0"], "x0": [5.0], "y0": [1.0], "x1": [2.0], "y1": [9.0]}
        ),
        root / "boxes.parquet",
    )
    with pytest.raises(ExternalError, match=r"row 0 \(camera cam0, frame 0\) has an invalid box"):
        read_external(root, ["cam0"])
    pq.write_table(pa.table({"frame": [0], "camera": ["cam0"]}), root / "boxes.parquet")
    with pytest.raises(ExternalError, match=r"missing columns \['x0', 'x1', 'y0', 'y1'\]"):
        read_external(root, ["cam0"])


def test_external_files_that_break_the_reader_name_the_file(tmp_path):
    """An object array, a truncated archive, a group where `frames` should be, the value 255,
    and `person_id` columns pandas writes with gaps (floats with NaN) or that hold names: each
    raised numpy's, h5py's or int()'s own error naming no file, or was read as a person."""
    root = tmp_path / "ext"
    root.mkdir()
    np.savez(root / "cam0.npz", masks=np.zeros((1, 4, 4), np.uint8), frames=np.array([0], object))
    with pytest.raises(ExternalError, match=r"camera 'cam0': cannot read .*cam0.npz"):
        IdMaskFile(root / "cam0.npz", "cam0")
    np.savez(root / "cam0.npz", masks=np.zeros((1, 4, 4), np.uint8))
    data = (root / "cam0.npz").read_bytes()
    (root / "cam0.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(ExternalError, match=r"cannot read .*cam0.npz"):
        IdMaskFile(root / "cam0.npz", "cam0")
    (root / "cam0.npz").unlink()
    with h5py.File(root / "cam0.h5", "w") as f:
        f["masks"] = np.zeros((1, 4, 4), np.uint8)
        f.create_group("frames")
    with pytest.raises(ExternalError, match="'frames' is a group"):
        IdMaskFile(root / "cam0.h5", "cam0")
    (root / "cam0.h5").write_bytes(b"not hdf5")
    with pytest.raises(ExternalError, match=r"cannot read .*cam0.h5"):
        IdMaskFile(root / "cam0.h5", "cam0")
    (root / "cam0.h5").unlink()
    binary = np.zeros((1, 4, 4), np.uint8)
    binary[0, 1:3, 1:3] = 255
    np.savez(root / "cam0.npz", masks=binary)
    with pytest.raises(ExternalError, match="frame 0 holds the value 255"):
        IdMaskFile(root / "cam0.npz", "cam0", external=True).get(0)
    assert IdMaskFile(root / "cam0.npz", "cam0").get(0).max() == 255  # truth: person 255
    (root / "cam0.npz").unlink()

    def boxes(**columns):
        table = {"frame": [0, 1], "camera": ["cam0", "cam0"], "x0": [1.0, 1.0],
                 "y0": [1.0, 1.0], "x1": [3.0, 3.0], "y1": [3.0, 3.0], **columns}  # fmt: skip
        pq.write_table(pa.table(table), root / "boxes.parquet")

    boxes(person_id=[1.0, float("nan")])
    assert [pid for _f, rows in sorted(read_external(root, ["cam0"]).boxes["cam0"].items())
            for pid, _b in rows] == [1, -1]  # fmt: skip
    for pids, match in (([1.7, 2.0], "row 0 is 1.7"), (["p1", "p2"], "'person_id' is string")):
        boxes(person_id=pids)
        with pytest.raises(ExternalError, match=match):
            read_external(root, ["cam0"])
    boxes(camera=["cam0", None])
    with pytest.raises(ExternalError, match="'camera' has 1 empty rows"):
        read_external(root, ["cam0"])
    boxes(x0=[0.1, 0.2], y0=[0.1, 0.2], x1=[0.4, 0.5], y1=[0.9, 0.8])
    with pytest.raises(ExternalError, match="look normalised"):
        read_external(root, ["cam0"]).validate({"cam0": (40, 30)}, n_frames=2)
    boxes(x0=[1.0, 45.0], x1=[3.0, 60.0])  # the second beyond the 40 px wide frame
    with pytest.raises(ExternalError, match=r"1 boxes entirely outside the 40x30 frame"):
        read_external(root, ["cam0"]).validate({"cam0": (40, 30)}, n_frames=2)


def _one_box(root, frame, frame_type=None) -> None:
    pq.write_table(
        pa.table({"frame": pa.array([frame], frame_type or pa.int64()), "camera": ["cam0"],
                  "x0": [1.0], "y0": [1.0], "x1": [3.0], "y1": [3.0]}),
        root / "boxes.parquet",
    )  # fmt: skip


def test_external_inputs_that_would_be_misread_are_refused(tmp_path):
    """Each of these was read silently, and wrongly: the text "false" as global ids on, a mask
    file named after no camera skipped (that camera falling back to the background model),
    repeated or fractional mask frame numbers (one mask lost, frames truncated), and box frames
    that are 1-based, fractional or missing (every box a frame late, the last one dropped)."""
    root = tmp_path / "ext"
    root.mkdir()
    _one_box(root, 0)
    (root / "meta.json").write_text(json.dumps({"global_ids": "false"}))
    with pytest.raises(ExternalError, match="global_ids is 'false', expected true or false"):
        read_external(root, ["cam0"])
    (root / "meta.json").unlink()
    np.savez(root / "Cam0.npz", masks=np.zeros((1, 4, 4), np.uint8))
    with pytest.raises(ExternalError, match=r"\['Cam0.npz'\] are named after no camera"):
        read_external(root, ["cam0"])
    (root / "Cam0.npz").unlink()
    for frames, match in (([5, 5], r"frames \[5\] more than once"), ([0.5, 1.9], "float64")):
        np.savez(root / "cam0.npz", masks=np.zeros((2, 4, 4), np.uint8), frames=np.array(frames))
        with pytest.raises(ExternalError, match=match):
            IdMaskFile(root / "cam0.npz", "cam0")
    (root / "cam0.npz").unlink()
    _one_box(root, 10)
    with pytest.raises(ExternalError, match=r"frames \[10\] outside the video's 0..9"):
        read_external(root, ["cam0"]).validate({"cam0": (4, 4)}, n_frames=10)
    _one_box(root, 1.7, pa.float64())
    with pytest.raises(ExternalError, match="column 'frame' is double"):
        read_external(root, ["cam0"])
    _one_box(root, None)
    with pytest.raises(ExternalError, match="with 1 nulls"):
        read_external(root, ["cam0"])


def test_truth_scoring_on_a_bounding_box_matches_full_resolution():
    from gst.data.evaluate import match_truth
    from gst.data.extract import score_against_truth

    rng = np.random.default_rng(3)
    truth = np.zeros((120, 160), np.uint8)
    cv2.ellipse(truth, (60, 60), (20, 40), 10, 0, 360, 3, -1)
    cv2.ellipse(truth, (110, 70), (15, 35), 0, 0, 360, 5, -1)
    work = np.zeros((60, 80), bool)
    cv2.ellipse(work.view(np.uint8), (31, 30), (10, 19), 12, 0, 360, 1, -1)
    work |= rng.random(work.shape) > 0.995
    full = (
        cv2.resize(work.astype(np.uint8) * 255, (160, 120), interpolation=cv2.INTER_LINEAR) >= 128
    )
    tid_ref, iou_ref = match_truth(full, truth)
    tid, iou = score_against_truth(work, truth, np.bincount(truth.ravel(), minlength=256))
    assert tid == tid_ref == 3
    assert iou == pytest.approx(iou_ref, abs=0.01)

"""Supplied boxes and predictor outputs: good input loads, bad input names the culprit."""

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from gst.data.camera_view import default_camera
from gst.data.crop import crop_intrinsics, crop_window
from gst.track.baseline import BoxDepthPredictor
from gst.track.detection import Detection, Detector, SuppliedBoxes, SuppliedBoxesError
from gst.track.predictor import PredictorOutputError, predict_batched, validate_prediction


def test_csv_with_two_videos(tmp_path):
    p = tmp_path / "boxes.csv"
    p.write_text(
        "video,frame,x0,y0,x1,y1,score,id\n"
        "a,0,10,20,50,120,0.9,3\n"
        "a,0,60,20,90,110,,\n"
        "b,0,1,1,5,5,1,\n"
        "a,2,12,20,52,121,0.8,3\n"
    )
    boxes = SuppliedBoxes.from_file(p, "a")
    assert isinstance(boxes, Detector)
    d0 = boxes.detect(np.zeros((4, 4, 3), np.uint8), 0)
    assert [d.box.tolist() for d in d0] == [[10, 20, 50, 120], [60, 20, 90, 110]]
    assert [d.score for d in d0] == [0.9, 1.0] and [d.id_hint for d in d0] == [3, None]
    assert boxes.detect(None, 1) == [] and len(boxes.detect(None, 2)) == 1
    with pytest.raises(SuppliedBoxesError, match="several videos"):
        SuppliedBoxes.from_file(p)
    with pytest.raises(SuppliedBoxesError, match="no boxes for video 'c'"):
        SuppliedBoxes.from_file(p, "c")


def test_parquet_boxes(tmp_path):
    p = tmp_path / "boxes.parquet"
    pq.write_table(
        pa.table(
            {
                "frame": [0, 0, 5],
                "x0": [1.0, 2, 3],
                "y0": [1.0, 2, 3],
                "x1": [9.0, 9, 9],
                "y1": [9.0, 9, 9],
            }
        ),
        p,
    )
    boxes = SuppliedBoxes.from_file(p)
    assert len(boxes.detect(None, 0)) == 2 and boxes.detect(None, 5)[0].score == 1.0


@pytest.mark.parametrize(
    "content, message",
    [
        ("frame,x0,y0,x1\n0,1,2,3\n", r"missing column\(s\) \['y1'\]"),
        ("frame,x0,y0,x1,y1\n0,1,2,zz,4\n", "row 2: non-numeric"),
        ("frame,x0,y0,x1,y1\n0,1,2,3,4\n0,5,5,4,9\n", "row 3: detection box must be"),
        ("frame,x0,y0,x1,y1\n-1,1,2,3,4\n", "row 2: frame must be >= 0"),
        # a trailing comma: the extra field came under DictReader's None key (AttributeError)
        ("frame,x0,y0,x1,y1\n0,1,2,3,4,\n", "row 2: more fields than the header"),
        # a non-finite score was kept, then silently dropped by `score >= min_score`
        ("frame,x0,y0,x1,y1,score\n0,1,2,3,4,nan\n", "row 2: score must be finite"),
        ("frame,x0,y0,x1,y1,score\n0,1,2,3,4,inf\n", "row 2: score must be finite"),
    ],
)
def test_bad_box_files_name_file_and_row(tmp_path, content, message):
    p = tmp_path / "bad.csv"
    p.write_text(content)
    with pytest.raises(SuppliedBoxesError, match=message) as err:
        SuppliedBoxes.from_file(p)
    assert "bad.csv" in str(err.value)


def test_unsupported_or_missing_box_file(tmp_path):
    with pytest.raises(SuppliedBoxesError, match="not found"):
        SuppliedBoxes.from_file(tmp_path / "none.csv")
    (tmp_path / "boxes.txt").write_text("x")
    with pytest.raises(SuppliedBoxesError, match="expected .csv or .parquet"):
        SuppliedBoxes.from_file(tmp_path / "boxes.txt")


def test_detection_validates_box():
    with pytest.raises(ValueError, match="x0 < x1"):
        Detection(np.array([5.0, 0, 5, 10]))


def test_prediction_contract_errors_name_the_key():
    good = BoxDepthPredictor()(np.zeros((2, 64, 64, 3), np.uint8), np.stack([np.eye(3)] * 2))
    assert len(validate_prediction(good, 2)) == 2
    with pytest.raises(PredictorOutputError, match="lacks 'joints_cam'"):
        validate_prediction({k: v for k, v in good.items() if k != "joints_cam"}, 2)
    bad = dict(good, rotmats=good["rotmats"][:, :23])
    with pytest.raises(
        PredictorOutputError, match=r"'rotmats' has shape \(2, 23, 3, 3\), expected \(2, 24, 3, 3\)"
    ):
        validate_prediction(bad, 2)
    with pytest.raises(PredictorOutputError, match="must return a dict"):
        validate_prediction([1, 2], 2)


def test_batched_prediction_equals_one_call():
    cam = default_camera(1920, 1080)
    rng = np.random.default_rng(0)
    Ks = []
    for _ in range(11):
        x, y = rng.uniform(0, 1700), rng.uniform(0, 800)
        Ks.append(
            crop_intrinsics(
                cam.K, crop_window([x, y, x + rng.uniform(30, 200), y + rng.uniform(80, 300)])
            )
        )
    crops = np.zeros((11, 256, 256, 3), np.uint8)
    pred = BoxDepthPredictor()
    one = validate_prediction(pred(crops, np.stack(Ks)), 11)
    many = predict_batched(pred, crops, np.stack(Ks), batch_size=4)
    np.testing.assert_allclose(many.joints_cam, one.joints_cam)


def test_baseline_places_pelvis_on_the_box_centre_ray_at_the_implied_depth():
    cam = default_camera(1920, 1080)
    box = [800.0, 300.0, 900.0, 640.0]  # 340 px tall
    K_crop = crop_intrinsics(cam.K, crop_window(box))
    out = BoxDepthPredictor(height_m=1.7)(np.zeros((1, 256, 256, 3), np.uint8), K_crop[None])
    pelvis = out["joints_cam"][0, 0]
    assert pelvis[2] == pytest.approx(cam.fy * 1.7 / 340)  # same depth in full-frame terms
    uv = pelvis[:2] / pelvis[2] * cam.fx + [cam.cx, cam.cy]
    np.testing.assert_allclose(uv, [849.5, 469.5], atol=1e-9)  # box centre, pixel-centre convention


def test_parquet_fractional_frame_is_refused(tmp_path):
    """A float frame column (2.7) was truncated to frame 2 without a word."""
    p = tmp_path / "boxes.parquet"
    table = {"frame": [0.0, 2.7], "x0": [1.0, 1], "y0": [1.0, 1], "x1": [9.0, 9], "y1": [9.0, 9]}
    pq.write_table(pa.table(table), p)
    with pytest.raises(SuppliedBoxesError, match="row 1: frame must be a whole number"):
        SuppliedBoxes.from_file(p)
    pq.write_table(pa.table({**table, "frame": [0.0, 2.0]}), p)  # whole floats still read
    assert len(SuppliedBoxes.from_file(p).detect(None, 2)) == 1

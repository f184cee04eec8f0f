"""The track summary's checks of the body against the landmark model (gst.track.agreement):
joints2d against the landmarks, and the body's own BlazePose points (virtual markers) against
them, on tables whose landmarks are made from a known body."""

import numpy as np
import pyarrow as pa
import pytest
import torch

from gst.body import load_body_model
from gst.body.markers import MarkerModel
from gst.data.camera_view import default_camera
from gst.track.agreement import (
    COMPARED_INDEX,
    body_markers_2d,
    joints_vs_landmarks,
    markers_vs_landmarks,
)
from gst.track.schema import file_metadata, tracks_schema

W, H = 1088, 1920


@pytest.fixture(scope="module")
def body():
    return load_body_model("anny")


@pytest.fixture(scope="module")
def markers():
    return MarkerModel.load()


def _fixed(a: np.ndarray) -> pa.FixedSizeListArray:
    a = np.asarray(a, np.float32).reshape(len(a), -1)
    return pa.FixedSizeListArray.from_arrays(pa.array(a.reshape(-1)), a.shape[1])


def _project(points: np.ndarray) -> np.ndarray:
    K = default_camera(W, H).K
    return points[..., :2] / points[..., 2:] @ K[:2, :2].T + K[:2, 2]


def _own_points(table, body, markers, **kw):
    return markers_vs_landmarks(table, body_markers_2d(table, body, markers, _project), **kw)


def _table(body, markers, n: int = 6, seed: int = 0, shift=(0.0, 0.0), conf: float = 0.9):
    """`n` rows of random people facing the camera 4 m away; landmarks = the body's own
    BlazePose points projected, moved by `shift` px, with confidence `conf`."""
    g = torch.Generator().manual_seed(seed)
    body_pose = 0.3 * (torch.rand(n, 69, generator=g) - 0.5)
    orient = torch.tensor([[np.pi, 0.0, 0.0]]).repeat(n, 1)  # body y up -> camera y down
    transl = torch.tensor([[0.0, 0.2, 4.0]]) + 0.2 * (torch.rand(n, 3, generator=g) - 0.5)
    betas = 0.5 * torch.randn(n, 10, generator=g)
    with torch.no_grad():  # posed here, not through the table, so the reading is checked too
        out = body(
            betas, body_pose, orient, transl, vertex_ids=markers.vertex_ids, return_transforms=True
        )
    joints = out.joints.numpy().astype(np.float64)
    own = markers.positions(out).numpy().astype(np.float64)
    cols = {
        "frame": pa.array(np.arange(n), pa.int64()),
        "time_s": pa.array(np.arange(n) / 30.0),
        "person_id": pa.array(np.ones(n, np.int64)),
        "bbox": _fixed(np.tile([100.0, 100.0, 900.0, 1800.0], (n, 1))),
        "score": pa.array(np.ones(n, np.float32)),
        "global_orient": _fixed(np.zeros((n, 3))),  # world: must not be read for the camera
        "global_orient_cam": _fixed(orient.numpy()),
        "body_pose": _fixed(body_pose.numpy()),
        "betas": _fixed(betas.numpy()),
        "transl_cam": _fixed(transl.numpy()),
        "transl_world": pa.nulls(n, pa.list_(pa.float32(), 3)),
        "joints3d": _fixed(joints),
        "joints2d": _fixed(_project(joints)),
        "landmarks2d": pa.nulls(n, pa.list_(pa.float32(), 66)),
        "landmarks_conf": pa.nulls(n, pa.list_(pa.float32(), 33)),
    }
    meta = file_metadata(
        fps=30.0,
        model={"name": "test", "version": "0", "body_model": "anny"},
        calibration={"calibrated": False},
        axes={"joints3d": "camera"},
        video={"name": "clip", "width": W, "height": H},
        tracking={},
        smoothing=None,
        stats={"rows": n},
        settings_sha256="0",
    )
    table = pa.table(cols, schema=tracks_schema(10, meta))
    lm = _project(own) + np.asarray(shift)
    table = table.set_column(
        table.schema.get_field_index("landmarks2d"), table.schema.field("landmarks2d"),
        _fixed(lm),
    )  # fmt: skip
    return table.set_column(
        table.schema.get_field_index("landmarks_conf"), table.schema.field("landmarks_conf"),
        _fixed(np.full((n, 33), conf)),
    )  # fmt: skip


def test_the_bodys_own_points_agree_exactly_where_its_joints_show_the_definition_offset(
    body, markers
):
    table = _table(body, markers)
    same = _own_points(table, body, markers)
    joints = joints_vs_landmarks(table)
    assert same.pairs == joints.pairs == 6 * len(COMPARED_INDEX)
    assert same.median_px < 1e-3
    # a perfect body's joints are not where BlazePose puts its landmarks: several px at 4 m
    assert joints.median_px > 2.0
    assert set(same.per_joint_median_px) == set(joints.per_joint_median_px)


def test_a_shift_of_the_landmarks_is_measured_as_that_shift(body, markers):
    same = _own_points(_table(body, markers, shift=(3.0, 4.0)), body, markers)
    assert same.median_px == pytest.approx(5.0, abs=1e-3)
    assert same.p90_px == pytest.approx(5.0, abs=1e-3)


def test_unsure_landmarks_are_not_compared(body, markers):
    table = _table(body, markers, conf=0.3)
    assert _own_points(table, body, markers).pairs == 0
    assert _own_points(table, body, markers, min_confidence=0.2).pairs > 0
    assert joints_vs_landmarks(table).median_px is None


def test_the_table_is_read_as_it_was_posed(body, markers):
    table = _table(body, markers)
    got = body_markers_2d(table, body, markers, _project, batch=4)  # two batches
    lm = np.asarray(table.column("landmarks2d").to_pylist()).reshape(-1, 33, 2)
    np.testing.assert_allclose(got, lm, atol=1e-3)


def test_a_table_without_rows_has_no_figure(body, markers):
    empty = _table(body, markers).slice(0, 0)
    assert _own_points(empty, body, markers).median_px is None

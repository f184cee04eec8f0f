"""Fused outputs: the TRC opens with OpenSim's header (Y up), the C3D reads back identical
through the `c3d` library, bodies.parquet has the tracks schema's columns and metadata."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gst.body.skeleton import SMPL_JOINT_NAMES
from gst.fuse.export import (
    Z_UP_TO_Y_UP,
    read_c3d,
    read_trc,
    write_c3d,
    write_trc,
    y_up_rotation,
)
from gst.track.schema import METADATA_KEYS, column_specs


def _points(T=5, M=24, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform([-2, -2, 0], [2, 2, 2], (T, M, 3))


def test_trc_header_units_and_y_up(tmp_path):
    pts = _points()
    frames = np.arange(10, 15)
    path = tmp_path / "person_1.trc"
    write_trc(path, frames, pts, fps=60.0)
    lines = path.read_text().splitlines()
    assert lines[0].split("\t") == ["PathFileType", "4", "(X/Y/Z)", "person_1.trc"]
    assert lines[1].split("\t") == [
        "DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate",
        "OrigDataStartFrame", "OrigNumFrames",
    ]  # fmt: skip
    assert lines[2].split("\t") == ["60", "60", "5", "24", "m", "60", "11", "5"]
    # an NTSC rate is written as it is (29.97 put rebuilt times 1.8 ms off after 30 minutes)
    write_trc(path, frames, pts, fps=30000 / 1001)
    assert float(path.read_text().splitlines()[2].split("\t")[0]) == pytest.approx(
        30000 / 1001, rel=1e-9
    )
    write_trc(path, frames, pts, fps=60.0)
    assert lines[3].split("\t")[:3] == ["Frame#", "Time", "pelvis"]
    assert lines[4].split("\t")[2:5] == ["X1", "Y1", "Z1"]
    header, names, fr, back = read_trc(path)
    assert names == list(SMPL_JOINT_NAMES) and fr.tolist() == [11, 12, 13, 14, 15]
    assert header["Units"] == "m"
    # Y up: world z (height) becomes TRC y, and the rotation is proper
    np.testing.assert_allclose(back[..., 1], pts[..., 2], atol=1e-6)
    np.testing.assert_allclose(back, pts @ Z_UP_TO_Y_UP.T, atol=1e-6)
    assert np.isclose(np.linalg.det(Z_UP_TO_Y_UP), 1.0)


def test_c3d_round_trip_is_identical(tmp_path):
    pts = _points(T=7)
    valid = np.ones((7, 24), bool)
    valid[3, 5] = False
    path = tmp_path / "p.c3d"
    write_c3d(path, np.arange(20, 27), pts, fps=30.0, valid=valid)
    names, rate, frames, back = read_c3d(path)
    assert names == list(SMPL_JOINT_NAMES) and rate == 30.0
    assert frames.tolist() == list(range(21, 28))
    np.testing.assert_array_equal(back[..., :3], (pts * 1000).astype(np.float32))
    # the C3D format's residuals: 0 a modelled point (the fit filled it), > 0 a measured one
    # (the two were the other way round)
    assert back[3, 5, 3] == 0 and (np.delete(back[..., 3].ravel(), 3 * 24 + 5) == 1).all()


def test_c3d_holds_what_other_readers_need(tmp_path):
    """Found with ezc3d: GST:FIRST_FRAME was an int32 under the format's float label (read as
    1.4e-43 for frame 100), measured points had an empty camera byte (ezc3d reads that byte as
    the residual: every point modelled), and POINT:SCALE was -1 whatever the coordinates."""
    import c3d

    pts = _points(T=5)
    valid = np.ones((5, 24), bool)
    valid[2, 7] = False
    cams = np.full((5, 24), 0b1011, np.int64)
    cams[1, 3] = 1 << 9  # only an eighth-or-later camera: the byte has 7 bits
    path = tmp_path / "p.c3d"
    write_c3d(path, np.arange(100, 105), pts, fps=50.0, valid=valid, cameras=cams)
    with open(path, "rb") as fh:
        reader = c3d.Reader(fh)
        assert reader.get("GST:FIRST_FRAME").float_value == 100
        scale = reader.point_scale
        biggest = float(np.abs(pts).max() * 1000)
        assert -1 < scale < 0 and abs(scale) >= biggest / 32000 and (1 / abs(scale)).is_integer()
        rows = [p.copy() for _, p, _ in reader.read_frames()]
    camera_byte = np.array([r[:, 4] for r in rows])
    assert camera_byte[2, 7] == 0 and camera_byte[1, 3] == 0  # modelled; camera out of reach
    assert (np.delete(camera_byte.ravel(), [2 * 24 + 7, 24 + 3]) == 0b1011).all()
    names, rate, frames, back = read_c3d(path)
    assert frames.tolist() == list(range(101, 106))
    assert back[2, 7, 3] == 0 and (np.delete(back[..., 3].ravel(), 2 * 24 + 7) == 1).all()


def test_c3d_camera_byte_of_a_rig_beyond_53_cameras(tmp_path):
    """The camera masks went through float64, which cannot hold a mask with camera 61's bit
    exactly: cameras 1-7's bits were lost from that point's byte."""
    import c3d

    pts = _points(T=2)
    cams = np.full((2, 24), 0b101, np.int64)
    cams[:, 0] |= np.int64(1) << 60
    path = tmp_path / "p.c3d"
    write_c3d(path, np.arange(2), pts, fps=30.0, cameras=cams)
    with open(path, "rb") as fh:
        rows = [p.copy() for _, p, _ in c3d.Reader(fh).read_frames()]
    assert (np.array([r[:, 4] for r in rows]) == 0b101).all()


def test_c3d_refuses_what_it_cannot_hold(tmp_path):
    """Names were cut to 30 characters (two could become one label, the TRC keeping both
    whole), and no frame failed inside the `c3d` writer with a shape message."""
    pts = _points(T=2)
    names = tuple(f"m{i}" for i in range(23)) + ("a_marker_name_longer_than_thirty_chars",)
    with pytest.raises(ValueError, match="longer than a C3D label's 30 characters"):
        write_c3d(tmp_path / "p.c3d", np.arange(2), pts, fps=30.0, names=names)
    with pytest.raises(ValueError, match="no frame to write"):
        write_c3d(tmp_path / "p.c3d", np.arange(0), pts[:0], fps=30.0)
    assert not list(tmp_path.iterdir())


def test_c3d_written_before_the_float_first_frame_still_reads(tmp_path):
    """Files of before 2026-12-01 hold GST:FIRST_FRAME as an int32 under the float label."""
    import warnings

    import c3d

    pts = _points(T=3)
    writer = c3d.Writer(point_rate=30.0, analog_rate=0.0, point_scale=-1.0)
    writer.set_point_labels(list(SMPL_JOINT_NAMES))
    writer.set_start_frame(101)
    group = writer.add_group(10, "GST", "gst-capture")
    group.set("FIRST_FRAME", "video frame of the first row (0-based)", 4, "<i", 100)
    data = np.zeros((3, 24, 5), np.float32)
    data[..., :3] = pts * 1000
    data[..., 3] = 1.0
    writer.add_frames([(data[i], np.zeros((0, 0), np.float32)) for i in range(3)])
    with open(tmp_path / "old.c3d", "wb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        writer.write(fh)
    assert read_c3d(tmp_path / "old.c3d")[2].tolist() == [101, 102, 103]


def test_bodies_parquet_has_the_tracks_schema(tmp_path):
    from gst.fuse.fit import PersonFit
    from gst.fuse.tables import EXTRA_COLUMNS, joint_evidence, write_bodies

    T, C = 4, 3
    rng = np.random.default_rng(1)
    fit = PersonFit(
        7, np.arange(T), rng.normal(size=10), rng.normal(size=(T, 3)), rng.normal(size=(T, 23, 3)),
        rng.normal(size=(T, 3)), rng.normal(size=(T, 24, 3)), rng.normal(size=(T, 33, 3)),
        np.abs(rng.normal(size=(T, C, 33))), np.ones(T, bool), np.zeros(T, bool), False, 3.0,
    )  # fmt: skip
    ev = joint_evidence(fit, None)
    path = tmp_path / "bodies.parquet"
    write_bodies(
        path, [fit], [ev], fps=30.0, camera_names=["a", "b", "c"], model={"name": "x"},
        settings={}, settings_sha256="0", stats={}, world_up=(0.0, -1.0, 0.0),
    )  # fmt: skip
    t = pq.read_table(path)
    names = [s.name for s in column_specs(10)]
    assert t.column_names == names + list(EXTRA_COLUMNS)
    meta = t.schema.metadata
    assert all(k.encode() in meta for k in METADATA_KEYS)
    assert json.loads(meta[b"gst.axes"])["joints3d"] == "world"
    assert json.loads(meta[b"gst.axes"])["world_up"] == [0.0, -1.0, 0.0]  # the rig's, not +Z
    # the tracks file's layout: axes["world"]["up"] raised TypeError on a fused file
    assert json.loads(meta[b"gst.axes"])["world"]["up"] == [0.0, -1.0, 0.0]
    joints = np.stack(t.column("joints3d").to_numpy(zero_copy_only=False)).reshape(-1, 24, 3)
    np.testing.assert_allclose(joints, fit.joints, rtol=1e-6)
    assert t.column("joints2d").null_count == T
    assert np.stack(t.column("joint_gap_filled").to_numpy(zero_copy_only=False)).all(axis=0)[0]
    # `score` is the fit's share of triangulated joints, not a detection score, and the fused
    # columns are in the file's own column table (they were in `gst.fused` only)
    columns = json.loads(meta[b"gst.columns"])
    assert "triangulated" in columns["score"]["description"]
    assert "triangulated" in t.schema.field("score").metadata[b"description"].decode()
    assert columns["joint_reprojection_px"]["shape"] == [24]
    assert set(EXTRA_COLUMNS) <= set(columns)


def test_marker_files_keep_a_row_for_every_frame_of_a_gap(tmp_path):
    """A gap the fit does not fill has no bodies.parquet rows; the marker files hold it as rows
    of missing markers, so that their constant rate stays true (a C3D has no frame column: a
    dropped row would put every later frame early)."""
    frames = np.array([0, 1, 2, 3, 10, 11])
    pts = _points(T=6)
    write_trc(tmp_path / "p.trc", frames, pts, fps=30.0)
    header, _, fr, back = read_trc(tmp_path / "p.trc")
    assert header["NumFrames"] == "12" and fr.tolist() == list(range(1, 13))
    assert np.isnan(back[4:10]).all()
    np.testing.assert_allclose(back[[0, 1, 2, 3, 10, 11]], pts @ Z_UP_TO_Y_UP.T, atol=1e-6)
    # OpenSim's reader drops a line's empty last field and wants 2 + 3 x markers fields: a gap
    # row (its last marker blank) without the trailing tab OpenSim's writer puts was one short
    # and the whole file was refused
    for row in (tmp_path / "p.trc").read_text().splitlines()[6:]:
        fields = row.split("\t")
        fields = fields[:-1] if fields[-1] == "" else fields
        assert len(fields) == 2 + 3 * 24, row[:40]
    write_c3d(tmp_path / "p.c3d", frames, pts, fps=30.0)
    _, _, fr, back = read_c3d(tmp_path / "p.c3d")
    assert fr.tolist() == list(range(1, 13))
    assert (back[4:10, :, 3] == -1).all() and (back[[0, 1, 2, 3, 10, 11], :, 3] == 1).all()
    np.testing.assert_array_equal(back[10, :, :3], (pts[4] * 1000).astype(np.float32))
    # a missing point's coordinates are 0, as the format wants (the c3d writer left frame 3's
    # there: a body frozen through the gap)
    assert (back[4:10, :, :3] == 0).all()


@pytest.mark.filterwarnings("ignore:No analog data found")
def test_c3d_of_a_person_who_first_appears_late_in_a_long_video(tmp_path):
    """The C3D header's first frame is 16 bits: a person first seen at video frame 70000 is
    numbered from 1 in the file, GST:FIRST_FRAME holds 70000, and every reader gets 3 frames."""
    import c3d

    pts = _points(T=3)
    path = tmp_path / "late.c3d"
    write_c3d(path, np.arange(70000, 70003), pts, fps=60.0)
    _, _, frames, back = read_c3d(path)
    assert frames.tolist() == [70001, 70002, 70003]
    np.testing.assert_array_equal(back[..., :3], (pts * 1000).astype(np.float32))
    with open(path, "rb") as fh:
        reader = c3d.Reader(fh)
        assert len(list(reader.read_frames())) == 3
        # a float, as its element size says (it was an int32 under the float label: every
        # other reader saw 9.8e-41)
        assert reader.get("GST:FIRST_FRAME").float_value == 70000
        assert reader.get("POINT:Y_SCREEN").string_value.strip() == "+Z"


def test_joints_without_landmarks_are_fitted_where_the_torso_is():
    from gst.fuse.tables import JointEvidence

    has = np.ones(24, bool)
    spine = [SMPL_JOINT_NAMES.index(n) for n in ("spine1", "spine2", "spine3", "neck")]
    has[spine] = False
    gap = np.zeros((3, 24), bool)
    gap[1, SMPL_JOINT_NAMES.index("left_shoulder")] = True  # frame 1: a torso joint filled
    gap[2, SMPL_JOINT_NAMES.index("left_wrist")] = True  # frame 2: only a wrist filled
    ev = JointEvidence(np.zeros((3, 24), np.uint8), np.zeros((3, 24), np.int64), np.zeros((3, 24)),
                       gap, has)  # fmt: skip
    fitted = ev.fitted_only()
    assert not fitted[0].any()
    assert fitted[1, spine].all() and fitted[1, SMPL_JOINT_NAMES.index("left_shoulder")]
    assert not fitted[2, spine].any() and fitted[2, SMPL_JOINT_NAMES.index("left_wrist")]
    assert (fitted[:, has] == gap[:, has]).all()


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 0.1))
def test_y_up_rotation_is_proper_and_puts_the_worlds_up_on_y(up):
    R = y_up_rotation(up)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.isclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(R @ (np.asarray(up) / np.linalg.norm(up)), [0, 1, 0], atol=1e-9)


def test_marker_files_of_a_y_down_world_stand_upright(tmp_path):
    """A Panoptic rig's world has up (0, -1, 0): the TRC's y is the height along it (was: the
    Z-up rotation, which laid the body on its back), the C3D's screen axis is -Y."""
    import c3d

    np.testing.assert_array_equal(y_up_rotation((0, 0, 1)), Z_UP_TO_Y_UP)
    pts = _points()
    write_trc(tmp_path / "p.trc", np.arange(5), pts, fps=30.0, up=(0.0, -1.0, 0.0))
    back = read_trc(tmp_path / "p.trc")[3]
    np.testing.assert_allclose(back[..., 1], -pts[..., 1], atol=1e-6)
    write_c3d(tmp_path / "p.c3d", np.arange(5), pts, fps=30.0, up=(0.0, -1.0, 0.0))
    with open(tmp_path / "p.c3d", "rb") as fh:
        point = c3d.Reader(fh).get("POINT")
        assert point.get("Y_SCREEN").string_value.strip() == "-Y"
        assert point.get("X_SCREEN").string_value.strip() == "+X"


@pytest.mark.parametrize("up", [(1e-8, 0.0, -1.0), (1e-5, 0.0, -1.0), (0.0, 0.0, -1.0)])
def test_y_up_rotation_near_a_downward_up(up):
    """A z-down world with float noise in its up (the smallest rotation's formula divided by
    1 + cos ~ 0: a NaN matrix at 1e-8)."""
    R = y_up_rotation(up)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R @ (np.asarray(up) / np.linalg.norm(up)), [0, 1, 0], atol=1e-12)


@pytest.mark.parametrize(
    "corrections, verdict",
    [
        ({"cam01": 0.31, "cam03": 0.46}, "Worth calibrating again: cam03 (more than 0.4 degrees)"),
        ({"cam01": 0.05, "cam02": 0.1}, "None more than 0.4 degrees: the calibration holds"),
    ],
)
def test_the_report_says_which_cameras_to_calibrate_again(tmp_path, corrections, verdict):
    """'A correction of more than a few tenths of a degree says the calibration is worth
    redoing' left a user with cam03 at 0.45 to guess."""
    from gst.fuse.report import FuseSummary, write_report

    write_report(FuseSummary(camera_corrections_deg=corrections), tmp_path, [], [])
    assert verdict in (tmp_path / "report.md").read_text()


def test_summary_json_is_strict_json_when_nothing_matched_the_truth(tmp_path):
    """A synthetic scene where no fused body was paired with the truth has no MPJPE: the
    summary said `NaN`, which is not JSON (jq and JavaScript refused the file); it is null."""
    from gst.fuse.evaluate import compare_with_truth
    from gst.fuse.report import summarise, write_report

    truth = compare_with_truth([], None).as_dict()
    summary = summarise([], [], [], ["cam01"], 10, truth=truth)
    write_report(summary, tmp_path, [], [])

    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")

    doc = json.loads((tmp_path / "summary.json").read_text(), parse_constant=refuse)
    assert doc["truth"]["mpjpe_mm"] is None and doc["truth"]["vertex_error_mm"] is None
    assert "| - | - | - |" in (tmp_path / "report.md").read_text()


def test_trc_refuses_a_person_of_no_frames(tmp_path):
    """A TRC without a data row was written (NumFrames 0); OpenSim's reader skips the blank
    lines before the first row and, at the end of the file, never stops. Refused, as the C3D
    writer refuses it, and nothing is left behind."""
    path = tmp_path / "person_1.trc"
    with pytest.raises(ValueError, match="no frame"):
        write_trc(path, np.zeros(0, np.int64), np.zeros((0, 24, 3)), fps=30.0)
    assert not path.exists()


def test_an_overlay_that_fails_leaves_no_partial_video(tmp_path, monkeypatch):
    """OpenCV encodes to `<temporary>.mp4` beside the output; a video that failed (or was
    interrupted) part-way left that partial file in the overlay folder, one more per try."""
    import cv2

    from gst.fuse import overlay
    from gst.fuse.fit import PersonFit

    src = tmp_path / "cam01.mp4"
    vw = cv2.VideoWriter(str(src), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (64, 48))
    for _ in range(3):
        vw.write(np.zeros((48, 64, 3), np.uint8))
    vw.release()
    T = 3
    fit = PersonFit(
        1, np.arange(T), np.zeros(10), np.zeros((T, 3)), np.zeros((T, 23, 3)), np.zeros((T, 3)),
        np.zeros((T, 24, 3)), np.zeros((T, 33, 3)), np.zeros((T, 1, 33)), np.ones(T, bool),
        np.zeros(T, bool), False, 3.0,
    )  # fmt: skip

    class Rig:
        names = ["cam01"]

        def __getitem__(self, name):
            return None

    def fail(img, cam, fit, i, verts, colour):
        if i == 1:
            raise RuntimeError("drawing failed")

    monkeypatch.setattr(overlay, "_vertices", lambda body, f, ids: np.zeros((T, len(ids), 3)))
    monkeypatch.setattr(overlay, "_draw", fail)
    body = type("Body", (), {"num_vertices": 24})()
    out = tmp_path / "overlay"
    with pytest.raises(RuntimeError, match="drawing failed"):
        overlay.write_overlays([fit], body, Rig(), {"cam01": src}, out)
    assert sorted(p.name for p in out.iterdir()) == []


@pytest.mark.filterwarnings("ignore:No analog data found")
def test_c3d_header_counts_every_frame_of_a_person_who_ends_past_the_16_bit_frame(tmp_path):
    """First seen at video frame 60000 (fits the header's 16-bit first frame) for 8000 frames
    (the last, 68000, does not): the header said frames 60001-65535, 5535 frames over 8000
    rows. Such a person is numbered from 1, as a late start is; GST:FIRST_FRAME keeps 60000."""
    import c3d

    path = tmp_path / "long.c3d"
    write_c3d(path, np.arange(60000, 68000), _points(T=8000, M=2), fps=60.0, names=("a", "b"))
    with open(path, "rb") as fh:
        reader = c3d.Reader(fh)
        assert reader.header.last_frame - reader.header.first_frame + 1 == 8000
    _, _, frames, _ = read_c3d(path)
    assert frames[0] == 60001 and frames[-1] == 68000

"""Rig file formats: sample files written from each format's documentation, projected through the
format's own math and through our Camera; lossless round trips; detection; bad input."""

import json
import tempfile
import warnings
from pathlib import Path

import cv2
import h5py
import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.camera import Camera, CameraError, Rig, look_at_rotation
from calibration.formats import FORMATS, RigFormatError, detect_format, read_rig, write_rig
from calibration.formats._common import atomic_write

QCA = Path("/work/shared/real/pose2sim-multiperson/Calib.qca.txt")
POINTS_M = np.array([[0.3, -0.2, 1.1], [-0.5, 0.4, 0.2], [0.0, 0.0, 1.7], [0.8, 0.6, 0.9]])


def opencv_distort(x, y, d):
    """OpenCV's distortion written out from its documentation (independent of cv2)."""
    d = np.r_[d, np.zeros(14 - len(d))]
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d[:12]
    r2 = x * x + y * y
    radial = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r2**2
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r2**2
    return xd, yd


def pinhole_project(X, K, R, t, dist):
    Xc = X @ np.asarray(R).T + np.ravel(t)
    xd, yd = opencv_distort(Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2], np.ravel(dist))
    K = np.asarray(K)
    return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1)


def ring_cameras(n=3, dist=(-0.21, 0.05, 0.0012, -0.0008, 0.011), skew=0.0):
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        pos = np.array([3.1 * np.cos(a), 3.1 * np.sin(a), 2.3 + 0.1 * i])
        R = look_at_rotation(pos, [0.1, -0.05, 0.9])
        K = [[1510.5 + 10 * i, skew, 962.25], [0, 1508.75, 541.5 - i], [0, 0, 1]]
        cams.append(Camera.create(f"c{i}", K, dist, R, -R @ pos, 1920, 1080, {"note": f"cam {i}"}))
    return Rig(tuple(cams), up=(0.0, 0.0, 1.0))


def assert_same_rig(a: Rig, b: Rig, atol=1e-9):
    assert a.names == b.names
    for ca, cb in zip(a, b, strict=True):
        assert (ca.width, ca.height) == (cb.width, cb.height)
        np.testing.assert_allclose(cb.K, ca.K, rtol=1e-12, atol=atol)
        da, db = np.zeros(14), np.zeros(14)
        da[: ca.dist.size], db[: cb.dist.size] = ca.dist, cb.dist
        np.testing.assert_allclose(db, da, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(cb.R, ca.R, atol=1e-12)
        np.testing.assert_allclose(cb.t, ca.t, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(cb.project(POINTS_M), ca.project(POINTS_M), atol=1e-7)


# -- sample files from the documentation --------------------------------------------------------
PANOPTIC_CAM = {
    "name": "00_03",
    "type": "hd",
    "resolution": [1920, 1080],
    "panel": 0,
    "node": 3,
    "K": [[1633.5, 0.0, 944.8], [0.0, 1628.9, 556.6], [0.0, 0.0, 1.0]],
    "distCoef": [-0.2212, 0.1843, 0.00031, -0.00044, -0.0411],
    "R": cv2.Rodrigues(np.array([0.2, -2.4, 0.15]))[0].tolist(),
    "t": [[-12.6], [135.3], [282.4]],
}


def test_panoptic_projects_like_its_own_math(tmp_path):
    path = tmp_path / "calibration_171204_pose1.json"
    vga = dict(PANOPTIC_CAM, name="01_01", type="vga", resolution=[640, 480], panel=1, node=1)
    path.write_text(json.dumps({"calibDataSource": "171204_calib", "cameras": [PANOPTIC_CAM, vga]}))
    assert detect_format(path) == "panoptic"
    rig = read_rig(path, camera_types=("hd",))
    assert rig.names == ["00_03"] and rig.up == (0.0, -1.0, 0.0)
    cam = rig["00_03"]
    # Panoptic math: centimetres, world y down. A point in front of the camera:
    X_cm = (
        np.linalg.inv(cam.R)
        @ (np.array([[10.0, -5, 300], [-40, 20, 250]]) - np.ravel(PANOPTIC_CAM["t"])).T
    ).T
    ref = pinhole_project(
        X_cm, PANOPTIC_CAM["K"], PANOPTIC_CAM["R"], PANOPTIC_CAM["t"], PANOPTIC_CAM["distCoef"]
    )
    np.testing.assert_allclose(cam.project(X_cm / 100), ref, atol=1e-8)
    assert len(read_rig(path)) == 2  # all types by default
    assert cam.meta["panel"] == 0 and cam.meta["node"] == 3
    # `camera_types: hd` in YAML arrives as text: it was matched as a substring ("h" kept)
    h = dict(PANOPTIC_CAM, name="00_04", type="h")
    path.write_text(json.dumps({"cameras": [PANOPTIC_CAM, vga, h]}))
    assert read_rig(path, camera_types="hd").names == ["00_03"]


def h36m_project(P_mm, R, T, f, c, k, p):
    """H36M's projection as documented (3d-pose-baseline): X = R (P - T), H36M distortion."""
    X = (R @ (P_mm - T.ravel()).T).T
    x, y = X[:, 0] / X[:, 2], X[:, 1] / X[:, 2]
    r2 = x**2 + y**2
    radial = 1 + k[0] * r2 + k[1] * r2**2 + k[2] * r2**3
    tan = p[0] * y + p[1] * x
    xd = x * (radial + tan) + p[1] * r2
    yd = y * (radial + tan) + p[0] * r2
    return np.stack([f[0] * xd + c[0], f[1] * yd + c[1]], axis=1)


H36M_CAMS = [  # (id, rvec world->cam, centre mm, f, c, k, p)
    (
        "54138969",
        [1.84, -0.42, 0.37],
        [-1841.1, 4955.3, 1563.4],
        [1145.05, 1143.78],
        [512.54, 515.45],
        [-0.2071, 0.2479, -0.0031],
        [-0.00097, -0.00142],
    ),
    (
        "55011271",
        [1.67, 0.72, -0.51],
        [1761.3, 4448.0, 1588.1],
        [1149.68, 1147.59],
        [508.85, 508.06],
        [-0.1942, 0.2404, 0.0068],
        [-0.0016, -0.00277],
    ),
]


def write_h36m_sample(path, subjects=(1,)):
    with h5py.File(path, "w") as h5:
        for s in subjects:
            for i, (name, rvec, T, f, c, k, p) in enumerate(H36M_CAMS):
                g = h5.create_group(f"subject{s}/camera{i + 1}")
                g["R"] = cv2.Rodrigues(np.array(rvec))[0].T  # stored transposed
                g["T"] = np.array(T).reshape(3, 1)
                g["f"], g["c"] = np.array(f).reshape(2, 1), np.array(c).reshape(2, 1)
                g["k"], g["p"] = np.array(k).reshape(3, 1), np.array(p).reshape(2, 1)
                g["Name"] = np.array([ord(ch) for ch in name], dtype=np.uint8)


def _points_in_front(R, centre_m, n=6, seed=0):
    rng = np.random.default_rng(seed)
    pts_cam = np.c_[rng.uniform(-0.35, 0.35, (n, 2)), np.ones(n)] * rng.uniform(2, 6, (n, 1))
    return pts_cam @ R + centre_m  # R^T X_cam + C


def test_h36m_h5_projects_like_its_own_math(tmp_path):
    path = tmp_path / "cameras.h5"
    write_h36m_sample(path, subjects=(1, 5))
    assert detect_format(path) == "h36m"
    with pytest.raises(RigFormatError, match="subject"):
        read_rig(path)  # two subjects: must choose
    rig = read_rig(path, subject="S5")
    assert rig.names == ["54138969", "55011271"] and (rig[0].width, rig[0].height) == (1000, 1002)
    for cam, (_, rvec, T, f, c, k, p) in zip(rig, H36M_CAMS, strict=True):
        R = cv2.Rodrigues(np.array(rvec))[0]
        P_m = _points_in_front(R, np.array(T) / 1000)
        ref = h36m_project(P_m * 1000, R, np.array(T), f, c, k, p)
        np.testing.assert_allclose(cam.project(P_m), ref, atol=1e-8)  # exact conversion
        np.testing.assert_allclose(cam.center, np.array(T) / 1000, atol=1e-12)


def test_h36m_export_exact_for_h36m_cameras_and_refuses_or_fits_others(tmp_path):
    src = tmp_path / "cameras.h5"
    write_h36m_sample(src)
    rig = read_rig(src)
    out = tmp_path / "out.h5"
    write_rig(rig, out, "h36m", subject=1)
    with h5py.File(out) as a, h5py.File(src) as b:
        for ck in ("camera1", "camera2"):
            for ds in ("R", "T", "f", "c", "k", "p"):
                np.testing.assert_allclose(
                    a[f"subject1/{ck}/{ds}"][()],
                    b[f"subject1/{ck}/{ds}"][()],
                    rtol=1e-12,
                    atol=1e-12,
                )
    assert_same_rig(rig, read_rig(out, "h36m"))
    general = ring_cameras(1)
    with pytest.raises(RigFormatError, match="approximate_distortion"):
        write_rig(general, tmp_path / "g.h5", "h36m")
    assert not (tmp_path / "g.h5").exists()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        write_rig(general, tmp_path / "g.h5", "h36m", approximate_distortion=True)
    assert any("worst error" in str(w.message) for w in caught)
    fitted = read_rig(tmp_path / "g.h5", image_size=(1920, 1080))
    # Fitted distortion reproduces the OpenCV camera to well under a pixel inside the image.
    cam, fit = general[0], fitted[0]
    uv = np.stack(np.meshgrid(np.linspace(0, 1919, 9), np.linspace(0, 1079, 7)), -1).reshape(-1, 2)
    rays = cam.unproject(uv, 3.0)
    assert np.abs(fit.project(rays) - uv).max() < 0.5


def test_h36m_json_variant(tmp_path):
    name, rvec, T, f, c, k, p = H36M_CAMS[0]
    R = cv2.Rodrigues(np.array(rvec))[0]
    t_mm = -R @ np.array(T)
    K = [[f[0], 0, c[0]], [0, f[1], c[1]], [0, 0, 1]]
    data = {
        "intrinsics": {
            name: {"calibration_matrix": K, "distortion": [k[0], k[1], p[0], p[1], k[2]]}
        },
        "extrinsics": {"S1": {name: {"R": R.tolist(), "t": t_mm.reshape(3, 1).tolist()}}},
    }
    path = tmp_path / "camera-parameters.json"
    path.write_text(json.dumps(data))
    assert detect_format(path) == "h36m-json"
    P_m = _points_in_front(R, np.array(T) / 1000)
    # Default reading: OpenCV coefficients, as the variant's users feed them to OpenCV.
    cam = read_rig(path)[name]
    ref = pinhole_project(P_m * 1000, K, R, t_mm, [k[0], k[1], p[0], p[1], k[2]])
    np.testing.assert_allclose(cam.project(P_m), ref, atol=1e-8)
    # tangential='h36m': H36M's own model, converted exactly.
    cam_h = read_rig(path, subject=1, tangential="h36m")[name]
    np.testing.assert_allclose(
        cam_h.project(P_m), h36m_project(P_m * 1000, R, np.array(T), f, c, k, p), atol=1e-8
    )
    out = tmp_path / "rt.json"
    write_rig(read_rig(path), out, "h36m-json", subject="S1")
    assert_same_rig(read_rig(path), read_rig(out))
    write_rig(read_rig(path, tangential="h36m"), out, "h36m-json", tangential="h36m")
    assert_same_rig(read_rig(path, tangential="h36m"), read_rig(out, tangential="h36m"))


ANIPOSE_TOML = """\
[cam_0]
name = "A"
size = [ 1280, 720,]
matrix = [ [ 912.4, 0.0, 640.2,], [ 0.0, 911.8, 361.7,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.102, 0.087, 0.0011, -0.0006, -0.021,]
rotation = [ 0.12, -0.83, 0.05,]
translation = [ 412.0, -95.5, 2210.0,]

[cam_1]
name = "B"
size = [ 1280, 720,]
matrix = [ [ 905.1, 0.0, 633.0,], [ 0.0, 904.9, 355.2,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.098, 0.079, -0.0004, 0.0009, -0.015,]
rotation = [ 0.07, 0.91, -0.02,]
translation = [ -388.3, -101.2, 2190.5,]

[metadata]
adjusted = false
error = 0.41
"""


def _toml_reference(section_rvec, section_t, K, dist, X_units):
    uv, _ = cv2.projectPoints(
        X_units, np.array(section_rvec), np.array(section_t), np.array(K), np.array(dist)
    )
    return uv.reshape(-1, 2)


def test_anipose_toml_units_and_projection(tmp_path):
    path = tmp_path / "calibration.toml"
    path.write_text(ANIPOSE_TOML)
    assert detect_format(path) == "anipose"
    rig = read_rig(path)  # mm by default
    X_mm = np.array([[100.0, 200.0, 300.0], [-250.0, 50.0, 600.0]])
    ref = _toml_reference(
        [0.12, -0.83, 0.05],
        [412.0, -95.5, 2210.0],
        [[912.4, 0.0, 640.2], [0.0, 911.8, 361.7], [0.0, 0.0, 1.0]],
        [-0.102, 0.087, 0.0011, -0.0006, -0.021],
        X_mm,
    )
    np.testing.assert_allclose(rig["A"].project(X_mm / 1000), ref, atol=1e-8)
    assert rig.names == ["A", "B"] and rig.meta["metadata"]["error"] == 0.41
    rig_cm = read_rig(path, "anipose", units="cm")
    np.testing.assert_allclose(rig_cm["A"].t, rig["A"].t * 10)
    with pytest.raises(RigFormatError, match="units"):
        read_rig(path, "anipose", units="furlong")
    # a NaN rotation vector was reported as the rotation matrix 'R' made from it
    path.write_text(ANIPOSE_TOML.replace("rotation = [ 0.12,", "rotation = [ nan,", 1))
    with pytest.raises(RigFormatError, match=r"\[cam_0\] rotation is not finite"):
        read_rig(path)


def test_anipose_tables_sort_as_text_in_rig_order(tmp_path):
    """aniposelib orders a file's cameras by their table names as text: [cam_10] came before
    [cam_2], and 2D points given in rig order went to the wrong cameras (12 cameras)."""
    import tomllib

    rig = ring_cameras(12)
    write_rig(rig, tmp_path / "calibration.toml", "anipose")
    tables = tomllib.loads((tmp_path / "calibration.toml").read_text())
    keys = [k for k in tables if k != "metadata"]
    assert [tables[k]["name"] for k in sorted(keys)] == rig.names
    assert read_rig(tmp_path / "calibration.toml").names == rig.names
    write_rig(ring_cameras(3), tmp_path / "three.toml", "anipose")  # 10 or fewer: as before
    assert "[cam_2]" in (tmp_path / "three.toml").read_text()


POSE2SIM_TOML = """\
[cam_01]
name = "cam_01"
size = [ 1088.0, 1920.0]
matrix = [ [ 1681.2, 0.0, 533.0], [ 0.0, 1681.1, 948.1], [ 0.0, 0.0, 1.0]]
distortions = [ -0.046, 0.14, 0.0006, 0.0007]
rotation = [ 1.688, 1.048, -0.4196]
translation = [ 0.3211, 0.9563, 2.8907]
fisheye = false

[metadata]
adjusted = false
error = 0.0
"""


def test_pose2sim_toml_metres_and_projection(tmp_path):
    path = tmp_path / "Calib.toml"
    path.write_text(POSE2SIM_TOML)
    assert detect_format(path) == "pose2sim"
    cam = read_rig(path)["cam_01"]
    assert (cam.width, cam.height) == (1088, 1920) and cam.dist.size == 4
    X = np.array([[0.2, 0.1, 1.0], [-0.4, 0.3, 0.5]])
    ref = _toml_reference(
        [1.688, 1.048, -0.4196],
        [0.3211, 0.9563, 2.8907],
        [[1681.2, 0.0, 533.0], [0.0, 1681.1, 948.1], [0.0, 0.0, 1.0]],
        [-0.046, 0.14, 0.0006, 0.0007],
        X,
    )
    np.testing.assert_allclose(cam.project(X), ref, atol=1e-8)
    bad = tmp_path / "fish.toml"
    bad.write_text(POSE2SIM_TOML.replace("fisheye = false", "fisheye = true"))
    with pytest.raises(RigFormatError, match="fisheye"):
        read_rig(bad)


QCA_SAMPLE = """<?xml version='1.0' encoding='ASCII'?>
<calibration type="regular">
  <cameras>
    <camera active="1" avg-residual="0.4" model="Miqus Video" serial="12345" viewrotation="0">
      <fov_video bottom="1087" left="16" right="1935" top="8"/>
      <transform x="3000.0" y="-1200.0" z="2100.0"
        r11="{r11}" r12="{r12}" r13="{r13}" r21="{r21}" r22="{r22}" r23="{r23}"
        r31="{r31}" r32="{r32}" r33="{r33}"/>
      <intrinsic focalLengthU="89600.0" focalLengthV="89536.0"
        centerPointU="62464.0" centerPointV="35264.0"
        radialDistortion1="-0.05" radialDistortion2="0.12" radialDistortion3="0.01"
        tangentalDistortion1="0.0004" tangentalDistortion2="-0.0003" skew="0"/>
    </camera>
    <camera active="1" avg-residual="0.3" model="Miqus M3" serial="marker-only" viewrotation="0">
      <fov_video bottom="1087" left="0" right="1919" top="0"/>
      <transform x="0" y="0" z="3000"
        r11="1" r12="0" r13="0" r21="0" r22="1" r23="0" r31="0" r32="0" r33="1"/>
      <intrinsic focalLengthU="64000" focalLengthV="64000" centerPointU="61440" centerPointV="34560"
        radialDistortion1="0" radialDistortion2="0" radialDistortion3="0"
        tangentalDistortion1="0" tangentalDistortion2="0"/>
    </camera>
  </cameras>
</calibration>
"""


def test_qualisys_sample_projects_like_its_own_math(tmp_path):
    # Qualisys camera looks down its -z axis, +y up; rows of M are its axes in the world.
    pos = np.array([3000.0, -1200.0, 2100.0])
    forward = np.array([0.0, 0.0, 1100.0]) - pos
    forward /= np.linalg.norm(forward)
    x_axis = np.cross(forward, [0, 0, 1.0])
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(x_axis, forward)  # up in the image
    M = np.stack([x_axis, y_axis, -forward])
    fields = {f"r{i + 1}{j + 1}": repr(float(M[i, j])) for i in range(3) for j in range(3)}
    path = tmp_path / "session.qca.txt"
    path.write_text(QCA_SAMPLE.format(**fields))
    assert detect_format(path) == "qualisys"
    rig = read_rig(path)
    assert rig.names == ["12345"]  # the marker-only camera is skipped
    cam = rig[0]
    assert (cam.width, cam.height) == (1920, 1080)
    # Qualisys math: X_q = M (P - pos); normalised x = X_q.x / -X_q.z, y (down) = X_q.y / X_q.z.
    P_mm = np.array([[200.0, 300.0, 900.0], [-500.0, 100.0, 1500.0]])
    Xq = (P_mm - pos) @ M.T
    x, y = Xq[:, 0] / -Xq[:, 2], Xq[:, 1] / Xq[:, 2]
    xd, yd = opencv_distort(x, y, [-0.05, 0.12, 0.0004, -0.0003, 0.01])
    ref = np.stack([89600 / 64 * xd + 62464 / 64 - 16, 89536 / 64 * yd + 35264 / 64 - 8], axis=1)
    np.testing.assert_allclose(cam.project(P_mm / 1000), ref, atol=1e-8)
    assert len(read_rig(path, video_only=False)) == 2


def test_qualisys_real_lab_file_matches_pose2sim_conversion():
    """The real lab file, against Pose2Sim's published conversion of it (Calib_qualisys.toml in
    the Pose2Sim demo: same cameras, rotation as Rodrigues vector, translation in metres)."""
    rig = read_rig(QCA)
    assert rig.names == ["cam01", "cam02", "cam03", "cam04"]
    assert all((c.width, c.height) == (1088, 1920) for c in rig)
    published = {
        "cam01": (
            [1.6882754799999993, 1.0483220499999997, -0.41955852000000016],
            [0.3211048899999996, 0.9563320600000009, 2.8907130499999996],
        ),
        "cam04": (
            [1.4045571699999995, -1.3887412699999993, 0.42535743000000026],
            [0.5030217200000007, 0.04894934000000107, 4.406564460000002],
        ),
    }
    for name, (rvec, t) in published.items():
        np.testing.assert_allclose(rig[name].rvec, rvec, atol=1e-9)
        np.testing.assert_allclose(rig[name].t, t, atol=1e-9)
    np.testing.assert_allclose(rig["cam01"].K[0, 0], 107599.671875 / 64)


def test_qualisys_video_resolution_scales_the_intrinsics(tmp_path):
    """A camera that records video below its native lines says so; its field of view and
    intrinsics are given at the native resolution. Before, '540p' was ignored and the camera
    read as 1088x1920. A video scaled by s maps a native pixel u to (u + 0.5) s - 0.5 (pixel
    centres at whole coordinates; a 2x area downscale takes pixels 600 and 601 to 300): the
    principal point was scaled as c s before, 0.25 px off at 540p."""
    base = read_rig(QCA)
    text = QCA.read_text()
    for res, scale in (("1080p", 1.0), ("540p", 0.5), ("N/A", 1.0)):
        path = tmp_path / f"c{res.replace('/', '')}.qca.txt"
        path.write_text(text.replace("<camera ", f'<camera video_resolution="{res}" '))
        rig = read_rig(path)
        for a, b in zip(base, rig, strict=True):
            assert (b.width, b.height) == (round(a.width * scale), round(a.height * scale))
            np.testing.assert_allclose(np.diag(b.K)[:2], np.diag(a.K)[:2] * scale)
            np.testing.assert_allclose(b.K[:2, 2], (a.K[:2, 2] + 0.5) * scale - 0.5)
            np.testing.assert_allclose(
                b.project(POINTS_M), (a.project(POINTS_M) + 0.5) * scale - 0.5, atol=1e-9
            )
            np.testing.assert_array_equal(b.R, a.R)
    area = cv2.resize(np.pad(np.ones((2, 2), np.float32), ((1000, 918), (600, 486))), (544, 960),
                      interpolation=cv2.INTER_AREA)  # fmt: skip
    assert np.unravel_index(area.argmax(), area.shape) == (500, 300)  # (1000.5 + 0.5) / 2 - 0.5
    for res, match in (("HD", "video_resolution='HD'"), ("2160p", "more lines than")):
        path = tmp_path / "bad.qca.txt"
        path.write_text(text.replace("<camera ", f'<camera video_resolution="{res}" '))
        with pytest.raises(RigFormatError, match=match):
            read_rig(path)


def test_qualisys_video_plus_is_not_scaled_as_1080p(tmp_path):
    """A Miqus Video Plus calibrates and records at 1440p (window 1920 x 1440). Pose2Sim's
    reader, and ours before, scaled every camera by N / 1080: a 1440p Video Plus camera came out
    2560 x 1920 with its focal length 4/3 too long (pose2sim issues 200, 212)."""
    text = QCA.read_text().replace(
        'bottom="1919" left="0" right="1087" top="0"', 'bottom="1439" left="0" right="1919" top="0"'
    )
    native = tmp_path / "plus.qca.txt"
    native.write_text(text.replace('model="none"', 'model="Miqus Video Plus"'))
    for res, scale in (("1440p", 1.0), ("720p", 0.5)):
        path = tmp_path / f"plus_{res}.qca.txt"
        path.write_text(
            text.replace('model="none"', f'model="Miqus Video Plus" video_resolution="{res}"')
        )
        for a, b in zip(read_rig(native), read_rig(path), strict=True):
            assert (a.width, a.height) == (1920, 1440)
            assert (b.width, b.height) == (1920 * scale, 1440 * scale)
            np.testing.assert_allclose(b.K[0, 0], a.K[0, 0] * scale)


def test_qualisys_transform_with_nan_is_refused_by_name(tmp_path):
    """NaN passed the orthonormality check (nan > tol is False) and crashed in the SVD."""
    path = tmp_path / "nan.qca.txt"
    path.write_text(QCA.read_text().replace('r11="0.5536380477336265"', 'r11="nan"', 1))
    with pytest.raises(RigFormatError, match="camera 'cam01' <transform> r11='nan' is not finite"):
        read_rig(path)


def test_qualisys_bad_skew_and_all_cameras_skipped_are_named(tmp_path):
    path = tmp_path / "skew.qca.txt"
    path.write_text(QCA.read_text().replace('skew="0.000000"', 'skew="abc"', 1))
    with pytest.raises(RigFormatError, match="camera 'cam01' <intrinsic> skew='abc' is not a"):
        read_rig(path)  # a bare "could not convert string to float"
    path.write_text(QCA.read_text().replace('model="none"', 'model="Miqus M5"'))
    with pytest.raises(RigFormatError, match=r"skipped cam01 \(model 'Miqus M5'\).*video_only"):
        read_rig(path)  # "no cameras found"


def test_h36m_json_sizes_are_whole_pixels(tmp_path):
    out = tmp_path / "h.json"
    write_rig(ring_cameras(1), out, "h36m-json", subject="S1")
    for bad, shown in ((1000.9, "1000.9"), (True, "True"), ("abc", "'abc'")):
        data = json.loads(out.read_text())
        next(iter(data["intrinsics"].values()))["width"] = bad
        out.write_text(json.dumps(data))
        with pytest.raises(RigFormatError, match=f"width is {shown}, expected a whole number"):
            read_rig(out, "h36m-json")  # 1000.9 read 1000, true read 1
    data = json.loads(out.read_text())
    del next(iter(data["intrinsics"].values()))["height"]
    out.write_text(json.dumps(data))
    with pytest.raises(RigFormatError, match="give width without the other"):
        read_rig(out, "h36m-json")  # the edited width was dropped for the standard size


def test_colmap_model_written_by_pycolmap(tmp_path):
    rec = pycolmap.Reconstruction()
    params = [1500.0, 1495.0, 960.5, 540.5, -0.11, 0.04, 0.0007, -0.0005]
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(model="OPENCV", width=1920, height=1080, params=params, camera_id=1)
    )
    R = cv2.Rodrigues(np.array([0.1, 2.9, -0.2]))[0]
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), np.array([0.2, 0.4, 3.0]))
    rec.add_image_with_trivial_frame(pycolmap.Image(name="left.jpg", camera_id=1, image_id=7), pose)
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    rec.write(model)
    assert detect_format(tmp_path) == "colmap"
    cam = read_rig(tmp_path)["left.jpg"]
    X = _points_in_front(R, -R.T @ np.array([0.2, 0.4, 3.0]))
    img = rec.image(7)
    ref = np.array([img.project_point(x) for x in X]) - 0.5  # COLMAP pixel centres are at +0.5
    np.testing.assert_allclose(cam.project(X), ref, atol=1e-7)


# -- round trips through every exporter -----------------------------------------------------------
ROUND_TRIP = [
    ("rig", {}, {}),
    ("panoptic", {}, {}),
    ("anipose", {"units": "mm"}, {"units": "mm"}),
    ("anipose", {"units": "m"}, {"units": "m"}),
    ("pose2sim", {}, {}),
    ("colmap", {}, {}),
    ("h36m", {"subject": 9}, {"subject": 9}),
    ("h36m-json", {"subject": "S9"}, {"subject": "S9"}),
]


@pytest.mark.parametrize("fmt,wopts,ropts", ROUND_TRIP)
def test_round_trip_is_lossless(tmp_path, fmt, wopts, ropts):
    if fmt == "h36m":  # H36M holds its own lens model: a rig read from H36M, or radial only
        rig = ring_cameras(3, dist=(-0.2, 0.05, 0.0, 0.0, 0.01))
    elif fmt == "pose2sim":
        rig = ring_cameras(3, dist=(-0.2, 0.05, 0.001, -0.002))
    else:
        rig = ring_cameras(3)
    suffix = {
        "rig": ".json",
        "panoptic": ".json",
        "anipose": ".toml",
        "pose2sim": ".toml",
        "colmap": "",
        "h36m": ".h5",
        "h36m-json": ".json",
    }[fmt]
    path = tmp_path / f"rig_{fmt}{suffix}"
    write_rig(rig, path, fmt, **wopts)
    back = read_rig(path, fmt, **ropts)
    assert_same_rig(rig, back)
    if fmt == "rig":  # canonical file: bit-exact, meta kept
        for a, b in zip(rig, back, strict=True):
            assert (
                np.array_equal(a.K, b.K) and np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t)
            )
            assert b.meta == a.meta
        assert back.up == rig.up
    if fmt not in (
        "anipose",
        "pose2sim",
    ):  # TOML's two layouts look alike; auto-detection elsewhere
        assert detect_format(path) == fmt
    # Written again from the read rig: identical file (stable writer).
    if fmt not in ("colmap", "h36m"):
        path2 = tmp_path / f"again{suffix}"
        write_rig(back, path2, fmt, **wopts)
        assert_same_rig(back, read_rig(path2, fmt, **ropts))


def test_formats_listing_and_options():
    assert set(FORMATS) == {
        "rig",
        "panoptic",
        "h36m",
        "h36m-json",
        "anipose",
        "pose2sim",
        "qualisys",
        "colmap",
    }
    assert not FORMATS["qualisys"].can_write
    with pytest.raises(RigFormatError, match="read only"):
        write_rig(ring_cameras(1), "/tmp/never.qca.txt", "qualisys")
    with pytest.raises(RigFormatError, match="unknown rig format"):
        read_rig(QCA, "vicon")
    with pytest.raises(RigFormatError, match="no read options"):
        read_rig(QCA, "qualisys", subject=1)


# -- bad input ------------------------------------------------------------------------------
def test_invalid_rig_is_never_written(tmp_path):
    good = ring_cameras(2)
    c = good[1]
    broken = Camera(c.name, c.K, c.dist, c.R * 1.01, c.t, c.width, c.height)  # bypasses validation
    rig = Rig((good[0], broken))
    for fmt, suffix in (
        ("rig", ".json"),
        ("panoptic", ".json"),
        ("colmap", ""),
        ("anipose", ".toml"),
    ):
        path = tmp_path / f"out{suffix}"
        with pytest.raises(CameraError, match="c1.*orthonormal"):
            write_rig(rig, path, fmt)
        assert not path.exists()
    nan_cam = Camera("nan-cam", np.full((3, 3), np.nan), c.dist, c.R, c.t, c.width, c.height)
    with pytest.raises(CameraError, match="nan-cam.*NaN"):
        write_rig(Rig((nan_cam,)), tmp_path / "x.json")
    assert list(tmp_path.iterdir()) == []  # no temporary files left behind either


def test_failed_write_keeps_the_old_file(tmp_path):
    path = tmp_path / "rig.json"
    write_rig(ring_cameras(1), path)
    before = path.read_bytes()

    def crash(tmp):
        tmp.write_text("partial")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(path, crash)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [
        "rig.json"
    ]


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda d: d.update(version=2), "newer"),
        (lambda d: d.update(schema="other"), "schema"),
        (lambda d: d["cameras"][0].pop("K"), "missing key 'K'.*camera 'c0'"),
        (lambda d: d["cameras"][0].update(R=[[1, 0], [0, 1]]), "c0.*R has shape"),
        (lambda d: d["cameras"][0].update(t=[0, float("nan"), 0]), "c0.*NaN"),
        (lambda d: d["cameras"][0].update(focal=1.0), "unknown keys"),
        # values of the wrong type escaped as bare ValueError / TypeError naming nothing
        (lambda d: d["cameras"][0].update(width="abc"), "camera 'c0' width is 'abc'"),
        (lambda d: d["cameras"][0].update(width=1000.9), "camera 'c0' width is 1000.9"),
        (lambda d: d["cameras"][0].update(height=True), "camera 'c0' height is True"),
        (lambda d: d["cameras"][0].update(dist={"k1": 0.1}), "camera 'c0'.*dict"),
        (lambda d: d.update(up=["z", 0, 1]), "up is not numeric"),
        (lambda d: d.update(up=[0, 1]), r"up has shape \(2,\)"),
        # taken before: a null or empty name, reshaped matrices, a nested dist, version true
        (lambda d: d["cameras"][0].update(name=None), r"cameras\[0\] name must be"),
        (lambda d: d["cameras"][0].update(name=""), r"cameras\[0\] name must be"),
        (lambda d: d["cameras"][0].update(K=sum(d["cameras"][0]["K"], [])), r"K has shape \(9,\)"),
        (lambda d: d["cameras"][0].update(dist=[[0.1, 0], [0, 0]]), "dist has shape"),
        (lambda d: d.update(version=True), "version must be a positive integer"),
        (lambda d: d["cameras"][0].update(dist="abc"), "camera 'c0' dist is not numeric"),
    ],
)
def test_bad_rig_json_is_reported_with_file_and_key(tmp_path, mutate, match):
    path = tmp_path / "rig.json"
    write_rig(ring_cameras(1), path)
    data = json.loads(path.read_text())
    mutate(data)
    path.write_text(json.dumps(data))
    with pytest.raises(RigFormatError, match=match) as info:
        read_rig(path, "rig")
    assert str(path) in str(info.value)


def test_rig_json_reads_rotations_as_written_and_checks_them_to_1e_6(tmp_path):
    """rig.json stores full precision: a rotation within Camera's 1e-6 is read bit-exact (not
    re-orthonormalised, which changed R by 2e-7), one beyond it is refused as the doc says
    (another tool's rounded file is repaired up to 1e-3; our own is not)."""
    path = tmp_path / "rig.json"
    write_rig(ring_cameras(1), path)
    data = json.loads(path.read_text())
    R = np.array(data["cameras"][0]["R"])
    R[0, 0] += 4e-7  # |R R^T - I| about 8e-7: a valid camera
    data["cameras"][0]["R"] = R.tolist()
    path.write_text(json.dumps(data))
    cam = read_rig(path, "rig").cameras[0]
    assert np.array_equal(cam.R, R) and "R_orthonormalised_from_error" not in cam.meta
    R[0, 0] += 1e-4
    data["cameras"][0]["R"] = R.tolist()
    path.write_text(json.dumps(data))
    with pytest.raises(RigFormatError, match="c0.*not orthonormal.*tolerance 1e-06"):
        read_rig(path, "rig")


def test_undetectable_file(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("hello")
    with pytest.raises(RigFormatError, match="cannot tell"):
        read_rig(path)


def test_rotations_printed_with_few_digits_are_accepted_but_bad_ones_refused(tmp_path):
    cam = dict(PANOPTIC_CAM, R=np.round(np.array(PANOPTIC_CAM["R"]), 5).tolist())
    path = tmp_path / "calibration_x.json"
    path.write_text(json.dumps({"cameras": [cam]}))
    c = read_rig(path)[0]
    assert 1e-7 < c.meta["R_orthonormalised_from_error"] < 1e-4
    np.testing.assert_allclose(c.R, PANOPTIC_CAM["R"], atol=1e-5)
    cam_bad = dict(PANOPTIC_CAM, R=(np.array(PANOPTIC_CAM["R"]) * 1.01).tolist())
    path.write_text(json.dumps({"cameras": [cam_bad]}))
    with pytest.raises(RigFormatError, match="00_03.*orthonormal"):
        read_rig(path)


def test_a_key_given_twice_is_refused(tmp_path):
    """'"width": 1920, "width": 640' read 640."""
    path = tmp_path / "rig.json"
    write_rig(ring_cameras(1), path)
    text = path.read_text().replace('"width": ', '"width": 1920, "width": ', 1)
    path.write_text(text)
    with pytest.raises(RigFormatError, match=r"keys given twice in one object: \['width'\]"):
        read_rig(path, "rig")


def test_non_finite_meta_is_written_as_strict_json(tmp_path):
    """A camera without residuals has rms_px NaN: written as a bare NaN, which jq, JavaScript
    and serde refuse."""
    rig = ring_cameras(2)
    cams = [replace_meta(c, {"rms_px": float("nan"), 7: (1, 2)}) for c in rig]
    path = tmp_path / "rig.json"
    write_rig(Rig(cams, up=rig.up), path)
    strict = json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"bare {c}"))
    assert strict["cameras"][0]["meta"] == {"rms_px": None, "7": [1, 2]}


def replace_meta(cam: Camera, meta: dict) -> Camera:
    return Camera.create(cam.name, cam.K, cam.dist, cam.R, cam.t, cam.width, cam.height, meta)


def test_colmap_model_in_the_other_encoding_is_replaced_and_units_checked(tmp_path):
    """An older text model beside the new binary one kept the old poses for any tool reading
    the text files; a unit of 0 wrote NaN translations, -1 mirrored the world on reading."""
    old = ring_cameras(2)
    rec = pycolmap.Reconstruction()
    write_rig(old, tmp_path, "colmap")
    rec.read(str(tmp_path))
    rec.write_text(str(tmp_path))
    for f in tmp_path.glob("*.bin"):
        f.unlink()
    assert (tmp_path / "images.txt").is_file()
    write_rig(ring_cameras(3), tmp_path, "colmap")
    assert not list(tmp_path.glob("*.txt")) and len(read_rig(tmp_path, "colmap")) == 3
    for unit in (0, -1.0, float("nan")):
        with pytest.raises(RigFormatError, match="metres_per_unit must be a finite number > 0"):
            write_rig(old, tmp_path / "x", "colmap", metres_per_unit=unit)
        with pytest.raises(RigFormatError, match="metres_per_unit must be a finite number > 0"):
            read_rig(tmp_path, "colmap", metres_per_unit=unit)


def test_a_guessed_toml_format_and_cameras_a_few_mm_apart_are_said(tmp_path, caplog):
    """A metres file in the anipose layout was read as millimetres (a camera 4.2 m away, 4.2 mm
    away) without a word."""
    path = tmp_path / "calib.toml"
    write_rig(ring_cameras(3), path, "anipose", units="m")
    with caplog.at_level("WARNING", logger="calibration"):
        read_rig(path)
    text = " ".join(caplog.messages)
    assert "read as 'anipose'" in text and "translations in mm" in text
    assert "stand within" in text  # metres read as mm: the ring is a few mm wide
    caplog.clear()
    with caplog.at_level("WARNING", logger="calibration"):
        read_rig(path, "anipose", units="m")
    assert not caplog.messages


def test_skew_is_not_written_where_readers_ignore_it(tmp_path):
    rig = ring_cameras(2)
    K = rig.cameras[0].K.copy()
    K[0, 1] = 2.0
    c = rig.cameras[0]
    skewed = Rig([Camera.create(c.name, K, c.dist, c.R, c.t, c.width, c.height),
                  rig.cameras[1]], up=rig.up)  # fmt: skip
    for fmt, suffix in (("pose2sim", "toml"), ("anipose", "toml"), ("h36m-json", "json")):
        with pytest.raises(RigFormatError, match="skew"):
            write_rig(skewed, tmp_path / f"x.{suffix}", fmt)


def test_fields_of_the_wrong_kind_are_refused_by_name(tmp_path):
    """Found by a review, each read without complaint before: a list as a rig's meta (the
    writers failed later with a bare AttributeError), true as a focal length (read 1.0), a
    null distortion (one NaN term), a null or table camera name (became 'None'), the text
    "false" as fisheye (refused as a fisheye)."""
    rig = ring_cameras(2)
    path = tmp_path / "rig.json"
    write_rig(rig, path, "rig")
    data = json.loads(path.read_text())
    for edit, message in (
        (lambda d: d.update(meta=[1]), "'meta' must be an object, got a list"),
        (lambda d: d["cameras"][0].update(meta=[1]), r"'meta' in camera .* object"),
    ):
        bad = json.loads(json.dumps(data))
        edit(bad)
        path.write_text(json.dumps(bad))
        with pytest.raises(RigFormatError, match=message):
            read_rig(path, "rig")
    toml = tmp_path / "calib.toml"
    write_rig(rig, toml, "pose2sim")
    text = toml.read_text()
    for old, new, message in (
        ("matrix = [[1510.5,", "matrix = [[true,", "true/false where numbers"),
        ("fisheye = false", 'fisheye = "false"', "fisheye is 'false'"),
    ):
        assert old in text
        toml.write_text(text.replace(old, new, 1))
        with pytest.raises(RigFormatError, match=message):
            read_rig(toml, "pose2sim")
    pan = tmp_path / "calibration.json"
    write_rig(rig, pan, "panoptic")
    data = json.loads(pan.read_text())
    for key, value, message in (
        ("name", None, "'name' in cameras.0. must be non-empty text, got null"),
        ("distCoef", None, "distCoef is null"),
    ):
        bad = json.loads(json.dumps(data))
        bad["cameras"][0][key] = value
        pan.write_text(json.dumps(bad))
        with pytest.raises(RigFormatError, match=message):
            read_rig(pan, "panoptic")


def test_meta_that_json_cannot_hold_is_written_or_named(tmp_path):
    """A Path in a rig's meta and numpy integers in Panoptic's panel and node failed in
    json.dumps with a TypeError naming nothing; paths are written as text, numpy values as
    numbers, and anything else is refused by name."""
    rig = ring_cameras(2)
    cams = [Camera.create(c.name, c.K, c.dist, c.R, c.t, c.width, c.height,
                          meta={"panel": np.int64(3), "node": np.int64(i)})
            for i, c in enumerate(rig.cameras)]  # fmt: skip
    with_meta = Rig(cams, up=rig.up, meta={"source": Path("/data/calib.qca.txt")})
    write_rig(with_meta, tmp_path / "rig.json", "rig")
    assert read_rig(tmp_path / "rig.json", "rig").meta["source"] == "/data/calib.qca.txt"
    write_rig(with_meta, tmp_path / "calibration.json", "panoptic")
    assert json.loads((tmp_path / "calibration.json").read_text())["cameras"][1]["node"] == 1
    odd = Rig(rig.cameras, up=rig.up, meta={"when": object()})
    with pytest.raises(RigFormatError, match="meta value .* cannot be written as JSON"):
        write_rig(odd, tmp_path / "odd.json", "rig")


def test_a_toml_fallback_key_does_not_take_another_cameras_name(tmp_path):
    """["a b", "cam_01"]: the first camera's fallback table [cam_01] was the second's name,
    and the writer refused a valid rig."""
    rig = ring_cameras(2)
    cams = [Camera.create(n, c.K, c.dist, c.R, c.t, c.width, c.height)
            for n, c in zip(("a b", "cam_01"), rig.cameras, strict=True)]  # fmt: skip
    path = tmp_path / "calib.toml"
    write_rig(Rig(cams, up=rig.up), path, "pose2sim")
    assert [c.name for c in read_rig(path, "pose2sim").cameras] == ["a b", "cam_01"]


def test_colmap_write_keeps_other_files_in_the_folder(tmp_path):
    (tmp_path / "images").mkdir()
    (tmp_path / "images" / "a.jpg").write_bytes(b"jpeg")
    write_rig(ring_cameras(2), tmp_path, "colmap")
    write_rig(ring_cameras(3), tmp_path, "colmap")  # overwrite the model
    assert (tmp_path / "images" / "a.jpg").read_bytes() == b"jpeg"
    assert len(read_rig(tmp_path, "colmap")) == 3
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".colmap-")]


@pytest.mark.parametrize("fmt", ["panoptic", "pose2sim", "anipose", "h36m-json"])
def test_writing_a_rig_of_another_up_warns_and_keeps_the_world(tmp_path, fmt, caplog):
    """The files carry no up: the world is written unchanged (3D data in it stay valid) and a
    warning says which up readers will assume (found silently wrong before: a z-up rig read
    back from Panoptic as y down)."""
    up = FORMATS[fmt].world_up
    other = (0.0, -1.0, 0.0) if up[2] == 1.0 else (0.0, 0.0, 1.0)
    rig = Rig(ring_cameras(3).cameras, up=other)
    name = "calibration_x.json" if fmt == "panoptic" else "rig.json" if "json" in fmt else "r.toml"
    opts = {"subject": "S9"} if fmt == "h36m-json" else {}
    write_rig(rig, tmp_path / name, fmt, **opts)
    assert "readers will assume" in caplog.text and str(up) in caplog.text
    back = read_rig(tmp_path / name, fmt, **opts)
    assert_same_rig(rig, back)
    caplog.clear()
    write_rig(Rig(rig.cameras, up=up), tmp_path / name, fmt, **opts)
    assert "readers will assume" not in caplog.text
    # the synthetic scenes' writer, whose files document their world (docs/formats/
    # synth_scene.md), does not warn: it did once per pretraining world, about scratch files
    from synth.scene import _default_rig_writer

    _default_rig_writer()(rig, tmp_path / name, fmt, **opts)
    assert "readers will assume" not in caplog.text
    assert_same_rig(rig, read_rig(tmp_path / name, fmt, **opts))


def test_h36m_keeps_a_camera_name_that_is_not_ascii(tmp_path):
    rig = ring_cameras(2, dist=(-0.2, 0.05, 0.0, 0.0, 0.01))
    rig = Rig(
        tuple(c.replace(name=n) for c, n in zip(rig.cameras, ["caméra 1", "カメラ2"], strict=True)),
        up=rig.up,
    )
    write_rig(rig, tmp_path / "cameras.h5", "h36m", subject=9)
    back = read_rig(tmp_path / "cameras.h5", "h36m", subject=9)
    assert [c.name for c in back.cameras] == ["caméra 1", "カメラ2"]


def test_five_term_formats_refuse_rational_or_prism_terms(tmp_path):
    """Panoptic's distCoef is k1, k2, p1, p2, k3 (the panoptic toolbox reads Kd[0..4]); an 8-term
    lens was written whole, which our reader round-tripped but the toolbox projects hundreds of
    pixels elsewhere. Refused as H36M JSON already did; 5 terms still write."""
    rig8 = ring_cameras(2, dist=(0.3, 0.05, 0.001, 0.0005, 0.001, 0.4, 0.06, 0.002))
    for fmt in ("panoptic", "h36m-json"):
        with pytest.raises(RigFormatError, match="needs more than the 5 OpenCV terms"):
            write_rig(rig8, tmp_path / f"{fmt}.json", fmt)
        assert not (tmp_path / f"{fmt}.json").exists()
        write_rig(ring_cameras(2), tmp_path / f"{fmt}5.json", fmt)
        assert_same_rig(ring_cameras(2), read_rig(tmp_path / f"{fmt}5.json", fmt))


def _drop_key(path: Path, fmt: str, key: str) -> None:
    """Remove `key` from every camera of a written file (JSON or TOML text)."""
    if fmt == "panoptic":
        data = json.loads(path.read_text())
        for cam in data["cameras"]:
            cam.pop(key)
        path.write_text(json.dumps(data))
    elif fmt == "h36m-json":
        data = json.loads(path.read_text())
        for cam in data["intrinsics"].values():
            cam.pop(key)
        path.write_text(json.dumps(data))
    else:
        path.write_text(
            "\n".join(x for x in path.read_text().splitlines() if not x.startswith(key))
        )


@pytest.mark.parametrize(
    "fmt,suffix,key",
    [
        ("panoptic", ".json", "distCoef"),
        ("h36m-json", ".json", "distortion"),
        ("anipose", ".toml", "distortions"),
        ("pose2sim", ".toml", "distortions"),
    ],
)
def test_a_file_without_its_distortion_key_is_refused(tmp_path, fmt, suffix, key):
    """A missing distortion key was read as a lens without distortion (tens of pixels at the
    corners for an H36M lens); the formats' own readers fail on it. An empty list still reads."""
    path = tmp_path / f"rig{suffix}"
    write_rig(ring_cameras(2), path, fmt)
    _drop_key(path, fmt, key)
    with pytest.raises(RigFormatError, match=f"missing key '{key}'") as info:
        read_rig(path, fmt)
    assert str(path) in str(info.value)


def test_panoptic_resolution_must_be_whole_pixels(tmp_path):
    path = tmp_path / "p.json"
    write_rig(ring_cameras(1), path, "panoptic")
    data = json.loads(path.read_text())
    data["cameras"][0]["resolution"] = [1919.6, 1080]
    path.write_text(json.dumps(data))
    with pytest.raises(RigFormatError, match=r"resolution\[0\] is 1919.6"):
        read_rig(path, "panoptic")
    data["cameras"][0]["resolution"] = [1920.0, 1080]  # a whole number written as a float
    path.write_text(json.dumps(data))
    assert read_rig(path, "panoptic")[0].width == 1920


@pytest.mark.parametrize("fmt", ["anipose", "pose2sim"])
def test_toml_tables_that_are_not_cameras_are_skipped(tmp_path, fmt):
    """Caliscope-style files carry [charuco] and [capture_volume] tables, which Pose2Sim's
    readers skip; ours read them as cameras and refused the file ('missing key size')."""
    path = tmp_path / "cal.toml"
    write_rig(ring_cameras(2), path, fmt)
    path.write_text(
        path.read_text()
        + "\n[charuco]\ncolumns = 4\nrows = 5\nsquare_size_overide_cm = 5.4\n"
        + "\n[capture_volume]\nstage = 1\n"
    )
    rig = read_rig(path, fmt)
    assert list(rig.names) == ["c0", "c1"]


@given(name=st.text(min_size=1, max_size=12).filter(lambda n: n.strip() == n and n))
@settings(max_examples=60, deadline=None)
def test_toml_camera_names_round_trip_whatever_their_characters(name):
    """Only backslash, quote and newline were escaped: a name with another control character
    (a carriage return, \\x01) made a file that no TOML reader accepts."""
    cam = ring_cameras(1)[0]
    rig = Rig((Camera.create(name, cam.K, cam.dist, cam.R, cam.t, cam.width, cam.height),))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "cal.toml"
        write_rig(rig, path, "anipose")
        assert list(read_rig(path, "anipose").names) == [name]


def test_toml_metadata_dates_survive_the_rig_json_written_after_import(tmp_path):
    """TOML has native dates: a [metadata] date was kept in Rig.meta and the rig.json written
    after every import crashed with a bare "datetime is not JSON serializable"."""
    path = tmp_path / "calib.toml"
    write_rig(ring_cameras(2), path, "anipose")
    text = path.read_text()
    assert "[metadata]\n" in text
    path.write_text(text.replace("[metadata]\n", "[metadata]\ncalibrated = 2024-05-02T10:31:00\n"))
    rig = read_rig(path, "anipose")
    out = tmp_path / "rig.json"
    write_rig(rig, out, "rig")
    assert read_rig(out).meta["metadata"]["calibrated"] == "2024-05-02T10:31:00"


@pytest.mark.parametrize(
    ("dataset", "value", "shown"),
    [
        ("R", np.eye(2), r"camera1 dataset R has shape \(2, 2\), expected \(3, 3\)"),
        ("f", np.array([1145.0]), r"camera1 dataset f has shape \(1,\), expected \(2,\)"),
        ("T", np.zeros(2), r"camera1 dataset T has shape \(2,\), expected \(3,\)"),
        ("k", np.zeros(2), r"camera1 dataset k has shape \(2,\), expected \(3,\)"),
    ],
)
def test_h36m_h5_malformed_datasets_are_named(tmp_path, dataset, value, shown):
    """Bare reshape, index and matmul errors (and a too-long f silently cut to two values)."""
    path = tmp_path / "cameras.h5"
    write_h36m_sample(path)
    with h5py.File(path, "r+") as h5:
        del h5[f"subject1/camera1/{dataset}"]
        h5[f"subject1/camera1/{dataset}"] = value
    with pytest.raises(RigFormatError, match=f"{path}: subject1/{shown}"):
        read_rig(path, "h36m")


def test_h36m_h5_camera_groups_must_be_numbered(tmp_path):
    path = tmp_path / "cameras.h5"
    write_h36m_sample(path)
    with h5py.File(path, "r+") as h5:
        h5.move("subject1/camera2", "subject1/camera_2")
    with pytest.raises(RigFormatError, match=r"camera groups \['camera_2'\]; expected camera<N>"):
        read_rig(path, "h36m")  # a bare "invalid literal for int()"


def test_h36m_caller_image_size_comes_before_the_known_sizes(tmp_path):
    """A caller's image_size for H36M's own camera ids was silently replaced by H36M's sizes."""
    path = tmp_path / "cameras.h5"
    write_h36m_sample(path)
    assert (read_rig(path)[0].width, read_rig(path)[0].height) == (1000, 1002)
    rig = read_rig(path, image_size=(500, 501))
    assert all((c.width, c.height) == (500, 501) for c in rig)
    written = tmp_path / "ours.h5"
    write_rig(rig, written, "h36m")  # stores the sizes: they come first
    assert read_rig(written, image_size=(10, 10))[0].width == 500


@pytest.mark.parametrize("size", [1000, (1000,), (1002, 1000, 3)])
def test_h36m_image_size_that_is_not_width_and_height_is_refused(tmp_path, size):
    """image_size: 1000 was a bare TypeError, (1000,) an IndexError, and an image's shape
    (height, width, 3) was read as width 1002, height 1000."""
    path = tmp_path / "cameras.h5"
    write_h36m_sample(path)
    with pytest.raises(RigFormatError, match=r"image_size is .*expected two numbers \(width"):
        read_rig(path, image_size=size)


@pytest.mark.parametrize("value", ["nan", "inf", "1e400"])
def test_qualisys_non_finite_field_of_view_is_refused_by_name(tmp_path, value):
    path = tmp_path / "bad.qca.txt"
    text = QCA.read_text()
    start = text.index("<fov_video")
    left = text.index('left="', start)
    end = text.index('"', left + 6)
    path.write_text(text[: left + 6] + value + text[end:])
    with pytest.raises(RigFormatError, match=f"camera 'cam01' <fov_video> left='{value}' is not"):
        read_rig(path)  # "cannot convert float NaN to integer" / OverflowError


def test_json_containers_of_the_wrong_kind_are_named(tmp_path):
    path = tmp_path / "calibration_x.json"
    write_rig(ring_cameras(1), path, "panoptic")
    for cameras, shown in ((None, "null"), ({"name": "a"}, "an object"), (5, "a number")):
        data = json.loads(path.read_text())
        data["cameras"] = cameras
        path.write_text(json.dumps(data))
        with pytest.raises(RigFormatError, match=f"'cameras' must be a list, got {shown}"):
            read_rig(path, "panoptic")
    path = tmp_path / "camera-parameters.json"
    write_rig(ring_cameras(1), path, "h36m-json", subject="S1")
    good = json.loads(path.read_text())
    for broken, shown in (
        ({**good, "extrinsics": []}, "'extrinsics' must be an object, got a list"),
        ({**good, "extrinsics": {"S1": []}}, "'S1' in extrinsics must be an object, got a list"),
    ):
        path.write_text(json.dumps(broken))
        with pytest.raises(RigFormatError, match=shown):
            read_rig(path, "h36m-json")


def test_h36m_json_writer_takes_the_option_its_refusal_suggests(tmp_path):
    general = ring_cameras(1)
    path = tmp_path / "camera-parameters.json"
    with pytest.raises(RigFormatError, match="approximate_distortion=True"):
        write_rig(general, path, "h36m-json", tangential="h36m")
    with pytest.warns(UserWarning, match="worst error"):
        write_rig(general, path, "h36m-json", tangential="h36m", approximate_distortion=True)
    back = read_rig(path, "h36m-json", tangential="h36m")
    uv = np.stack(np.meshgrid(np.linspace(0, 1919, 9), np.linspace(0, 1079, 7)), -1).reshape(-1, 2)
    assert np.abs(back[0].project(general[0].unproject(uv, 3.0)) - uv).max() < 0.5


def test_a_declared_format_the_file_is_not_says_what_it_looks_like(tmp_path):
    """`format: pose2sim` on a Panoptic file said only "not valid TOML" (a user review)."""
    path = tmp_path / "calibration.json"
    write_rig(ring_cameras(2), path, "panoptic")
    with pytest.raises(RigFormatError, match="the file looks like 'panoptic': give that format"):
        read_rig(path, "pose2sim")
    assert len(read_rig(path)) == 2  # detected


def _qca_with(tmp_path, *edits) -> Path:
    text = QCA.read_text()
    for old, new in edits:
        assert old in text
        text = text.replace(old, new, 1)
    path = tmp_path / "edited.qca.txt"
    path.write_text(text)
    return path


def test_qualisys_cameras_passed_over_are_said_and_the_scene_names_them(tmp_path, caplog):
    """A camera the reader's options pass over was said only when none was left; the scene
    then told the user to rename their files, though the cameras were in the file."""
    from calibration.scene import CalibrationFile, calibrate_scene

    path = _qca_with(
        tmp_path,
        ('model="none" point-count="999999999" serial="cam04"',
         'model="Miqus Hybrid" point-count="999999999" serial="cam04"'),
        ('active="1" avg-residual="0.444749"', 'active="0" avg-residual="0.444749"'),
    )  # fmt: skip
    with caplog.at_level("WARNING", logger="calibration"):
        rig = read_rig(path)
    assert rig.names == ["cam01", "cam03"]
    assert rig.meta["skipped"] == ["cam02 (inactive)", "cam04 (model 'Miqus Hybrid')"]
    assert "cam02 (inactive) passed over" in caplog.text and "include_inactive" in caplog.text
    videos = {n: QCA.parent / f"{n}.mp4" for n in ("cam01", "cam02", "cam03", "cam04")}
    with pytest.raises(ValueError, match=r"cam02 \(inactive\), cam04 .*passed over.*options"):
        calibrate_scene(videos, tmp_path / "rig.json", tmp_path / "rep", file=CalibrationFile(path))
    kept = read_rig(path, include_inactive=True, video_only=False)
    assert kept.names == ["cam01", "cam02", "cam03", "cam04"] and "skipped" not in kept.meta


def test_qualisys_read_options_are_checked_and_a_fraction_is_read():
    """YAML keeps `distortion_scale: 1/64` as text (it failed in a numpy ufunc, naming
    nothing); the text 'false' for a flag was read as true; a negative scale was taken."""
    as_given = read_rig(QCA)
    scaled = read_rig(QCA, "qualisys", distortion_scale="1/64")
    np.testing.assert_allclose(scaled[0].dist, as_given[0].dist / 64)
    for bad in ("abc", -1.0, 0, float("nan"), "1/0", True):
        with pytest.raises(RigFormatError, match="distortion_scale must be a number > 0"):
            read_rig(QCA, "qualisys", distortion_scale=bad)
    for flag in ("video_only", "include_inactive"):
        with pytest.raises(RigFormatError, match=f"{flag} must be true or false, got 'false'"):
            read_rig(QCA, "qualisys", **{flag: "false"})


def test_a_toml_camera_without_its_geometry_is_refused(tmp_path):
    """A camera table whose geometry keys were misspelled, or a file cut after a camera's name,
    loaded with one camera fewer and no word."""
    path = tmp_path / "calib.toml"
    write_rig(ring_cameras(3), path, "pose2sim")
    text = path.read_text()
    typo = tmp_path / "typo.toml"
    typo.write_text(text.replace("rotation =", "rvec =", 3).replace("rvec =", "rotation =", 2))
    with pytest.raises(RigFormatError, match=r"lacks \['rotation'\].*typo'd key"):
        read_rig(typo, "pose2sim")
    cut = tmp_path / "cut.toml"
    cut.write_text(text[: text.index("[metadata]")] + '[c3]\nname = "c3"\n')
    with pytest.raises(RigFormatError, match="looks like a camera"):
        read_rig(cut, "pose2sim")
    assert len(read_rig(path, "pose2sim")) == 3  # the whole file still reads


@pytest.mark.parametrize("fmt", [None, "anipose", "pose2sim"])
def test_toml_distortions_that_are_no_list_are_refused_by_name(tmp_path, fmt):
    """`distortions = 0` raised a bare TypeError from the format sniffer (it took the length
    of an int), hiding the reader's own message."""
    path = tmp_path / "calib.toml"
    write_rig(ring_cameras(2), path, "pose2sim")
    text = path.read_text()
    start = text.index("distortions =")
    end = text.index("\n", start)
    # without `fisheye` (aniposelib's layout) the sniffer reads the distortions' length
    path.write_text(
        (text[:start] + "distortions = 0" + text[end:]).replace("fisheye = false\n", "")
    )
    with pytest.raises(RigFormatError, match="distortion"):
        read_rig(path, fmt)


def test_panoptic_types_that_match_nothing_are_listed_whatever_their_kind(tmp_path):
    """Cameras without a `type` beside typed ones broke the message's sort (None against str)."""
    data = {
        "cameras": [
            {"name": "a", "type": "hd"},
            {"name": "b"},
        ]
    }
    path = tmp_path / "calibration_x.json"
    path.write_text(json.dumps(data))
    with pytest.raises(
        RigFormatError, match=r"no cameras of types .*types present: \['None', 'hd'\]"
    ):
        read_rig(path, "panoptic", camera_types=("vga",))


@pytest.mark.parametrize(
    "fmt, options, match",
    [
        ("panoptic", {"camera_types": 5}, "camera_types is 5, expected a camera type"),
        ("colmap", {"up": "z"}, "option up is 'z', expected the world's up axis"),
        ("colmap", {"up": 1.0}, "option up is 1.0, expected the world's up axis"),
    ],
)
def test_read_options_of_the_wrong_kind_are_refused_by_name(tmp_path, fmt, options, match):
    """Options from pipeline.yaml of the wrong kind were bare TypeErrors and ValueErrors."""
    rig = ring_cameras(3)
    path = tmp_path / ("model" if fmt == "colmap" else "calibration.json")
    write_rig(rig, path, fmt, warn_up=False)
    with pytest.raises(RigFormatError, match=match):
        read_rig(path, fmt, **options)


@pytest.mark.parametrize(
    "fmt,suffix",
    [("rig", ".json"), ("panoptic", ".json"), ("h36m-json", ".json"), ("pose2sim", ".toml"),
     ("anipose", ".toml")],
)  # fmt: skip
@pytest.mark.parametrize("given", [True, False])
def test_a_file_not_in_utf8_is_refused_with_its_name(tmp_path, fmt, suffix, given):
    """A camera name saved as Latin-1 by an editor ("caméra" as byte 0xE9) was a bare
    UnicodeDecodeError naming neither file nor camera."""
    path = tmp_path / f"rig{suffix}"
    write_rig(ring_cameras(2), path, fmt, warn_up=False)
    path.write_bytes(path.read_bytes().replace(b'"c1"', '"caméra1"'.encode("latin-1")))
    with pytest.raises(RigFormatError, match=r"rig\.(json|toml).*UTF-8"):
        read_rig(path, fmt if given else None)


@pytest.mark.parametrize(
    "fmt,suffix",
    [("rig", ".json"), ("panoptic", ".json"), ("h36m-json", ".json"), ("pose2sim", ".toml"),
     ("anipose", ".toml")],
)  # fmt: skip
def test_a_file_saved_with_a_utf8_bom_is_read(tmp_path, fmt, suffix):
    """Windows editors (Notepad before 2019, PowerShell 5's Out-File) save UTF-8 with a byte
    order mark: such a file was refused as "not valid JSON" or, for TOML, "not valid TOML
    (Invalid statement (at line 1, column 1))", though nothing else was wrong with it."""
    path = tmp_path / f"rig{suffix}"
    rig = ring_cameras(2)
    write_rig(rig, path, fmt, warn_up=False)
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    assert_same_rig(rig, read_rig(path, fmt, **({"subject": 1} if fmt == "h36m-json" else {})))
    assert detect_format(path) == fmt


def test_qualisys_names_edited_in_another_case_are_read_as_meant(tmp_path):
    """XML names are case-sensitive and the reader matched Qualisys's spelling only: a
    hand-edited `Active="0"` kept the inactive camera, `Serial="cam02"` renamed it 'camera2',
    and a `<Camera>` element was dropped without a word."""
    reference = read_rig(QCA)
    path = _qca_with(
        tmp_path,
        ('active="1" avg-residual="0.402000"', 'Active="0" avg-residual="0.402000"'),
        ('serial="cam02"', 'Serial="cam02"'),
        ('<camera active="1" avg-residual="0.450323"',
         '<Camera active="1" avg-residual="0.450323"'),
        ('</camera>\n    <camera active="1" avg-residual="0.504772"',
         '</Camera>\n    <camera active="1" avg-residual="0.504772"'),
        ('focalLengthU="107118.695313"', 'FOCALLENGTHU="107118.695313"'),
    )  # fmt: skip
    rig = read_rig(path)
    assert rig.names == ["cam02", "cam03", "cam04"]
    assert rig.meta["skipped"] == ["cam01 (inactive)"]
    assert_same_rig(reference.subset(rig.names), rig)


@pytest.mark.parametrize("fmt", ["anipose", "pose2sim"])
def test_a_toml_camera_table_without_any_key_is_refused(tmp_path, fmt):
    """A camera listed with no data (a file cut right after `[cam_3]`, or a table left empty
    by hand) loaded with one camera fewer and no word; Pose2Sim's and aniposelib's readers
    fail on it."""
    path = tmp_path / "calib.toml"
    write_rig(ring_cameras(2), path, fmt)
    text = path.read_text()
    cut = tmp_path / "cut.toml"
    cut.write_text(text[: text.index("[metadata]")] + "[cam_3]\n")
    with pytest.raises(RigFormatError, match=r"cut\.toml: \[cam_3\] .*no keys"):
        read_rig(cut, fmt)
    ok = tmp_path / "ok.toml"  # an empty table that is not a camera's is still skipped
    ok.write_text(text + "[charuco]\n")
    assert len(read_rig(ok, fmt)) == 2


def test_colmap_refuses_a_camera_name_it_cannot_hold(tmp_path):
    """COLMAP's binary model ends an image name at its first NUL character: a camera named
    "a\\x00b" was written without a word and read back as "a", or the model could not be read
    at all (std::bad_alloc)."""
    rig = ring_cameras(2)
    rig = Rig((rig[0].replace(name="c\x000"), rig[1]))
    with pytest.raises(RigFormatError, match=r"camera 'c\\x000'.*NUL"):
        write_rig(rig, tmp_path / "model", "colmap")
    assert not (tmp_path / "model" / "images.bin").exists()

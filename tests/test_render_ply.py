"""3DGS PLY export: round trip, an independent parse of the bytes, and bad files."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from gst.render.ply import (
    SH_C0,
    PlyFormatError,
    read_gaussians_ply,
    write_gaussians_ply,
)

EXPECTED_PROPS = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [
    "scale_0",
    "scale_1",
    "scale_2",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
]


def _cloud(n=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    return dict(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        scales=torch.rand(n, 3, generator=g) * 0.05 + 1e-3,
        opacities=torch.rand(n, generator=g) * 0.98 + 0.01,
        colors=torch.rand(n, 3, generator=g),
    )


def test_round_trip(tmp_path):
    cloud = _cloud()
    path = write_gaussians_ply(tmp_path / "sub" / "person.ply", **cloud)
    back = read_gaussians_ply(path)
    for name, value in cloud.items():
        torch.testing.assert_close(getattr(back, name), value, rtol=1e-5, atol=1e-6)
    assert not list((tmp_path / "sub").glob("*.tmp")), "temporary file left behind"


def test_bytes_follow_the_standard_layout(tmp_path):
    """Parse the header and records by hand with numpy, not with our reader."""
    cloud = _cloud(n=7, seed=1)
    path = write_gaussians_ply(tmp_path / "g.ply", **cloud)
    raw = path.read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    lines = header.decode("ascii").splitlines()
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 7"]
    assert lines[3:] == [f"property float {p}" for p in EXPECTED_PROPS]
    rec = np.frombuffer(body, dtype="<f4").reshape(7, len(EXPECTED_PROPS))
    col = {p: rec[:, i] for i, p in enumerate(EXPECTED_PROPS)}
    np.testing.assert_allclose(
        np.stack([col["x"], col["y"], col["z"]], 1), cloud["means"], rtol=1e-6
    )
    rgb = 0.5 + 0.28209479 * np.stack([col[f"f_dc_{i}"] for i in range(3)], 1)
    np.testing.assert_allclose(rgb, cloud["colors"], atol=1e-5)
    o = cloud["opacities"].double().numpy()
    np.testing.assert_allclose(col["opacity"], np.log(o / (1 - o)), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(
        np.stack([col[f"scale_{i}"] for i in range(3)], 1),
        np.log(cloud["scales"].numpy()),
        rtol=1e-5,
    )
    np.testing.assert_allclose(np.stack([col[f"rot_{i}"] for i in range(4)], 1), cloud["quats"])
    assert np.all(np.stack([col["nx"], col["ny"], col["nz"]]) == 0)


def test_trimesh_reads_the_file(tmp_path):
    cloud = _cloud(n=20, seed=2)
    path = write_gaussians_ply(tmp_path / "g.ply", **cloud)
    loaded = trimesh.load(path)
    np.testing.assert_allclose(np.asarray(loaded.vertices), cloud["means"].numpy(), rtol=1e-6)


def test_extreme_values_stay_finite(tmp_path):
    cloud = _cloud(n=4)
    cloud["opacities"] = torch.tensor([0.0, 1.0, 0.5, 1e-9])
    cloud["scales"][0] = 0.0
    path = write_gaussians_ply(tmp_path / "g.ply", **cloud)
    back = read_gaussians_ply(path)
    for name in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.isfinite(getattr(back, name)).all()
    assert back.opacities[1] > 0.99999 and back.opacities[0] < 1e-5


def test_a_zero_quaternion_is_written_as_no_rotation_and_float32_overflow_refused(tmp_path):
    """A zero quaternion went into the file as it was: viewers divide by its norm (NaN) while
    the rasteriser reads it as no rotation. A finite float64 beyond float32's range was written
    as infinity, against the module's promise of finite numbers."""
    cloud = _cloud(n=3)
    cloud["quats"][1] = 0.0
    back = read_gaussians_ply(write_gaussians_ply(tmp_path / "q.ply", **cloud))
    assert back.quats[1].tolist() == [1.0, 0.0, 0.0, 0.0]
    assert torch.equal(back.quats[[0, 2]], cloud["quats"][[0, 2]].float())
    huge = _cloud(n=2)
    huge["means"] = huge["means"].double()
    huge["means"][0, 0] = 1e39
    with pytest.raises(ValueError, match=r"\['x'\] exceed float32's range"):
        write_gaussians_ply(tmp_path / "huge.ply", **huge)
    assert not (tmp_path / "huge.ply").exists()


def test_reads_other_tools_files_with_extra_properties(tmp_path):
    """A file as trainers write it: doubles, f_rest_* and a face element after the vertices."""
    props = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]
    props += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    n = 3
    data = np.arange(n * len(props), dtype="<f8").reshape(n, len(props)) * 0.01
    header = "ply\nformat binary_little_endian 1.0\ncomment made by hand\n"
    header += f"element vertex {n}\n" + "".join(f"property double {p}\n" for p in props)
    header += "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
    path = tmp_path / "other.ply"
    path.write_bytes(header.encode() + data.tobytes())
    back = read_gaussians_ply(path)
    i = props.index("f_dc_1")
    np.testing.assert_allclose(back.colors[:, 1], 0.5 + SH_C0 * data[:, i], rtol=1e-6)
    np.testing.assert_allclose(back.quats, data[:, -4:], rtol=1e-6)


@pytest.mark.parametrize(
    "content, message",
    [
        (b"hello", "not a PLY"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n",
            "binary_little_endian",
        ),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n"
            b"property float x\nend_header\n",
            "lacks properties",
        ),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n", "no end_header"),
        # these raised bare ValueErrors naming no file, or (no format line) read on silently
        (b"ply\nformat binary_little_endian 1.0\nelement vertex x\nend_header\n", "vertex count"),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n"
            b"property float x\nproperty float x\nend_header\n",
            "'x' given twice",
        ),
        (b"ply\nelement vertex 1\nproperty float x\nend_header\n", "no format line"),
    ],
)
def test_bad_files_are_named(tmp_path, content, message):
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(PlyFormatError, match=message):
        read_gaussians_ply(path)


def test_truncated_file(tmp_path):
    path = write_gaussians_ply(tmp_path / "g.ply", **_cloud(n=5))
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(PlyFormatError, match="truncated"):
        read_gaussians_ply(path)


def test_bad_shapes_are_named(tmp_path):
    cloud = _cloud(n=5)
    cloud["quats"] = cloud["quats"][:, :3]
    with pytest.raises(ValueError, match="quats has shape"):
        write_gaussians_ply(tmp_path / "g.ply", **cloud)
    assert not (tmp_path / "g.ply").exists()


def test_a_negative_scale_is_written_as_the_rasteriser_renders_it(tmp_path):
    """R diag(s) renders |s|; the writer clipped a negative scale to 1e-12 (a degenerate
    Gaussian in every viewer where ours showed 1 cm)."""
    cloud = _cloud(3)
    cloud["scales"][0] = torch.tensor([-0.01, 0.02, 0.03])
    path = tmp_path / "neg.ply"
    write_gaussians_ply(path, **cloud)
    back = read_gaussians_ply(path)
    np.testing.assert_allclose(np.asarray(back.scales)[0], [0.01, 0.02, 0.03], rtol=1e-5)


@pytest.mark.parametrize("prop, value", [("x", np.nan), ("rot_2", np.inf), ("scale_1", np.nan)])
def test_non_finite_values_in_a_file_are_named(tmp_path, prop, value):
    """NaN (or an infinite position, colour or rotation) was read into the cloud silently."""
    path = write_gaussians_ply(tmp_path / "g.ply", **_cloud(n=4))
    raw = path.read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    rec = np.frombuffer(body, dtype="<f4").reshape(4, len(EXPECTED_PROPS)).copy()
    rec[2, EXPECTED_PROPS.index(prop)] = value
    path.write_bytes(header + b"end_header\n" + rec.tobytes())
    with pytest.raises(PlyFormatError, match=rf"g.ply: vertex properties \['{prop}'\] hold NaN"):
        read_gaussians_ply(path)


def test_infinite_log_scale_and_opacity_logit_still_read(tmp_path):
    path = write_gaussians_ply(tmp_path / "g.ply", **_cloud(n=2))
    header, body = path.read_bytes().split(b"end_header\n", 1)
    rec = np.frombuffer(body, dtype="<f4").reshape(2, len(EXPECTED_PROPS)).copy()
    rec[0, EXPECTED_PROPS.index("scale_0")] = -np.inf
    rec[1, EXPECTED_PROPS.index("opacity")] = np.inf
    path.write_bytes(header + b"end_header\n" + rec.tobytes())
    back = read_gaussians_ply(path)
    assert back.scales[0, 0] == 0 and back.opacities[1] == 1

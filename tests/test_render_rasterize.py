"""The torch rasteriser against a brute-force per-pixel reference written here with loops."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gst.render.rasterize import RenderOutput, rasterize


def reference_render(means, quats, scales, opacities, colors, viewmat, K, width, height, near,
                     background=(0.0, 0.0, 0.0)):  # fmt: skip
    """One scene, one camera, float64 numpy, one pixel and one Gaussian at a time.

    Written from the 3DGS definitions, independently of gst.render: EWA projection with the
    Jacobian's x/z, y/z clamped to 1.3x the field of view (gsplat's limits, integer pixel
    centres), 0.3 px^2 low-pass, 3-sigma cut, alpha = min(0.99, o exp(-m / 2)) skipped below
    1/255, front to back, stop before transmittance < 1e-4.
    """
    means, quats, scales, opacities, colors, viewmat, K = (
        np.asarray(a, dtype=np.float64)
        for a in (means, quats, scales, opacities, colors, viewmat, K)
    )
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    projected = []
    for i in range(len(means)):
        x, y, z = rot @ means[i] + trans
        if z < near:
            continue
        qn = np.linalg.norm(quats[i])
        w, qx, qy, qz = quats[i] / qn if qn > 0 else (1.0, 0.0, 0.0, 0.0)
        rq = np.array([
            [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy)],
            [2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx)],
            [2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)],
        ])  # fmt: skip
        cov_world = rq @ np.diag(scales[i] ** 2) @ rq.T
        cov_cam = rot @ cov_world @ rot.T
        lim_xp = (width - 0.5 - cx) / fx + 0.3 * 0.5 * width / fx
        lim_xn = (cx + 0.5) / fx + 0.3 * 0.5 * width / fx
        lim_yp = (height - 0.5 - cy) / fy + 0.3 * 0.5 * height / fy
        lim_yn = (cy + 0.5) / fy + 0.3 * 0.5 * height / fy
        tx = min(max(x / z, -lim_xn), lim_xp)
        ty = min(max(y / z, -lim_yn), lim_yp)
        jac = np.array([[fx / z, 0, -fx * tx / z], [0, fy / z, -fy * ty / z]])
        cov2d = jac @ cov_cam @ jac.T + 0.3 * np.eye(2)
        projected.append((z, i, np.array([fx * x / z + cx, fy * y / z + cy]), np.linalg.inv(cov2d)))
    projected.sort(key=lambda p: (p[0], p[1]))

    rgb = np.zeros((height, width, 3))
    alpha = np.zeros((height, width))
    depth = np.zeros((height, width))
    for v in range(height):
        for u in range(width):
            trans_t, col, dep = 1.0, np.zeros(3), 0.0
            for z, i, mean2d, conic in projected:
                d = np.array([u, v], dtype=np.float64) - mean2d
                maha2 = d @ conic @ d
                if maha2 > 9.0:
                    continue
                a = opacities[i] * math.exp(-0.5 * maha2)
                if a < 1.0 / 255.0:
                    continue
                a = min(a, 0.99)
                if trans_t * (1.0 - a) < 1e-4:
                    break
                col += a * trans_t * colors[i]
                dep += a * trans_t * z
                trans_t *= 1.0 - a
            alpha[v, u] = 1.0 - trans_t
            rgb[v, u] = col + trans_t * np.asarray(background)
            depth[v, u] = dep / alpha[v, u] if alpha[v, u] > 0 else 0.0
    return rgb, alpha, depth


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """World-to-camera 4x4 for an OpenCV camera at `eye` looking at `target`."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    rot = np.stack([x, y, z])
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = -rot @ eye
    return m


def random_scene(seed: int, s: int, n: int, c: int, width: int, height: int, dtype=torch.float64):
    """Gaussians around the origin, cameras about 3 m away; some Gaussians behind a camera."""
    g = np.random.default_rng(seed)
    means = g.normal(0.0, 0.35, (s, n, 3))
    quats = g.normal(size=(s, n, 4))
    scales = np.exp(g.uniform(np.log(0.005), np.log(0.08), (s, n, 3)))
    opacities = g.uniform(0.02, 1.0, (s, n))
    opacities[g.uniform(size=(s, n)) < 0.15] = 1.0  # exercises the 0.99 clamp
    colors = g.uniform(0.0, 1.0, (s, n, 3))
    viewmats = np.zeros((s, c, 4, 4))
    ks = np.zeros((s, c, 3, 3))
    for si in range(s):
        for ci in range(c):
            ang = g.uniform(0, 2 * np.pi)
            eye = np.array([3.0 * np.sin(ang), g.uniform(-0.5, 0.5), 3.0 * np.cos(ang)])
            viewmats[si, ci] = look_at(eye, g.normal(0, 0.1, 3))
            f = g.uniform(0.9, 1.4) * width
            ks[si, ci] = [[f, 0, width / 2 - 0.5 + g.uniform(-2, 2)],
                          [0, f * g.uniform(0.95, 1.05), height / 2 - 0.5 + g.uniform(-2, 2)],
                          [0, 0, 1]]  # fmt: skip
    # A few Gaussians right at / behind the first camera of each scene.
    for si in range(s):
        cam_pos = -viewmats[si, 0, :3, :3].T @ viewmats[si, 0, :3, 3]
        means[si, 0] = cam_pos
        means[si, 1] = cam_pos - 0.5 * viewmats[si, 0, 2, :3]
    t = lambda a: torch.tensor(a, dtype=dtype)  # noqa: E731
    return (t(means), t(quats), t(scales), t(opacities), t(colors), t(viewmats), t(ks))


def _compare(scene, width, height, backgrounds, atol_rgb, atol_depth, near=0.01):
    means, quats, scales, opac, colors, viewmats, ks = scene
    out = rasterize(means, quats, scales, opac, colors, viewmats, ks, width, height,
                    backgrounds=backgrounds, backend="torch", near=near)  # fmt: skip
    s, c = viewmats.shape[:2]
    for si in range(s):
        for ci in range(c):
            bg = (0, 0, 0) if backgrounds is None else backgrounds[si, ci].numpy()
            rgb, alpha, depth = reference_render(
                means[si], quats[si], scales[si], opac[si], colors[si], viewmats[si, ci],
                ks[si, ci], width, height, near, bg,
            )  # fmt: skip
            assert alpha.max() > 0.5, "scene should cover part of the image"
            np.testing.assert_allclose(out.rgb[si, ci].double().numpy(), rgb, atol=atol_rgb, rtol=0)
            np.testing.assert_allclose(
                out.alpha[si, ci].double().numpy(), alpha, atol=atol_rgb, rtol=0
            )
            np.testing.assert_allclose(
                out.depth[si, ci].double().numpy(), depth, atol=atol_depth, rtol=0
            )


@pytest.mark.parametrize("seed", [0, 1])
def test_matches_reference_float64(seed):
    scene = random_scene(seed, s=2, n=60, c=2, width=37, height=29)
    bgs = torch.rand(2, 2, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    _compare(scene, 37, 29, bgs, atol_rgb=1e-9, atol_depth=1e-8)


@pytest.mark.parametrize("seed", [2, 3])
def test_matches_reference_float32(seed):
    scene = random_scene(seed, s=1, n=80, c=2, width=33, height=40, dtype=torch.float32)
    _compare(scene, 33, 40, None, atol_rgb=1e-5, atol_depth=1e-5 * 4.0)


def test_early_stop_on_deep_stack():
    """Many opaque Gaussians along one ray: compositing must stop at transmittance 1e-4."""
    n = 12
    z = torch.linspace(2.0, 3.0, n, dtype=torch.float64)
    means = torch.stack(
        [torch.zeros(n, dtype=torch.float64), torch.zeros(n, dtype=torch.float64), z], -1
    )
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).repeat(n, 1)
    scales = torch.full((n, 3), 0.05, dtype=torch.float64)
    opac = torch.full((n,), 0.93, dtype=torch.float64)
    colors = torch.rand(n, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    vm = torch.eye(4, dtype=torch.float64)[None]
    ks = torch.tensor([[[40.0, 0, 10], [0, 40.0, 10], [0, 0, 1]]], dtype=torch.float64)
    out = rasterize(means, quats, scales, opac, colors, vm, ks, 21, 21, backend="torch")
    rgb, alpha, depth = reference_render(
        means, quats, scales, opac, colors, vm[0], ks[0], 21, 21, 0.01
    )
    np.testing.assert_allclose(out.rgb[0].numpy(), rgb, atol=1e-10)
    np.testing.assert_allclose(out.alpha[0].numpy(), alpha, atol=1e-10)
    np.testing.assert_allclose(out.depth[0].numpy(), depth, atol=1e-10)
    # At the centre alpha = 0.93: T = 3.4e-4 after 3 Gaussians; a 4th would give 2.4e-5.
    t_centre = 1.0 - out.alpha[0, 10, 10].item()
    assert t_centre == pytest.approx(0.07**3, rel=1e-9)


def test_unbatched_matches_batched():
    scene = random_scene(5, s=1, n=40, c=3, width=24, height=20)
    batched = rasterize(*scene, 24, 20, backend="torch")
    unbatched = rasterize(*(t[0] for t in scene), 24, 20, backend="torch")
    assert isinstance(unbatched, RenderOutput)
    assert unbatched.rgb.shape == (3, 20, 24, 3)
    assert torch.equal(unbatched.rgb, batched.rgb[0])
    assert torch.equal(unbatched.depth, batched.depth[0])


def test_tile_block_and_chunk_settings_change_nothing():
    """Images and gradients are the same for any tiling, compositing block and chunk size
    (small blocks exercise the carried transmittance and gradient prefix sums)."""
    from gst.render.cpu_backend import CompositeSettings, rasterize_cpu
    from gst.render.scenes import SplatScenes

    scene = random_scene(7, s=2, n=70, c=2, width=45, height=31)
    scene[3][:] = scene[3].clamp_min(0.6)  # opaque enough to stop compositing early
    w = torch.rand(2, 2, 31, 45, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(0))

    def run(**kw):
        inputs = [t.clone().requires_grad_(True) for t in scene]
        rgb, alpha, dsum = rasterize_cpu(
            SplatScenes(*inputs, 45, 31, 0.01), CompositeSettings(**kw)
        )
        loss = (rgb * w[..., :3]).sum() + (alpha * w[..., 3]).sum() + (dsum * w[..., 4]).sum()
        loss.backward()
        return [rgb, alpha, dsum] + [t.grad for t in inputs]

    ref = run(tile=16, block=256, chunk_elements=1 << 24)
    for kw in [dict(tile=4, block=2, chunk_elements=1 << 8), dict(tile=8, block=3),
               dict(tile=32, block=5, chunk_elements=1 << 12)]:  # fmt: skip
        for a, b in zip(ref, run(**kw), strict=True):
            torch.testing.assert_close(a, b, atol=1e-11, rtol=1e-9)


def test_auto_backend_on_cpu_is_torch():
    scene = random_scene(9, s=1, n=20, c=1, width=16, height=16)
    a = rasterize(*scene, 16, 16, backend="auto")
    b = rasterize(*scene, 16, 16, backend="cpu")
    assert torch.equal(a.rgb, b.rgb)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda a: a.update(quats=a["quats"][..., :3]), "quats has shape"),
        (lambda a: a.update(Ks=a["Ks"][:, :1]), "Ks has shape"),
        (lambda a: a.update(colors=a["colors"].float()), "colors is torch.float32"),
        (lambda a: a.update(backend="vulkan"), "unknown backend"),
        (lambda a: a.update(near=0.0), "near must be > 0"),
        (lambda a: a.update(width=0), "width and height"),
        (lambda a: a["Ks"].__setitem__((0, 0, 0, 1), 3.0), "skew"),
        # a broken camera rendered a blank image with NaN gradients on every Gaussian
        (lambda a: a["Ks"].__setitem__((0, 0, 0, 2), float("nan")), "Ks holds NaN or Inf"),
        (lambda a: a["Ks"].__setitem__((0, 0, 1, 1), float("inf")), "Ks holds NaN or Inf"),
        (lambda a: a["viewmats"].__setitem__((0, 0, 2, 3), float("nan")), "viewmats holds NaN"),
        (lambda a: a.update(width=True), "width and height"),
    ],
)
def test_bad_input_names_the_culprit(change, message):
    means, quats, scales, opac, colors, viewmats, ks = random_scene(1, 1, 5, 2, 8, 8)
    args = dict(means=means, quats=quats, scales=scales, opacities=opac, colors=colors,
                viewmats=viewmats, Ks=ks, width=8, height=8)  # fmt: skip
    change(args)
    with pytest.raises(ValueError, match=message):
        rasterize(**args)


def test_numpy_integer_sizes_are_sizes():
    """`rasterize(..., np.int64(32), np.int64(32))` was refused: 'must be positive ints, got
    32, 32'."""
    import numpy as np

    scene = random_scene(1, 1, 5, 2, 8, 8)
    a = rasterize(*scene, np.int64(8), np.int64(8))
    assert torch.equal(a.rgb, rasterize(*scene, 8, 8).rgb)


def test_empty_and_fully_culled_scenes_render_the_background():
    means, quats, scales, opac, colors, viewmats, ks = random_scene(
        4, s=1, n=6, c=2, width=9, height=7
    )
    bgs = torch.rand(1, 2, 3, dtype=torch.float64)
    empty = rasterize(means[:, :0], quats[:, :0], scales[:, :0], opac[:, :0], colors[:, :0],
                      viewmats, ks, 9, 7, backgrounds=bgs)  # fmt: skip
    assert torch.equal(empty.alpha, torch.zeros(1, 2, 7, 9, dtype=torch.float64))
    assert torch.equal(empty.rgb, bgs[:, :, None, None, :].expand(1, 2, 7, 9, 3))
    behind = rasterize(means, quats, scales, opac, colors, viewmats, ks, 9, 7, near=100.0)
    assert behind.alpha.abs().max() == 0 and behind.depth.abs().max() == 0

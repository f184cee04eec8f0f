"""Benchmark: the tile-binned torch rasteriser against a dense all-pairs torch rasteriser.

Scenes are body-sized: Gaussians (1-2 cm scales, random rotations, opacity 0.5-1) on the
surface of a 1.75 m person made of capsules, seen from about 3 m by a square crop camera
whose focal length makes the person fill about 40% of the crop (the printed `cover` column is
the measured fraction of pixels with alpha > 0.5).

Both rasterisers implement the same conventions and share the projection code, so the table
also prints their disagreement (max |rgb - rgb_dense|, and the relative difference of the
gradient of a fixed random loss with respect to the means).

    python benchmarks/bench_rasterizer.py                 # full table (several minutes)
    python benchmarks/bench_rasterizer.py --quick         # 128^2 and 256^2 with 6.9k only
    python benchmarks/bench_rasterizer.py --tiles 8 16 32 # compare tile sizes (ours only)
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np
import torch
from torch.utils.checkpoint import checkpoint

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.timing import median_time  # noqa: E402
from calibration.camera import look_at_rotation  # noqa: E402
from gst.render.conventions import (  # noqa: E402
    ALPHA_MAX,
    ALPHA_MIN,
    LOG_TRANSMITTANCE_MIN,
    SIGMA_CUTOFF,
)
from gst.render.cpu_backend import (  # noqa: E402
    DEFAULT_CHUNK_ELEMENTS,
    DEFAULT_TILE,
    CompositeSettings,
    rasterize_cpu,
)
from gst.render.projection import project_gaussians  # noqa: E402
from gst.render.scenes import SplatScenes  # noqa: E402

# (centre a, centre b, radius) capsules of a person in an athletic stance in loose sports
# kit, metres, z up, facing -y: legs apart, arms away from the body.
_BODY = [
    ((0.0, 0.0, 0.92), (0.0, 0.0, 1.36), 0.22),  # torso
    ((0.0, 0.0, 1.55), (0.0, -0.01, 1.64), 0.12),  # head
    ((-0.11, 0.0, 0.88), (-0.26, 0.02, 0.10), 0.12),  # left leg
    ((0.11, 0.0, 0.88), (0.26, 0.02, 0.10), 0.12),  # right leg
    ((-0.26, 0.0, 1.38), (-0.62, -0.08, 1.02), 0.09),  # left arm
    ((0.26, 0.0, 1.38), (0.62, -0.08, 1.02), 0.09),  # right arm
]


def body_scene(n: int, size: int, seed: int = 0, dtype=torch.float32):
    """Gaussians on a capsule person and a crop camera 3 m in front; see the module docstring."""
    g = np.random.default_rng(seed)
    caps = [(np.array(a), np.array(b), r) for a, b, r in _BODY]
    areas = np.array(
        [2 * np.pi * r * np.linalg.norm(b - a) + 4 * np.pi * r * r for a, b, r in caps]
    )
    which = g.choice(len(caps), size=n, p=areas / areas.sum())
    pts = np.zeros((n, 3))
    for k, (a, b, r) in enumerate(caps):
        sel = which == k
        m = int(sel.sum())
        t = g.uniform(0, 1, m)[:, None]
        d = g.normal(size=(m, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        pts[sel] = a + t * (b - a) + r * d  # on the swept sphere: the capsule surface
    pts[:, 2] -= 0.85  # centre the body at the origin
    quats = g.normal(size=(n, 4))
    scales = g.uniform(0.01, 0.02, (n, 3))
    opac = g.uniform(0.5, 1.0, n)
    colors = g.uniform(0, 1, (n, 3))

    # OpenCV camera at (0.3, -3, 0.1) looking at the origin: x right, y down (-z world), z in.
    eye = np.array([0.3, -3.0, 0.1])
    rot = look_at_rotation(eye, np.zeros(3))
    view = np.eye(4)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ eye
    f = 0.97 * size * 3.0 / 1.78  # person height ~ 97% of the crop height
    K = np.array([[f, 0, size / 2 - 0.5], [0, f, size / 2 - 0.5], [0, 0, 1]])
    t = lambda a: torch.tensor(a, dtype=dtype)  # noqa: E731
    return (t(pts)[None], t(quats)[None], t(scales)[None], t(opac)[None], t(colors)[None],
            t(view)[None, None], t(K)[None, None])  # fmt: skip


def dense_rasterize(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                    near=0.01, pairs_per_chunk=1 << 20):  # fmt: skip
    """All-pairs reference: every pixel against every Gaussian, chunked over pixels.

    Same conventions as the tile rasteriser (shared projection). Each chunk is a
    (pixels, N) problem: depth-sorted Gaussians, alpha with footprint and clamp, a float64
    cumulative sum of log(1 - alpha) along N, weights, one matmul. Chunks are checkpointed
    so backward recomputes them instead of storing (pixels x N) intermediates (reentrant
    checkpointing: the non-reentrant variant kept ~18 bytes per pair alive here).
    One scene and one camera (S = C = 1). Returns (colour sum, alpha, depth sum).
    """
    proj = project_gaussians(means, quats, scales, viewmats, Ks, width, height, near)
    m2 = proj.means2d[0, 0]
    con = proj.conics[0, 0]
    depth = proj.depths[0, 0]
    op = opacities[0]
    thr = torch.minimum(
        torch.log(op.detach().clamp_min(1e-30) / ALPHA_MIN),
        torch.full_like(op, 0.5 * SIGMA_CUTOFF**2),
    )
    keep = proj.valid[0, 0] & (op.detach() >= ALPHA_MIN)
    # Stable: equal float32 depths (dozens among 14k Gaussians) keep index order, as in ours.
    order = torch.argsort(
        torch.where(keep, depth.detach(), torch.full_like(depth, math.inf)), stable=True
    )
    order = order[: int(keep.sum())]
    feats = torch.cat([colors[0], depth[:, None], torch.ones_like(depth[:, None])], 1)[order]
    m2, con, op, thr = m2[order], con[order], op[order], thr[order]
    pixels = width * height
    step = max(1, pairs_per_chunk // max(1, len(order)))  # pixels per chunk

    def chunk(p0, m2, con, op, feats):
        ids = torch.arange(p0, min(p0 + step, pixels))
        px = (ids % width).to(means.dtype)[:, None]
        py = (ids // width).to(means.dtype)[:, None]
        dx = px - m2[None, :, 0]
        dy = py - m2[None, :, 1]
        power = 0.5 * (con[:, 0] * dx * dx + con[:, 2] * dy * dy) + con[:, 1] * dx * dy
        alpha = torch.clamp(op * torch.exp(-power), max=ALPHA_MAX) * (power <= thr)
        log_1m = torch.log1p(-alpha)
        log_t = torch.cumsum(log_1m.double(), dim=1).to(alpha.dtype)
        w = alpha * torch.exp(log_t - log_1m) * (log_t >= LOG_TRANSMITTANCE_MIN)
        return w @ feats

    grad = torch.is_grad_enabled()
    outs = [
        checkpoint(chunk, p0, m2, con, op, feats, use_reentrant=True)
        if grad
        else chunk(p0, m2, con, op, feats)
        for p0 in range(0, pixels, step)
    ]
    acc = torch.cat(outs, 0).reshape(1, 1, height, width, 5)
    return acc[..., :3], acc[..., 4], acc[..., 3]


def _run(render, scene, size, loss_w, repeats, warmup=True):
    """(forward s, forward+backward s, rgb, alpha, grad of means) for one rasteriser."""
    inputs = [t.clone().requires_grad_(True) for t in scene]

    def fwd():
        return render(*inputs, size, size)

    def fwd_bwd():
        for t in inputs:
            t.grad = None
        rgb, alpha, dsum = render(*inputs, size, size)
        loss = (rgb * loss_w[..., :3]).sum() + (alpha * loss_w[..., 3]).sum()
        loss.backward()
        return rgb.detach(), alpha.detach(), inputs[0].grad.clone()

    if warmup:
        fwd()  # allocator, thread pool
    t_f, _ = median_time(fwd, repeats)
    t_fb, (rgb, alpha, gmeans) = median_time(fwd_bwd, repeats)
    return t_f, t_fb, rgb, alpha, gmeans


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="only 6.9k Gaussians")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs of ours (median)")
    ap.add_argument("--dense-repeats", type=int, default=1, help="timed runs of dense (median)")
    ap.add_argument("--no-dense", action="store_true", help="skip the dense baseline")
    ap.add_argument("--tiles", type=int, nargs="*", default=[DEFAULT_TILE])
    ap.add_argument("--chunk", type=int, default=DEFAULT_CHUNK_ELEMENTS)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    counts = [6890] if args.quick else [1700, 6890, 13718]
    sizes = [128, 256]
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cpus")  # fmt: skip
    print("times are medians in ms; speed-up = dense / ours; f+b = forward + backward")
    head = (f"{'size':>5} {'N':>6} {'tile':>4} {'cover':>5} | {'ours fwd':>8} {'ours f+b':>8} | "
            f"{'dense fwd':>9} {'dense f+b':>9} | {'x fwd':>6} {'x f+b':>6} | "
            f"{'max|drgb|':>9} {'grad rel':>8}")  # fmt: skip
    print(head)
    print("-" * len(head))
    if not args.no_dense:
        # one untimed dense forward and forward + backward on the smallest scene: the dense rows
        # time single calls (warmup=False below), so the first would pay first-call costs
        small = body_scene(counts[0], sizes[0])
        _run(dense_rasterize, small, sizes[0], torch.rand(1, 1, sizes[0], sizes[0], 4), 1, False)
    for size in sizes:
        for n in counts:
            scene = body_scene(n, size)
            g = torch.Generator().manual_seed(0)
            loss_w = torch.rand(1, 1, size, size, 4, generator=g)
            dense = None
            if not args.no_dense:
                dense = _run(
                    lambda *a: dense_rasterize(*a),
                    scene,
                    size,
                    loss_w,
                    args.dense_repeats,
                    warmup=False,  # seconds per call; warmed once on the smallest scene above
                )
            for tile in args.tiles:

                def ours(*a, tile=tile):
                    return rasterize_cpu(
                        SplatScenes(*a, near=0.01),
                        CompositeSettings(tile=tile, chunk_elements=args.chunk),
                    )

                t_f, t_fb, rgb, alpha, gm = _run(ours, scene, size, loss_w, args.repeats)
                cover = float((alpha > 0.5).float().mean())
                row = (f"{size:>5} {n:>6} {tile:>4} {cover:>5.2f} | {t_f * 1e3:>8.1f} "
                       f"{t_fb * 1e3:>8.1f} | ")  # fmt: skip
                if dense is None:
                    row += f"{'-':>9} {'-':>9} | {'-':>6} {'-':>6} | {'-':>9} {'-':>8}"
                else:
                    d_f, d_fb, d_rgb, d_alpha, d_gm = dense
                    err = float((rgb - d_rgb).abs().max())
                    grel = float((gm - d_gm).norm() / d_gm.norm().clamp_min(1e-30))
                    row += (f"{d_f * 1e3:>9.0f} {d_fb * 1e3:>9.0f} | {d_f / t_f:>6.1f} "
                            f"{d_fb / t_fb:>6.1f} | {err:>9.1e} {grel:>8.1e}")  # fmt: skip
                print(row, flush=True)

    # A training-like batch: 4 scenes x 4 cameras each (the views of one sample spread round
    # the person), ours only; dense would take 16x its single-view time.
    size, n = 256, 6890
    scenes = [body_scene(n, size, seed=s) for s in range(4)]
    batch = [torch.cat([sc[i] for sc in scenes]) for i in range(7)]
    view = batch[5]
    yaw = torch.tensor([0.0, 1.2, 2.4, 3.6])
    rz = torch.zeros(4, 4, 4)
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1] = yaw.cos(), -yaw.sin(), yaw.sin(), yaw.cos()
    rz[:, 2, 2] = rz[:, 3, 3] = 1.0
    batch[5] = (view @ rz[None]).contiguous()  # (4, 4, 4, 4): each camera orbits the person
    batch[6] = batch[6].expand(4, 4, 3, 3).contiguous()
    loss_w = torch.rand(4, 4, size, size, 4, generator=torch.Generator().manual_seed(0))

    def ours_batch(*a):
        return rasterize_cpu(
            SplatScenes(*a, near=0.01), CompositeSettings(chunk_elements=args.chunk)
        )

    t_f, t_fb, _, alpha, _ = _run(ours_batch, batch, size, loss_w, max(1, args.repeats // 2))
    print(f"batch S=4 x C=4 views at {size}^2, N={n}: ours fwd {t_f * 1e3:.0f} ms, "
          f"f+b {t_fb * 1e3:.0f} ms ({t_fb * 1e3 / 16:.1f} ms per view), "
          f"cover {float((alpha > 0.5).float().mean()):.2f}")  # fmt: skip


if __name__ == "__main__":
    main()

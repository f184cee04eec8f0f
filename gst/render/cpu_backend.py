"""CPU rasteriser backend: tile-binned, dense-per-tile compositing in pure torch.

How it works (no per-Gaussian or per-pixel Python loops; the only loop is over chunks):

1. Projection (`gst.render.projection`) is plain differentiable torch on (S, C, N) tensors.
2. Binning (no gradient): each visible Gaussian's footprint is the ellipse where it can
   contribute, Mahalanobis radius r = min(3, sqrt(2 ln(255 o))) (beyond the second bound its
   alpha is below 1/255 anyway). Its bounding box is split into T x T pixel tiles, giving
   (Gaussian, tile) entries; one sort by (tile, depth) of these entries -- a few per Gaussian,
   not one per pixel -- puts each tile's Gaussians front to back.
3. Compositing: tiles with similar entry counts are grouped into chunks that fit a memory
   budget; each chunk is evaluated densely as (tiles, K Gaussians, T*T pixels): the
   Gaussian's power at each pixel, the footprint / 1/255 mask, alpha clamped at 0.99,
   an inclusive cumulative sum of log(1 - alpha) along K (per pixel, so the sum stays short
   and accurate), the stop before transmittance drops below 1e-4, weights, and one batched
   matmul that composites colour, depth and alpha together.
4. Backward is a hand-written autograd.Function that recomputes each chunk rather than storing
   it (memory stays at one chunk) and uses the standard suffix-sum identity
   dL/dalpha_k = T_k g.f_k - (sum_{j>k} w_j g.f_j) / (1 - alpha_k).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from gst.render.conventions import (
    ALPHA_MAX,
    ALPHA_MIN,
    LOG_TRANSMITTANCE_MIN,
    SIGMA_CUTOFF,
)
from gst.render.projection import project_gaussians

#: Tile edge in pixels. Measured (benchmarks/bench_rasterizer.py --tile): see docs/rasterizer.md.
DEFAULT_TILE = 16
#: Elements of one chunk's (tiles, K, pixels) tensors; bounds memory at roughly 12x this x 4 B.
DEFAULT_CHUNK_ELEMENTS = 1 << 21


@dataclass
class TileBins:
    """Which Gaussians touch which tiles, front to back. All index tensors are int64."""

    entry_splat: Tensor  # (E,) splat index per entry, sorted by (tile, depth)
    tile_ids: Tensor  # (A,) global id of each active tile: (image * tiles_y + ty) * tiles_x + tx
    tile_start: Tensor  # (A,) first entry of the tile
    tile_count: Tensor  # (A,) number of entries of the tile
    chunks: list[tuple[Tensor, int]]  # (active-tile positions, padded K) per chunk
    num_images: int
    tiles_x: int
    tiles_y: int
    tile: int


@dataclass
class _SplatTable:
    """Per-splat parameters used by the tile kernel: one gather per chunk."""

    params: Tensor  # (G, 7): mean x, mean y, conic a, b, c, log opacity, power threshold
    feats: Tensor  # (G, D + 1): features to composite and a trailing column of ones (alpha)


def _footprint_threshold(opacities: Tensor, cutoff: float) -> Tensor:
    """Largest power 0.5 d^T conic d at which a Gaussian may still contribute (or -inf).

    Two conditions: d inside `cutoff` sigmas (power <= cutoff^2 / 2) and alpha = o exp(-power)
    at least 1/255 (power <= ln(255 o)).
    """
    o = opacities.detach()
    alpha_bound = torch.log(o.clamp_min(1e-30) / ALPHA_MIN)
    thr = torch.minimum(alpha_bound, torch.full_like(o, 0.5 * cutoff * cutoff))
    return torch.where(o >= ALPHA_MIN, thr, torch.full_like(o, -math.inf))


@torch.no_grad()
def bin_splats(
    means2d: Tensor,
    radii: Tensor,
    depths: Tensor,
    thresholds: Tensor,
    num_images: int,
    width: int,
    height: int,
    tile: int = DEFAULT_TILE,
    chunk_elements: int = DEFAULT_CHUNK_ELEMENTS,
) -> TileBins:
    """Assign splats (G = num_images * N flattened, image-major) to tiles, sorted by depth.

    `thresholds` is -inf for splats that cannot contribute (culled, transparent).
    """
    g_total = means2d.shape[0]
    n_per_image = g_total // num_images
    tiles_x = -(-width // tile)
    tiles_y = -(-height // tile)
    device = means2d.device

    r = torch.sqrt(2.0 * thresholds.clamp_min(0.0))  # Mahalanobis radius of the footprint
    # Slightly grow the box so rounding in the per-pixel test can never reach outside it.
    ext = r[:, None] * radii * (1 + 1e-4) + 1e-3
    lo = torch.ceil(torch.clamp(means2d - ext, min=-1.0, max=float(max(width, height))))
    hi = torch.floor(torch.clamp(means2d + ext, min=-1.0, max=float(max(width, height))))
    lo = lo.to(torch.int64)
    hi = hi.to(torch.int64)
    x0 = lo[:, 0].clamp_min(0)
    y0 = lo[:, 1].clamp_min(0)
    x1 = hi[:, 0].clamp_max(width - 1)
    y1 = hi[:, 1].clamp_max(height - 1)
    visible = (thresholds > -math.inf) & (x0 <= x1) & (y0 <= y1)
    vis_idx = torch.nonzero(visible).squeeze(1)

    tx0 = x0[vis_idx] // tile
    ty0 = y0[vis_idx] // tile
    ntx = x1[vis_idx] // tile - tx0 + 1
    nty = y1[vis_idx] // tile - ty0 + 1
    counts = ntx * nty
    num_vis = vis_idx.numel()
    rep = torch.repeat_interleave(torch.arange(num_vis, device=device), counts)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(rep.numel(), device=device) - first[rep]
    ntx_rep = ntx[rep]
    tx = tx0[rep] + local % ntx_rep
    ty = ty0[rep] + local // ntx_rep
    image = vis_idx[rep] // n_per_image
    tile_global = (image * tiles_y + ty) * tiles_x + tx

    # Front-to-back order: rank visible splats by depth (stable, so ties keep index order).
    depth_rank = torch.empty(num_vis, dtype=torch.int64, device=device)
    depth_rank[torch.argsort(depths[vis_idx], stable=True)] = torch.arange(num_vis, device=device)
    order = torch.argsort(tile_global * max(num_vis, 1) + depth_rank[rep])
    entry_splat = vis_idx[rep[order]]
    tile_ids, tile_count = torch.unique_consecutive(tile_global[order], return_counts=True)
    tile_start = torch.cumsum(tile_count, 0) - tile_count

    # Chunks: tiles sorted by entry count, so each chunk pads K to a similar count.
    by_count = torch.argsort(tile_count, descending=True)
    counts_sorted = tile_count[by_count].tolist()
    pixels = tile * tile
    chunks: list[tuple[Tensor, int]] = []
    i = 0
    while i < len(counts_sorted):
        k_max = counts_sorted[i]
        n_tiles = max(1, chunk_elements // (k_max * pixels))
        chunks.append((by_count[i : i + n_tiles], k_max))
        i += n_tiles
    return TileBins(
        entry_splat=entry_splat,
        tile_ids=tile_ids,
        tile_start=tile_start,
        tile_count=tile_count,
        chunks=chunks,
        num_images=num_images,
        tiles_x=tiles_x,
        tiles_y=tiles_y,
        tile=tile,
    )


@dataclass
class _ChunkState:
    """Recomputable per-chunk tensors; (Tc, K, P) unless noted."""

    sid: Tensor  # (Tc, K) splat per entry (0 for padding)
    dx: Tensor  # (Tc, K, 1, T) pixel x minus mean x
    dy: Tensor  # (Tc, K, T, 1)
    entry: Tensor  # (Tc, K, 7) gathered splat parameters
    feats: Tensor  # (Tc, K, D + 1)
    alpha: Tensor  # alpha after mask and clamp
    unclamped: Tensor  # bool: alpha follows o exp(-power) (inside footprint, below clamp)
    log_t_incl: Tensor  # inclusive cumulative log transmittance
    t_excl: Tensor  # transmittance in front of the entry
    weight: Tensor  # alpha * t_excl, zero after the stop


def _chunk_forward(
    table: _SplatTable, bins: TileBins, positions: Tensor, k_max: int, alpha_max: float
) -> _ChunkState:
    tile = bins.tile
    start = bins.tile_start[positions]
    count = bins.tile_count[positions]
    tile_id = bins.tile_ids[positions]
    ar = torch.arange(k_max, device=start.device)
    in_list = ar[None, :] < count[:, None]
    idx = torch.where(in_list, start[:, None] + ar[None, :], torch.zeros_like(start[:, None]))
    sid = bins.entry_splat[idx]  # (Tc, K)
    entry = table.params[sid]  # (Tc, K, 7)
    entry[..., 6].masked_fill_(~in_list, -math.inf)  # padding never contributes
    feats = table.feats[sid]

    dtype = table.params.dtype
    within = torch.arange(tile, device=start.device, dtype=dtype)
    tx = tile_id % bins.tiles_x
    ty = (tile_id // bins.tiles_x) % bins.tiles_y
    px = (tx * tile).to(dtype)[:, None, None] + within  # (Tc, 1, T)
    py = (ty * tile).to(dtype)[:, None, None] + within
    mx, my, ca, cb, cc, logo, thr = entry.unbind(-1)  # each (Tc, K)
    dx = (px - mx[..., None])[..., None, :]  # (Tc, K, 1, T)
    dy = (py - my[..., None])[..., :, None]  # (Tc, K, T, 1)

    # power = 0.5 a dx^2 + b dx dy + 0.5 c dy^2, built from separable pieces.
    power = (cb[..., None, None] * dx) * dy
    power += 0.5 * ca[..., None, None] * dx * dx
    power += 0.5 * cc[..., None, None] * dy * dy
    power = power.flatten(2)  # (Tc, K, P)

    inside = power <= thr[..., None]
    log_pre = logo[..., None] - power  # log(o exp(-power))
    unclamped = inside & (log_pre < math.log(alpha_max))
    alpha = torch.exp(log_pre.clamp_(max=math.log(alpha_max)))
    alpha = alpha.mul_(inside)
    log_1m = torch.log1p(-alpha)
    log_t_incl = torch.cumsum(log_1m, dim=1)
    t_excl = torch.exp(log_t_incl - log_1m)
    weight = alpha * t_excl
    weight = weight.mul_(log_t_incl >= LOG_TRANSMITTANCE_MIN)
    return _ChunkState(sid, dx, dy, entry, feats, alpha, unclamped, log_t_incl, t_excl, weight)


def _to_tiles(image: Tensor, bins: TileBins) -> Tensor:
    """(B, H, W, D) -> (B * tiles_y * tiles_x, T * T, D), zero padded."""
    b, h, w, d = image.shape
    t = bins.tile
    padded = image.new_zeros(b, bins.tiles_y * t, bins.tiles_x * t, d)
    padded[:, :h, :w] = image
    padded = padded.reshape(b, bins.tiles_y, t, bins.tiles_x, t, d).permute(0, 1, 3, 2, 4, 5)
    return padded.reshape(b * bins.tiles_y * bins.tiles_x, t * t, d)


def _from_tiles(tiles: Tensor, bins: TileBins, height: int, width: int) -> Tensor:
    """Inverse of `_to_tiles`, cropped to (B, H, W, D)."""
    t = bins.tile
    d = tiles.shape[-1]
    img = tiles.reshape(bins.num_images, bins.tiles_y, bins.tiles_x, t, t, d)
    img = img.permute(0, 1, 3, 2, 4, 5).reshape(
        bins.num_images, bins.tiles_y * t, bins.tiles_x * t, d
    )
    return img[:, :height, :width]


class _Composite(torch.autograd.Function):
    """Front-to-back compositing of binned splats; outputs (B, H, W, D + 1), last = alpha."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, thresholds, bins, width, height, alpha_max):
        table = _make_table(means2d, conics, opacities, feats, thresholds)
        d1 = table.feats.shape[1]
        n_tiles = bins.num_images * bins.tiles_y * bins.tiles_x
        out = means2d.new_zeros(n_tiles, bins.tile * bins.tile, d1)
        for positions, k_max in bins.chunks:
            st = _chunk_forward(table, bins, positions, k_max, alpha_max)
            tiles_out = torch.bmm(st.weight.transpose(1, 2), st.feats)  # (Tc, P, D + 1)
            out[bins.tile_ids[positions]] = tiles_out
        ctx.save_for_backward(means2d, conics, opacities, feats, thresholds)
        ctx.bins = bins
        ctx.size = (width, height)
        ctx.alpha_max = alpha_max
        return _from_tiles(out, bins, height, width)

    @staticmethod
    def backward(ctx, grad_image):
        means2d, conics, opacities, feats, thresholds = ctx.saved_tensors
        bins: TileBins = ctx.bins
        table = _make_table(means2d, conics, opacities, feats, thresholds)
        grad_tiles = _to_tiles(grad_image.contiguous(), bins)
        g_params = torch.zeros_like(table.params[:, :6])  # mx, my, a, b, c, opacity
        g_feats = torch.zeros_like(table.feats)
        for positions, k_max in bins.chunks:
            st = _chunk_forward(table, bins, positions, k_max, ctx.alpha_max)
            gout = grad_tiles[bins.tile_ids[positions]]  # (Tc, P, D + 1)
            ge, gf = _chunk_backward(st, gout)
            g_params.index_add_(0, st.sid.flatten(), ge.flatten(0, 1))
            g_feats.index_add_(0, st.sid.flatten(), gf.flatten(0, 1))
        g_means2d = g_params[:, 0:2]
        g_conics = g_params[:, 2:5]
        g_opac = g_params[:, 5]
        return g_means2d, g_conics, g_opac, g_feats[:, :-1], None, None, None, None, None


def _make_table(means2d, conics, opacities, feats, thresholds) -> _SplatTable:
    logo = torch.log(opacities.clamp_min(1e-30))
    params = torch.cat([means2d, conics, logo[:, None], thresholds[:, None]], dim=1)
    ones = feats.new_ones(feats.shape[0], 1)
    return _SplatTable(params=params, feats=torch.cat([feats, ones], dim=1))


def _chunk_backward(st: _ChunkState, gout: Tensor) -> tuple[Tensor, Tensor]:
    """Gradients of one chunk: per entry (Tc, K, 6) [mx, my, a, b, c, o] and (Tc, K, D + 1)."""
    g_feats = torch.bmm(st.weight, gout)  # (Tc, K, D + 1)
    gdotf = torch.bmm(st.feats, gout.transpose(1, 2))  # (Tc, K, P): g . f_k at each pixel
    h = st.weight * gdotf
    suffix = torch.cumsum(h, dim=1)
    suffix = suffix[:, -1:, :] - suffix  # sum over later entries j > k
    included = st.log_t_incl >= LOG_TRANSMITTANCE_MIN
    g_alpha = st.t_excl * gdotf - suffix / (1.0 - st.alpha)
    # Only entries that were composited and whose alpha is not clamped pass gradient to
    # o exp(-power); q = dL/dalpha * alpha is dL/dlog(alpha) = dL/dlog(o) = -dL/dpower.
    q = g_alpha.mul_(st.alpha).mul_(included & st.unclamped)
    tc, k = q.shape[:2]
    t = st.dx.shape[-1]
    gpow = q.view(tc, k, t, t).neg()  # rows = y, cols = x
    gcol = gpow.sum(dim=-2)  # (Tc, K, T) as a function of x
    grow = gpow.sum(dim=-1)  # (Tc, K, T) as a function of y
    dx = st.dx[..., 0, :]  # (Tc, K, T)
    dy = st.dy[..., :, 0]
    gxy = (gpow * st.dy).sum(dim=-2)  # (Tc, K, T): sum over y of gpow * dy, per x
    mx_, my_, ca, cb, cc, logo, _ = st.entry.unbind(-1)
    s_dx = (gcol * dx).sum(-1)
    s_dy = (grow * dy).sum(-1)
    g_a = 0.5 * (gcol * dx * dx).sum(-1)
    g_c = 0.5 * (grow * dy * dy).sum(-1)
    g_b = (gxy * dx).sum(-1)
    g_mx = -(ca * s_dx + cb * s_dy)
    g_my = -(cc * s_dy + cb * s_dx)
    g_o = q.sum(-1) * torch.exp(-logo)
    g_entry = torch.stack([g_mx, g_my, g_a, g_b, g_c, g_o], dim=-1)
    return g_entry, g_feats


def composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    feats: Tensor,
    radii: Tensor,
    depths: Tensor,
    valid: Tensor,
    num_images: int,
    width: int,
    height: int,
    *,
    sigma_cutoff: float = SIGMA_CUTOFF,
    alpha_max: float = ALPHA_MAX,
    tile: int = DEFAULT_TILE,
    chunk_elements: int = DEFAULT_CHUNK_ELEMENTS,
) -> Tensor:
    """Composite G = num_images * N flattened splats into (num_images, H, W, D + 1).

    The last channel is alpha (1 - final transmittance); the first D channels are the
    alpha-weighted sums of `feats` (no background).
    """
    thresholds = _footprint_threshold(opacities, sigma_cutoff)
    thresholds = torch.where(valid, thresholds, torch.full_like(thresholds, -math.inf))
    bins = bin_splats(
        means2d.detach(), radii, depths.detach(), thresholds, num_images, width, height,
        tile=tile, chunk_elements=chunk_elements,
    )  # fmt: skip
    return _Composite.apply(
        means2d, conics, opacities, feats, thresholds, bins, width, height, alpha_max
    )


def rasterize_cpu(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near: float,
    *,
    sigma_cutoff: float = SIGMA_CUTOFF,
    alpha_max: float = ALPHA_MAX,
    tile: int = DEFAULT_TILE,
    chunk_elements: int = DEFAULT_CHUNK_ELEMENTS,
) -> tuple[Tensor, Tensor, Tensor]:
    """Render batched, validated inputs (S, N, ...) x (S, C, ...) on any torch device.

    Returns (colour sum (S, C, H, W, 3) without background, alpha (S, C, H, W),
    alpha-weighted depth sum (S, C, H, W)).
    """
    s, n = means.shape[:2]
    c = viewmats.shape[1]
    proj = project_gaussians(means, quats, scales, viewmats, Ks, width, height, near)
    g = s * c * n
    feats = torch.cat(
        [colors[:, None].expand(s, c, n, colors.shape[-1]), proj.depths[..., None]], dim=-1
    )
    acc = composite(
        proj.means2d.reshape(g, 2),
        proj.conics.reshape(g, 3),
        opacities[:, None].expand(s, c, n).reshape(g),
        feats.reshape(g, -1),
        proj.radii.reshape(g, 2),
        proj.depths.reshape(g),
        proj.valid.reshape(g),
        s * c,
        width,
        height,
        sigma_cutoff=sigma_cutoff,
        alpha_max=alpha_max,
        tile=tile,
        chunk_elements=chunk_elements,
    ).reshape(s, c, height, width, -1)
    return acc[..., :3], acc[..., 4], acc[..., 3]

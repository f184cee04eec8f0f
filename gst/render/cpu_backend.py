"""CPU rasteriser backend: tile-binned, dense-per-tile compositing in pure torch.

How it works (no per-Gaussian or per-pixel Python loops; Python loops run over chunks of tiles
and blocks of entries only):

1. Projection (`gst.render.projection`) is plain differentiable torch on (S, C, N) tensors.
2. Binning (no gradient): each visible Gaussian's footprint is the ellipse where it can
   contribute, Mahalanobis radius r = min(3, sqrt(2 ln(255 o))) (beyond the second bound its
   alpha is below 1/255 anyway). Its bounding box is split into T x T pixel tiles, giving
   (Gaussian, tile) entries; one sort by (tile, depth) of these entries -- tens per Gaussian,
   not one per pixel -- puts each tile's Gaussians front to back.
3. Compositing: tiles are grouped into chunks of similar entry counts (a cache-sized budget)
   and their entries are taken in blocks of 32, front to back. A block is evaluated densely as
   (tiles, 32 Gaussians, T*T pixels): the Gaussian's power at each pixel, the footprint and
   1/255 mask, alpha clamped at 0.99, the cumulative sum of log(1 - alpha) along the block,
   continued from the previous block (per pixel, so sums stay short and float32 stays
   accurate), the stop before transmittance drops below 1e-4, weights, and one batched matmul
   that composites colour, depth and alpha together. A tile leaves the loop once all of its
   pixels have stopped, so Gaussians hidden behind opaque ones cost nothing.
4. Backward is a hand-written autograd.Function that recomputes each block rather than
   storing it (memory stays at one block). The 3DGS gradient
   dL/dalpha_k = T_k g.f_k - (sum_{j>k} w_j g.f_j) / (1 - alpha_k) needs a suffix sum; since
   sum_j w_j g.f_j = g.output, it is "g.output minus a running prefix", so the backward
   also runs front to back, block by block, with the same early exit.
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
from gst.render.scenes import SplatScenes

#: Tile edge in pixels (benchmarks/bench_rasterizer.py --tiles compares sizes).
DEFAULT_TILE = 4
#: Entries (Gaussians per tile) composited per step; tiles whose pixels have all reached the
#: transmittance stop are dropped between steps, so hidden Gaussians cost nothing.
DEFAULT_BLOCK = 32
#: Elements of one step's (tiles, block, pixels) tensors: small enough to stay in cache.
DEFAULT_CHUNK_ELEMENTS = 1 << 18


@dataclass
class TileBins:
    """Which Gaussians touch which tiles, front to back. All index tensors are int64."""

    entry_splat: Tensor  # (E,) splat index per entry, sorted by (tile, depth)
    tile_ids: Tensor  # (A,) global id of each active tile: (image * tiles_y + ty) * tiles_x + tx
    tile_start: Tensor  # (A,) first entry of the tile
    tile_count: Tensor  # (A,) number of entries of the tile
    chunks: list[tuple[Tensor, int]]  # (active-tile positions, longest list) per chunk
    block: int  # entries per compositing step
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
    block: int = DEFAULT_BLOCK,
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
    finite = torch.isfinite(means2d).all(1) & torch.isfinite(ext).all(1)  # NaN input: skip
    visible = (thresholds > -math.inf) & finite & (x0 <= x1) & (y0 <= y1)
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

    # Chunks: tiles sorted by entry count, so the tiles of a chunk run out of entries together.
    by_count = torch.argsort(tile_count, descending=True)
    per_chunk = max(1, chunk_elements // (block * tile * tile))
    longest = tile_count[by_count[::per_chunk]].tolist()
    chunks = [(by_count[i * per_chunk : (i + 1) * per_chunk], k) for i, k in enumerate(longest)]
    return TileBins(
        entry_splat=entry_splat,
        tile_ids=tile_ids,
        tile_start=tile_start,
        tile_count=tile_count,
        chunks=chunks,
        block=block,
        num_images=num_images,
        tiles_x=tiles_x,
        tiles_y=tiles_y,
        tile=tile,
    )


@dataclass
class _Block:
    """One block of K entries for the still-active tiles of a chunk; (Ta, K, P) unless noted."""

    sid: Tensor  # (Ta, K) splat per entry (0 for padding)
    entry: Tensor  # (Ta, K, 7) gathered splat parameters
    feats: Tensor  # (Ta, K, D + 1)
    dx: Tensor  # (Ta, K, 1, T) pixel x minus mean x
    dy: Tensor  # (Ta, K, T, 1)
    log_pre: Tensor  # log(o exp(-power)), before the clamp; -inf outside the footprint
    alpha: Tensor  # alpha after footprint mask and clamp
    log_t_incl: Tensor  # cumulative log transmittance including this entry
    t_excl: Tensor  # transmittance in front of the entry
    weight: Tensor  # alpha * t_excl, zero once compositing has stopped


@dataclass
class _Chunk:
    """Tiles composited together: positions into the active-tile arrays and their geometry."""

    positions: Tensor  # (Tc,) indices into TileBins.tile_ids / tile_start / tile_count
    k_max: int
    px: Tensor  # (Tc, 1, T) pixel x of each tile column
    py: Tensor  # (Tc, 1, T) pixel y of each tile row
    log_t0: Tensor  # (Tc, P) initial log transmittance: 0, or -inf for pixels off the image


def _make_chunk(bins: TileBins, positions: Tensor, k_max: int, dtype, width, height) -> _Chunk:
    tile = bins.tile
    tile_id = bins.tile_ids[positions]
    within = torch.arange(tile, device=positions.device)
    tx = tile_id % bins.tiles_x
    ty = (tile_id // bins.tiles_x) % bins.tiles_y
    px = (tx * tile)[:, None, None] + within  # (Tc, 1, T)
    py = (ty * tile)[:, None, None] + within
    on_image = (py[:, 0, :, None] < height) & (px[:, :, None, :][:, 0] < width)  # (Tc, T, T)
    log_t0 = torch.zeros(on_image.shape, dtype=dtype, device=positions.device)
    log_t0.masked_fill_(~on_image, -math.inf)  # treated as already stopped
    return _Chunk(positions, k_max, px.to(dtype), py.to(dtype), log_t0.flatten(1))


def _block_forward(
    table: _SplatTable,
    bins: TileBins,
    chunk: _Chunk,
    active: Tensor | None,
    k0: int,
    k1: int,
    log_t_carry: Tensor,
    alpha_max: float,
) -> _Block:
    """Entries k0..k1-1 of the `active` tiles (indices into the chunk, None for all),
    continuing from the log transmittance `log_t_carry` (Ta, P) left by entries before k0."""
    positions = _take(chunk.positions, active)
    start = bins.tile_start[positions]
    count = bins.tile_count[positions]
    ar = torch.arange(k0, k1, device=start.device)
    in_list = ar[None, :] < count[:, None]
    idx = torch.where(in_list, start[:, None] + ar[None, :], torch.zeros_like(start[:, None]))
    sid = _rows(bins.entry_splat, idx)  # (Ta, K)
    entry = _rows(table.params, sid)  # (Ta, K, 7), a copy
    entry[..., 6].masked_fill_(~in_list, -math.inf)  # padding never contributes
    feats = _rows(table.feats, sid)

    mx, my, ca, cb, cc, logo, thr = entry.unbind(-1)  # each (Ta, K)
    dx = (_take(chunk.px, active) - mx[..., None])[..., None, :]  # (Ta, K, 1, T)
    dy = (_take(chunk.py, active) - my[..., None])[..., :, None]  # (Ta, K, T, 1)
    # power = 0.5 a dx^2 + b dx dy + 0.5 c dy^2 from separable pieces: one full-size product.
    power = (cb[..., None, None] * dx) * dy
    power += 0.5 * ca[..., None, None] * dx * dx
    power += 0.5 * cc[..., None, None] * dy * dy
    power = power.flatten(2)  # (Ta, K, P)

    outside = power > thr[..., None]
    log_pre = torch.sub(logo[..., None], power, out=power)  # log(o exp(-power)), in place
    log_pre.masked_fill_(outside, -math.inf)
    alpha = torch.exp(torch.clamp(log_pre, max=math.log(alpha_max)))
    log_1m = torch.log1p(alpha.neg())
    log_t_incl = torch.cumsum(log_1m, dim=1).add_(log_t_carry[:, None, :])
    t_excl = torch.exp(log_t_incl - log_1m)
    weight = alpha * t_excl
    weight.masked_fill_(log_t_incl < LOG_TRANSMITTANCE_MIN, 0.0)
    return _Block(sid, entry, feats, dx, dy, log_pre, alpha, log_t_incl, t_excl, weight)


def _blocks(bins: TileBins, chunk: _Chunk, block: int):
    """Yield (k0, k1, tiles of the chunk whose lists reach k0) for successive blocks."""
    count = bins.tile_count[chunk.positions]
    for k0 in range(0, chunk.k_max, block):
        yield k0, min(k0 + block, chunk.k_max), count > k0


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
            chunk = _make_chunk(bins, positions, k_max, means2d.dtype, width, height)
            log_t = chunk.log_t0
            acc = out.new_zeros(len(positions), bins.tile * bins.tile, d1)
            for k0, k1, listed in _blocks(bins, chunk, bins.block):
                active = _active(listed & _running(log_t))
                if active is not None and active.numel() == 0:
                    break
                blk = _block_forward(
                    table, bins, chunk, active, k0, k1, _take(log_t, active), alpha_max
                )
                contrib = torch.bmm(blk.weight.transpose(1, 2), blk.feats)
                acc = _put(acc, active, _take(acc, active) + contrib)
                log_t = _put(log_t, active, blk.log_t_incl[:, -1])
            out[bins.tile_ids[positions]] = acc
        image = _from_tiles(out, bins, height, width)
        ctx.save_for_backward(means2d, conics, opacities, feats, thresholds, image)
        ctx.bins = bins
        ctx.size = (width, height)
        ctx.alpha_max = alpha_max
        return image

    @staticmethod
    def backward(ctx, grad_image):
        # The forward ran with autocast off (see rasterize); a backward called inside an autocast
        # region would otherwise run its matmuls in bf16 and mix dtypes in the index_add_ below.
        with torch.autocast(grad_image.device.type, enabled=False):
            return _Composite._backward(ctx, grad_image)

    @staticmethod
    def _backward(ctx, grad_image):
        means2d, conics, opacities, feats, thresholds, image = ctx.saved_tensors
        bins: TileBins = ctx.bins
        width, height = ctx.size
        table = _make_table(means2d, conics, opacities, feats, thresholds)
        grad_tiles = _to_tiles(grad_image.contiguous(), bins)
        # sum_j w_j (g . f_j) over a whole pixel equals g . output: with it, the suffix sums
        # the alpha gradient needs become "total minus prefix", so blocks run front to back.
        g_dot_out = (grad_tiles * _to_tiles(image, bins)).sum(-1)  # (tiles, P)
        g_params = torch.zeros_like(table.params[:, :6])  # mx, my, a, b, c, opacity
        g_feats = torch.zeros_like(table.feats)
        for positions, k_max in bins.chunks:
            chunk = _make_chunk(bins, positions, k_max, means2d.dtype, width, height)
            tiles = bins.tile_ids[positions]
            gout_chunk = _rows(grad_tiles, tiles)
            gdo_chunk = _rows(g_dot_out, tiles)
            log_t = chunk.log_t0
            h_prefix = torch.zeros_like(log_t)
            for k0, k1, listed in _blocks(bins, chunk, bins.block):
                active = _active(listed & _running(log_t))
                if active is not None and active.numel() == 0:
                    break
                blk = _block_forward(
                    table, bins, chunk, active, k0, k1, _take(log_t, active), ctx.alpha_max
                )
                ge, gf, h_last = _block_backward(
                    blk,
                    _take(gout_chunk, active),
                    _take(gdo_chunk, active),
                    _take(h_prefix, active),
                    ctx.alpha_max,
                )
                g_params.index_add_(0, blk.sid.flatten(), ge.flatten(0, 1))
                g_feats.index_add_(0, blk.sid.flatten(), gf.flatten(0, 1))
                log_t = _put(log_t, active, blk.log_t_incl[:, -1])
                h_prefix = _put(h_prefix, active, h_last)
        g_means2d = g_params[:, 0:2]
        g_conics = g_params[:, 2:5]
        g_opac = g_params[:, 5]
        return g_means2d, g_conics, g_opac, g_feats[:, :-1], None, None, None, None, None


def _active(mask: Tensor) -> Tensor | None:
    """Indices of the True entries, or None when all are True (saves gathers and scatters)."""
    if bool(mask.all()):
        return None
    return torch.nonzero(mask).squeeze(1)


def _take(t: Tensor, idx: Tensor | None) -> Tensor:
    return t if idx is None else _rows(t, idx)


def _rows(t: Tensor, idx: Tensor) -> Tensor:
    """t[idx] along dim 0 for an index tensor of any shape (index_select: faster on CPU)."""
    return t.index_select(0, idx.reshape(-1)).view(*idx.shape, *t.shape[1:])


def _put(t: Tensor, idx: Tensor | None, values: Tensor) -> Tensor:
    """`t` with rows `idx` replaced by `values` (all rows when idx is None)."""
    return values if idx is None else t.index_copy(0, idx, values)


def _running(log_t: Tensor) -> Tensor:
    """(Tc,) bool: tiles with at least one pixel still compositing."""
    return (log_t >= LOG_TRANSMITTANCE_MIN).any(dim=1)


def _make_table(means2d, conics, opacities, feats, thresholds) -> _SplatTable:
    logo = torch.log(opacities.clamp_min(1e-30))
    params = torch.cat([means2d, conics, logo[:, None], thresholds[:, None]], dim=1)
    ones = feats.new_ones(feats.shape[0], 1)
    return _SplatTable(params=params, feats=torch.cat([feats, ones], dim=1))


def _block_backward(
    blk: _Block, gout: Tensor, g_dot_out: Tensor, h_prefix: Tensor, alpha_max: float
) -> tuple[Tensor, Tensor, Tensor]:
    """Gradients of one block.

    Returns per entry (Ta, K, 6) [mx, my, a, b, c, o] and (Ta, K, D + 1), and the running sum
    of h_j = w_j g.f_j over entries up to the block's last (Ta, P).
    """
    g_feats = torch.bmm(blk.weight, gout)  # (Ta, K, D + 1)
    gdotf = torch.bmm(blk.feats, gout.transpose(1, 2))  # (Ta, K, P): g . f_k at each pixel
    h_incl = torch.cumsum(blk.weight * gdotf, dim=1).add_(h_prefix[:, None, :])
    later = g_dot_out[:, None, :] - h_incl  # sum of h_j over entries j behind entry k
    # dL/dalpha_k = T_k g.f_k - (sum_{j>k} w_j g.f_j) / (1 - alpha_k)
    g_alpha = blk.t_excl * gdotf - later / (1.0 - blk.alpha)
    # Only composited entries whose alpha is not clamped pass gradient to o exp(-power);
    # q = dL/dalpha * alpha is dL/dlog(o) and -dL/dpower.
    frozen = (blk.log_t_incl < LOG_TRANSMITTANCE_MIN) | (blk.log_pre >= math.log(alpha_max))
    q = g_alpha.mul_(blk.alpha).masked_fill_(frozen, 0.0)
    ta, k = q.shape[:2]
    t = blk.dx.shape[-1]
    gpow = q.view(ta, k, t, t)  # rows = y, cols = x; dL/dpower = -gpow
    gcol = gpow.sum(dim=-2)  # (Ta, K, T) as a function of x
    grow = gpow.sum(dim=-1)  # (Ta, K, T) as a function of y
    dx = blk.dx[..., 0, :]  # (Ta, K, T)
    dy = blk.dy[..., :, 0]
    gxy = (gpow * blk.dy).sum(dim=-2)  # (Ta, K, T): sum over y of gpow * dy, per x
    _, _, ca, cb, cc, logo, _ = blk.entry.unbind(-1)
    s_dx = (gcol * dx).sum(-1)
    s_dy = (grow * dy).sum(-1)
    g_a = -0.5 * (gcol * dx * dx).sum(-1)
    g_c = -0.5 * (grow * dy * dy).sum(-1)
    g_b = -(gxy * dx).sum(-1)
    g_mx = ca * s_dx + cb * s_dy
    g_my = cc * s_dy + cb * s_dx
    g_o = q.sum(-1) * torch.exp(-logo)
    g_entry = torch.stack([g_mx, g_my, g_a, g_b, g_c, g_o], dim=-1)
    return g_entry, g_feats, h_incl[:, -1]


@dataclass(frozen=True)
class CompositeSettings:
    """The compositor's footprint, clamp and work sizes (the conventions by default; tiling,
    block and chunk sizes change speed only, never the images or gradients)."""

    sigma_cutoff: float = SIGMA_CUTOFF
    alpha_max: float = ALPHA_MAX
    tile: int = DEFAULT_TILE
    block: int = DEFAULT_BLOCK
    chunk_elements: int = DEFAULT_CHUNK_ELEMENTS


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
    settings: CompositeSettings = CompositeSettings(),
) -> Tensor:
    """Composite G = num_images * N flattened splats into (num_images, H, W, D + 1).

    The last channel is alpha (1 - final transmittance); the first D channels are the
    alpha-weighted sums of `feats` (no background).
    """
    thresholds = _footprint_threshold(opacities, settings.sigma_cutoff)
    thresholds = torch.where(valid, thresholds, torch.full_like(thresholds, -math.inf))
    bins = bin_splats(
        means2d.detach(), radii, depths.detach(), thresholds, num_images, width, height,
        tile=settings.tile, block=settings.block, chunk_elements=settings.chunk_elements,
    )  # fmt: skip
    return _Composite.apply(
        means2d, conics, opacities, feats, thresholds, bins, width, height, settings.alpha_max
    )


def rasterize_cpu(
    sc: SplatScenes, settings: CompositeSettings = CompositeSettings()
) -> tuple[Tensor, Tensor, Tensor]:
    """Render batched, validated inputs on any torch device.

    Returns (colour sum (S, C, H, W, 3) without background, alpha (S, C, H, W),
    alpha-weighted depth sum (S, C, H, W)).
    """
    s, n = sc.means.shape[:2]
    c = sc.viewmats.shape[1]
    proj = project_gaussians(
        sc.means, sc.quats, sc.scales, sc.viewmats, sc.Ks, sc.width, sc.height, sc.near
    )
    g = s * c * n
    feats = torch.cat(
        [sc.colors[:, None].expand(s, c, n, sc.colors.shape[-1]), proj.depths[..., None]], dim=-1
    )
    acc = composite(
        proj.means2d.reshape(g, 2),
        proj.conics.reshape(g, 3),
        sc.opacities[:, None].expand(s, c, n).reshape(g),
        feats.reshape(g, feats.shape[-1]),
        proj.radii.reshape(g, 2),
        proj.depths.reshape(g),
        proj.valid.reshape(g),
        s * c,
        sc.width,
        sc.height,
        settings,
    ).reshape(s, c, sc.height, sc.width, -1)
    return acc[..., :3], acc[..., 4], acc[..., 3]

"""People out of occupied voxels: 3D components split where several people touch (ground-plane
density peaks, or person instances the cameras agree on), pieces of one body merged back."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from gst.data.association.hull import Person3D, VoxelGrid


def candidates(
    grid: VoxelGrid,
    occupied: np.ndarray,
    strict: np.ndarray | None = None,
    labels: dict[str, np.ndarray] | None = None,
) -> list[Person3D]:
    """Person candidates among the occupied voxels: 3D components, split where several
    people touch, with pieces of one body merged back (pieces standing on one spot, and,
    given the `labels`, pieces that land on the same silhouettes in the cameras)."""
    cfg = grid.config
    v = cfg.voxel_size
    strict = occupied if strict is None else strict
    dense = np.zeros(grid.dims, dtype=bool)
    occ_idx = np.nonzero(occupied)[0]
    if len(occ_idx) == 0:
        return []
    dense.reshape(-1)[grid.kept[occ_idx]] = True
    comp, n = ndimage.label(dense, structure=np.ones((3, 3, 3), dtype=bool))
    comp_of_kept = comp.reshape(-1)[grid.kept[occ_idx]]
    order = np.argsort(comp_of_kept, kind="stable")
    bounds = np.searchsorted(comp_of_kept[order], np.arange(1, n + 2))
    out = []
    for k in range(n):
        vox = occ_idx[order[bounds[k] : bounds[k + 1]]]
        for part in split_component(grid, vox):
            pieces = (
                split_by_instances(grid, part, labels) if cfg.instance_split and labels else [part]
            )
            out.extend(grid.person(piece, strict) for piece in pieces)
    out = merge_stacked(grid, out, strict)
    if labels is not None:
        out = merge_same_blobs(grid, out, strict, labels)
    return [
        p
        for p in out
        if len(p.voxels) * v**3 >= cfg.min_person_volume and p.height >= cfg.min_person_height
    ]


def split_component(grid: VoxelGrid, vox: np.ndarray) -> list[np.ndarray]:
    """Split one 3D component into people at the peaks of its ground-plane density."""
    cfg = grid.config
    v = cfg.voxel_size
    ij = grid.ijk[vox, :2]
    lo = ij.min(axis=0)
    size = ij.max(axis=0) - lo + 1
    dens = np.zeros(size, dtype=np.float32)
    np.add.at(dens, (ij[:, 0] - lo[0], ij[:, 1] - lo[1]), 1.0)
    if max(size) * v < cfg.peak_separation:
        return [vox]
    pad = int(np.ceil(3 * cfg.ground_sigma / v))
    dens = np.pad(dens, pad)
    dens = ndimage.gaussian_filter(dens, cfg.ground_sigma / v)
    win = max(3, int(round(cfg.peak_separation / v)) | 1)
    peaks = np.argwhere(
        (dens == ndimage.maximum_filter(dens, size=win)) & (dens >= cfg.peak_ratio * dens.max())
    )
    if len(peaks) <= 1:
        return [vox]
    # Keep peaks that are far enough apart, strongest first.
    order = np.argsort(-dens[peaks[:, 0], peaks[:, 1]])
    chosen: list[np.ndarray] = []
    for p in peaks[order]:
        if all(np.linalg.norm(p - q) * v >= cfg.peak_separation for q in chosen):
            chosen.append(p)
    if len(chosen) <= 1:
        return [vox]
    centres = np.array(chosen) - pad + lo  # grid (i, j)
    d = ((ij[:, None, :] - centres[None]) ** 2).sum(-1)
    owner = d.argmin(axis=1)
    return [vox[owner == k] for k in range(len(chosen))]


def split_by_instances(
    grid: VoxelGrid, vox: np.ndarray, labels: dict[str, np.ndarray]
) -> list[np.ndarray]:
    """Split a component along person instances when the cameras agree it holds several.

    Per camera, the instances holding at least `instance_share` of the component's labelled
    voxels are its people there. With at least two such instances in `min_views` cameras,
    the camera that separates the component most evenly gives a first grouping. Then every
    camera votes: each of its instances goes to the group most of its voxels are in (when
    that group holds at least 60% of them), and each voxel takes the group most cameras vote
    for. A voxel hidden behind another person in one view is outvoted by the other views.
    Voxels nobody votes for go to the nearest group on the ground.
    """
    cfg = grid.config
    names = [n for n in grid.names if n in labels]
    lab = np.zeros((len(names), len(vox)), dtype=np.int64)
    for c, n in enumerate(names):
        p = grid.pixel[n][vox]
        ok = p >= 0
        lab[c, ok] = labels[n].reshape(-1)[p[ok]]
    best: tuple[float, int, np.ndarray] | None = None
    separating = 0
    for c in range(len(names)):
        counts = np.bincount(lab[c], minlength=2)
        counts[0] = 0
        total = counts.sum()
        if total == 0:
            continue
        big = np.nonzero(counts >= cfg.instance_share * total)[0]
        if len(big) < 2:
            continue
        separating += 1
        balance = float(np.sort(counts[big])[-2] / total)  # share of the second largest
        if best is None or balance > best[0]:
            best = (balance, c, big)
    if best is None or separating < cfg.min_views:
        return [vox]
    _, seed, big = best
    n_groups = len(big)
    group = np.full(len(vox), -1)
    for g, value in enumerate(big):
        group[lab[seed] == value] = g
    for _ in range(3):
        votes = np.zeros((len(vox), n_groups), dtype=np.int64)
        for c in range(len(names)):
            for value in np.unique(lab[c][lab[c] > 0]):
                members = lab[c] == value
                counts = np.bincount(group[members & (group >= 0)], minlength=n_groups)
                if counts.sum() and counts.max() >= 0.6 * counts.sum():
                    votes[members, counts.argmax()] += 1
        voted = votes.max(axis=1) > 0
        group = np.where(voted, votes.argmax(axis=1), -1)
    ground = grid.ground[vox]
    centres = [ground[group == g].mean(axis=0) for g in range(n_groups) if (group == g).any()]
    if len(centres) < 2:
        return [vox]
    centres = np.array(centres)
    kept = [g for g in range(n_groups) if (group == g).any()]
    remap = {g: i for i, g in enumerate(kept)}
    group = np.array([remap.get(int(g), -1) for g in group])
    rest = group < 0
    if rest.any():
        group[rest] = ((ground[rest, None, :] - centres[None]) ** 2).sum(-1).argmin(axis=1)
    return [vox[group == g] for g in range(len(kept))]


def merge_same_blobs(
    grid: VoxelGrid, cands: list[Person3D], strict: np.ndarray, labels: dict[str, np.ndarray]
) -> list[Person3D]:
    """Merge pieces that never appear apart: in (nearly) every camera that sees both, most of
    their voxels land on the same silhouette blob. Two people stand apart in some view;
    the pieces of one person with a ragged silhouette (a lunge, clothes matching the
    background) do not."""
    slack = grid.config.blob_merge_slack
    names = [n for n in grid.names if n in labels]

    def main_blobs(c: Person3D) -> dict[str, int]:
        out = {}
        for n in names:
            p = grid.pixel[n][c.core]
            lab = labels[n].reshape(-1)[p[p >= 0]]
            lab = lab[lab > 0]
            if len(lab):
                out[n] = int(np.bincount(lab).argmax())
        return out

    blobs = [main_blobs(c) for c in cands]
    merged = True
    while merged and len(cands) > 1:
        merged = False
        for a in range(len(cands)):
            for b in range(a + 1, len(cands)):
                both = [n for n in blobs[a] if n in blobs[b]]
                same = sum(1 for n in both if blobs[a][n] == blobs[b][n])
                if len(both) >= 2 and same >= max(2, len(both) - slack):
                    cands[a] = grid.person(
                        np.concatenate([cands[a].voxels, cands[b].voxels]), strict
                    )
                    blobs[a] = main_blobs(cands[a])
                    del cands[b], blobs[b]
                    merged = True
                    break
            if merged:
                break
    return cands


def merge_stacked(grid: VoxelGrid, cands: list[Person3D], strict: np.ndarray) -> list[Person3D]:
    """Merge candidates whose ground positions are closer than `merge_radius`."""
    limit = grid.config.merge_radius
    merged = True
    while merged and len(cands) > 1:
        merged = False
        for a in range(len(cands)):
            for b in range(a + 1, len(cands)):
                if np.linalg.norm(cands[a].ground - cands[b].ground) < limit:
                    cands[a] = grid.person(
                        np.concatenate([cands[a].voxels, cands[b].voxels]), strict
                    )
                    del cands[b]
                    merged = True
                    break
            if merged:
                break
    return cands

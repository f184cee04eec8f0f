"""Who owns which pixels: keep the candidates that explain the foreground (drop visual-hull
ghosts), then split each camera's foreground blobs or instances among the people, nearer person
first, with a crop box and a mask support per person and view. `associate_frame` runs the whole
per-frame association."""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage
from scipy.optimize import linear_sum_assignment

from gst.data.association.hull import FrameAssociation, Person3D, VoxelGrid
from gst.data.association.splitting import candidates

_MIN_INSTANCE_IOU = 0.1  # a footprint overlapping an instance less than this does not own it


def associate_frame(
    grid: VoxelGrid, labels: dict[str, np.ndarray], active: set[str] | None = None
) -> FrameAssociation:
    """People in one frame and, per camera, which pixels belong to whom."""
    occupied, strict = grid.occupancy(labels, active)
    persons = select(grid, candidates(grid, occupied, strict, labels), labels)
    result = FrameAssociation(persons)
    for name in grid.names:
        if name in labels:
            result.labels[name] = person_labels(grid, name, labels[name], persons)
            result.views[name] = person_views(grid, name, result.labels[name], persons)
    return result


def select(grid: VoxelGrid, cands: list[Person3D], labels: dict[str, np.ndarray]) -> list[Person3D]:
    """Keep the candidates that explain the foreground; drop visual-hull ghosts.

    Greedy cover: repeatedly accept the candidate that explains the most foreground not yet
    explained, as long as it explains a fair share of its own footprint anew in at least
    `min_views` cameras. A ghost lies where real people's viewing cones cross, so once the
    real people are accepted, it explains almost nothing new.
    """
    cfg = grid.config
    if cfg.instance_split:
        return select_instance_owners(grid, cands, labels)
    names = [n for n in grid.names if n in labels]
    fg = {n: labels[n] > 0 for n in names}
    feet = [{n: grid.footprint(n, c, labels[n].shape) & fg[n] for n in names} for c in cands]
    explained = {n: np.zeros(labels[n].shape, dtype=bool) for n in names}
    remaining = list(range(len(cands)))
    chosen = []
    while remaining:
        best, best_gain = None, 0
        for k in remaining:
            gains = []
            for n in names:
                own = np.count_nonzero(feet[k][n])
                new = np.count_nonzero(feet[k][n] & ~explained[n])
                min_px = cfg.min_mask_fraction * fg[n].size
                gains.append(new if (new >= cfg.new_fraction * own and new >= min_px) else 0)
            views = sum(1 for g in gains if g > 0)
            if views >= cfg.min_views and sum(gains) > best_gain:
                best, best_gain = k, sum(gains)
        if best is None:
            break
        chosen.append(best)
        remaining.remove(best)
        for n in names:
            explained[n] |= feet[best][n]
    return [cands[k] for k in sorted(chosen)]


def instance_scores(
    grid: VoxelGrid, name: str, labels: np.ndarray, cands: list[Person3D]
) -> np.ndarray:
    """(candidates, instances + 1) IoU of each candidate's footprint in camera `name` with
    each instance mask (column 0, the background, is 0). A person's footprint matches its
    own instance; a ghost (where two people's viewing cones cross) covers only parts of
    theirs, and a bigger region than either."""
    flat = labels.reshape(-1)
    n_inst = int(flat.max()) + 1
    areas = np.bincount(flat, minlength=n_inst)
    scores = np.zeros((len(cands), n_inst))
    for k, c in enumerate(cands):
        foot = grid.footprint(name, c, labels.shape).reshape(-1)
        inter = np.bincount(flat[foot], minlength=n_inst)
        scores[k] = inter / np.maximum(np.count_nonzero(foot) + areas - inter, 1)
    scores[:, 0] = 0
    return scores


def select_instance_owners(
    grid: VoxelGrid, cands: list[Person3D], labels: dict[str, np.ndarray]
) -> list[Person3D]:
    """With instance masks: keep the candidates that claim an instance in enough cameras.

    Greedy, best first: the candidate whose footprints overlap unclaimed instances most
    (summed IoU over cameras, each camera's best instance with IoU >= 0.1) claims those
    instances, provided it gets one in `min_views` cameras and in at least half of the
    cameras that see it. A ghost, where two people's viewing cones cross, matches parts of
    their instances; once the people have claimed them it is left with nothing.
    """
    names = [n for n in grid.names if n in labels]
    if not cands or not names:
        return []
    scores = {n: instance_scores(grid, n, labels[n], cands) for n in names}
    seeing = np.zeros(len(cands), dtype=np.int64)
    for n in names:
        for k, c in enumerate(cands):
            p = grid.pixel[n][c.core]
            seeing[k] += int(len(p) > 0 and np.mean(p >= 0) >= 0.5)
    need = np.maximum(grid.config.min_views, np.ceil(0.5 * seeing))
    free = {n: np.ones(scores[n].shape[1], dtype=bool) for n in names}
    remaining, chosen = list(range(len(cands))), []
    while remaining:
        best, best_total, best_claims = None, 0.0, {}
        for k in remaining:
            claims, total = {}, 0.0
            for n in names:
                row = np.where(free[n], scores[n][k], 0.0)
                j = int(row.argmax())
                if row[j] >= _MIN_INSTANCE_IOU:
                    claims[n], total = j, total + row[j]
            if len(claims) >= need[k] and total > best_total:
                best, best_total, best_claims = k, total, claims
        if best is None:
            break
        for n, j in best_claims.items():
            free[n][j] = False
        chosen.append(best)
        remaining.remove(best)
    return [cands[k] for k in sorted(chosen)]


def person_labels(
    grid: VoxelGrid, name: str, labels: np.ndarray, persons: list[Person3D]
) -> np.ndarray:
    """Split camera `name`'s foreground blobs among the people; returns a label image with
    value k + 1 for persons[k] (uint8, so at most 254 people)."""
    cfg = grid.config
    h, w = labels.shape
    out = np.zeros((h, w), dtype=np.uint8)
    if not persons:
        return out
    flat = labels.reshape(-1)
    n_blobs = int(flat.max()) + 1
    votes = np.zeros((len(persons), n_blobs), dtype=np.int64)
    proj = []
    for k, person in enumerate(persons):
        p = grid.pixel[name][person.core]
        p = p[p >= 0]
        proj.append(p)
        if len(p):
            votes[k] = np.bincount(flat[p], minlength=n_blobs)
    votes[:, 0] = 0
    cam = grid.cameras[name]
    depth = np.array([cam.to_camera(p.centroid)[0, 2] for p in persons])
    if cfg.instance_split:
        # A blob is one person's instance mask: it has one owner. One person, one instance
        # first (Hungarian on footprint IoU): someone half hidden behind another overlaps
        # the front person's instance too, yet their own sliver is theirs. Leftover
        # instances go to the person with the most core voxels on them.
        owner_of = np.full(n_blobs, -1)
        scores = instance_scores(grid, name, labels, persons)
        rows, cols = linear_sum_assignment(-scores[:, 1:])
        for k, b in zip(rows, cols + 1, strict=True):
            if scores[k, b] >= _MIN_INSTANCE_IOU:
                owner_of[b] = k
        for b in range(1, n_blobs):
            k = int(votes[:, b].argmax())
            # A leftover instance must be this person's too, not a neighbour (a bystander
            # nobody accepted) that a few edge voxels happen to land on.
            if owner_of[b] < 0 and votes[k, b] > 0 and scores[k, b] >= _MIN_INSTANCE_IOU:
                owner_of[b] = k
            if owner_of[b] >= 0:
                out[labels == b] = owner_of[b] + 1
        return drop_small_views(grid, out, len(persons))
    for b in range(1, n_blobs):
        top = votes[:, b].max()
        if top == 0:
            continue
        owners = np.nonzero(votes[:, b] >= max(1, cfg.owner_ratio * top))[0]
        blob = labels == b
        if len(owners) == 1:
            out[blob] = owners[0] + 1
            continue
        split_blob(grid, out, blob, owners, proj, depth, grid.focal[name])
    return drop_small_views(grid, out, len(persons))


def drop_small_views(grid: VoxelGrid, out: np.ndarray, n_persons: int) -> np.ndarray:
    """Unlabel people whose mask in this view is smaller than `min_mask_fraction`."""
    min_px = grid.config.min_mask_fraction * out.size
    for k in range(n_persons):
        if 0 < np.count_nonzero(out == k + 1) < min_px:
            out[out == k + 1] = 0
    return out


def person_views(
    grid: VoxelGrid, name: str, person_labels: np.ndarray, persons: list[Person3D]
) -> list[tuple[np.ndarray, float] | None]:
    """Per person seen in camera `name`: (box, support), else None.

    support = the share of the person's hull voxels (those within `box_radius` of its
    ground position) seen by this camera that land on its mask here. Every other camera
    agrees those voxels are occupied, so a low value means this view's mask is partial
    (someone standing still against the background model). box (x0, y0, x1, y1:
    work-image pixel edges counted from the image's top-left corner, i.e. pixel-centre
    coordinate + 0.5) is the mask's box, widened to cover the voxels' projections when
    support is below `partial_support`, so such a person is still cropped whole.
    """
    cfg = grid.config
    h, w = person_labels.shape
    r = grid.reach_px[name]
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)) if r > 0 else None
    out: list[tuple[np.ndarray, float] | None] = []
    for k, person in enumerate(persons):
        mask = person_labels == k + 1
        if not mask.any():
            out.append(None)
            continue
        near = np.linalg.norm(grid.ground[person.voxels] - person.ground, axis=1) <= cfg.box_radius
        p = grid.pixel[name][person.voxels[near]]
        p = p[p >= 0]
        reach = cv2.dilate(mask.view(np.uint8), disk) if disk is not None else mask.view(np.uint8)
        support = float(np.mean(reach.reshape(-1)[p] > 0)) if len(p) else float("nan")
        rows = np.nonzero(mask.any(axis=1))[0]
        cols = np.nonzero(mask.any(axis=0))[0]
        x0, y0, x1, y1 = cols[0], rows[0], cols[-1] + 1, rows[-1] + 1
        if len(p) and support < cfg.partial_support:
            pr, pc = p // w, p % w
            x0, y0 = min(x0, pc.min() - r), min(y0, pr.min() - r)
            x1, y1 = max(x1, pc.max() + 1 + r), max(y1, pr.max() + 1 + r)
        out.append(
            (
                np.array([max(0, x0), max(0, y0), min(w, x1), min(h, y1)], dtype=np.float64),
                support,
            )
        )
    return out


def split_blob(
    grid: VoxelGrid,
    out: np.ndarray,
    blob: np.ndarray,
    owners: np.ndarray,
    proj: list[np.ndarray],
    depth: np.ndarray,
    focal: float,
) -> None:
    """Share one blob among several people: paint each one's projected footprint, far to
    near (the nearer person occludes), then give leftover blob pixels to the nearest paint."""
    h, w = out.shape
    ys, xs = np.nonzero(blob)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    roi_blob = blob[y0:y1, x0:x1]
    paint = np.zeros(roi_blob.shape, dtype=np.uint8)
    for k in sorted(owners, key=lambda k: -depth[k]):
        p = proj[k]
        r, c = p // w - y0, p % w - x0
        ok = (r >= 0) & (r < y1 - y0) & (c >= 0) & (c < x1 - x0)
        dots = np.zeros_like(paint)
        dots[r[ok], c[ok]] = 1
        rad = max(1, int(round(0.75 * focal * grid.config.voxel_size / max(depth[k], 1e-3))))
        foot = cv2.dilate(
            dots, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1))
        )
        paint[(foot > 0) & roi_blob] = k + 1
    if not paint.any():
        return
    if (roi_blob & (paint == 0)).any():
        _, (ii, jj) = ndimage.distance_transform_edt(paint == 0, return_indices=True)
        paint = np.where(roi_blob, paint[ii, jj], 0).astype(np.uint8)
    region = out[y0:y1, x0:x1]
    region[roi_blob] = paint[roi_blob]

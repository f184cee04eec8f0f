"""Multi-view person association with a coarse visual hull, and ids that persist over time.

Per frame:
1. Every voxel of a grid over the capture volume is projected (once: the cameras are static)
   into every camera's foreground label image. A voxel is occupied when it lands on foreground
   in at least `min_views` cameras and in all but `max_misses` of the cameras that see it.
2. Occupied voxels form 3D connected components. People are roughly upright, so a component
   holding two people who touch is split at the peaks of its ground-plane density.
3. Each person's voxels are projected back: a 2D blob that only one person's voxels land in
   belongs to that person; a blob shared by several (one person occludes another) is split by
   their projected footprints, nearer person first.
4. `PersonTracker` matches people to the previous frame's by ground-plane distance (Hungarian),
   so ids stay the same over time.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage
from scipy.optimize import linear_sum_assignment

from calibration import Camera, Rig

_MIN_INSTANCE_IOU = 0.1  # a footprint overlapping an instance less than this does not own it


@dataclass(frozen=True)
class AssociationConfig:
    """Visual-hull association. Lengths in metres."""

    voxel_size: float = 0.08
    voxel_reach: float = 0.5  # foreground within this many voxel sizes of a voxel's centre counts
    min_views: int = 2  # a voxel must be foreground in at least this many cameras ...
    max_misses: int = 1  # ... and in all but this many of the cameras that see it
    min_person_volume: float = 0.02  # m^3 of occupied voxels
    min_person_height: float = 0.5  # vertical extent of a person's voxels
    merge_radius: float = 0.3  # pieces whose ground positions are closer are one person
    blob_merge_slack: int = 1  # pieces on the same blobs in all but this many shared views merge
    peak_separation: float = 0.45  # two people's ground-plane centres are at least this far apart
    peak_ratio: float = 0.35  # a second density peak counts if it is this fraction of the highest
    ground_sigma: float = 0.08  # smoothing of the ground-plane density
    min_mask_fraction: float = 0.0003  # smaller person masks (fraction of image) are not a view
    owner_ratio: float = 0.15  # a blob belongs to every person with >= this share of its top vote
    new_fraction: float = 0.3  # a person must explain this share of its footprint anew in a view
    box_radius: float = 1.0  # hull voxels this far (ground) from a person's centre are its own
    partial_support: float = (
        0.6  # below this mask support, crop boxes also cover the hull footprint
    )
    track_max_speed: float = 8.0  # m/s a person can move on the ground (a sprint is ~9)
    track_slack: float = 0.5  # m of centroid jitter tolerated on top (partial silhouettes move it)
    track_max_gap: int = 15  # processed frames a lost id is kept for re-identification
    min_track_frames: int = 5  # ids seen in fewer processed frames are dropped (flicker, fragments)
    # Offline linking of id fragments (`link_tracklets`): a track that starts after another
    # ended, where that one would have got to at `link_speed`, continues it.
    link_max_gap: int = 60  # processed frames between the end of one piece and the next
    link_speed: float = 2.0  # m/s: a person's typical displacement speed over a gap
    link_slack: float = 0.5  # m: centroid jitter tolerated on top
    # Masks are person instances (a learned segmenter): a hull component whose voxels land on
    # different instances in at least `min_views` cameras is split along them (pieces whose
    # ground centres end up closer than `merge_radius` are still merged back). Off for
    # background-subtraction blobs, where one body can be two blobs.
    instance_split: bool = False
    instance_share: float = (
        0.2  # an instance must hold this share of a component's voxels in a view
    )

    def __post_init__(self):
        if self.voxel_size <= 0:
            raise ValueError(f"voxel_size must be positive, got {self.voxel_size}")
        if self.min_views < 2:
            raise ValueError(
                f"min_views must be >= 2 (one view cannot place a person in 3D), got {self.min_views}"
            )
        if self.max_misses < 0:
            raise ValueError(f"max_misses must be >= 0, got {self.max_misses}")
        if not 0 < self.instance_share < 1:
            raise ValueError(f"instance_share must be in (0, 1), got {self.instance_share}")


@dataclass(frozen=True)
class CaptureVolume:
    """A box aligned with the ground: grid coordinates g = basis @ X_world, with basis rows
    (e1, e2, up); the box spans [lo, hi] in g."""

    basis: np.ndarray  # (3, 3)
    lo: np.ndarray  # (3,)
    hi: np.ndarray  # (3,)

    @staticmethod
    def ground_basis(up) -> np.ndarray:
        up = np.asarray(up, dtype=np.float64)
        up = up / np.linalg.norm(up)
        ref = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = ref - up * (ref @ up)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(up, e1)
        return np.stack([e1, e2, up])

    @classmethod
    def around(cls, center, half_extent, up=(0.0, 0.0, 1.0)) -> CaptureVolume:
        basis = cls.ground_basis(up)
        c = basis @ np.asarray(center, dtype=np.float64)
        h = np.broadcast_to(np.asarray(half_extent, dtype=np.float64), (3,))
        return cls(basis, c - h, c + h)

    @classmethod
    def from_rig(
        cls, rig: Rig, extent_factor: float = 0.8, half_height: float = 1.5
    ) -> CaptureVolume:
        """The region the cameras look at: a box around the point nearest to all optical axes,
        `extent_factor` times the median camera distance to it across the ground, and
        +-`half_height` metres along the up axis (cameras usually aim at people's middles)."""
        A = np.zeros((3, 3))
        b = np.zeros(3)
        for cam in rig:
            d = cam.optical_axis
            P = np.eye(3) - np.outer(d, d)
            A += P
            b += P @ cam.center
        if np.linalg.cond(A) > 1e8:
            raise ValueError(
                f"cameras {rig.names} have parallel optical axes; give the capture volume explicitly"
            )
        center = np.linalg.solve(A, b)
        dist = np.median([np.linalg.norm(cam.center - center) for cam in rig])
        r = extent_factor * dist
        return cls.around(center, (r, r, half_height), rig.up)


@dataclass
class Person3D:
    """One person found in one frame."""

    voxels: np.ndarray  # indices into the grid's kept voxels
    core: np.ndarray  # the voxels that all cameras seeing them agree on (no misses)
    centroid: np.ndarray  # (3,) world, metres
    ground: np.ndarray  # (2,) ground-plane position (grid e1, e2)
    height: float  # vertical extent of the voxels
    person_id: int = -1


@dataclass
class FrameAssociation:
    """Who is where in one frame: per camera a label image (0 = nobody, k + 1 = persons[k])
    and, per person, its crop box and mask support (see `VoxelGrid.person_views`)."""

    persons: list[Person3D]
    labels: dict[str, np.ndarray] = field(default_factory=dict)
    views: dict[str, list[tuple[np.ndarray, float] | None]] = field(default_factory=dict)


def project_fast(cam: Camera, world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project many points (float32 is fine) to distorted pixels; returns (uv, valid).

    The same model as `cv2.projectPoints` (radial k1..k6, tangential p1, p2, thin prism
    s1..s4; like OpenCV it ignores skew), vectorised in numpy, which is several times faster
    for the millions of voxel centres of a grid. Tilted-sensor models (14 terms) go through
    OpenCV. Points behind the camera or outside the image's field of view (where the
    polynomial folds back) are marked invalid.
    """
    world = np.asarray(world)
    pc = world @ cam.R.T.astype(world.dtype) + cam.t.astype(world.dtype)
    z = pc[:, 2]
    valid = z > 1e-3
    zs = np.where(valid, z, 1.0)
    x, y = pc[:, 0] / zs, pc[:, 1] / zs
    lo, hi = _normalised_bounds(cam)
    valid &= (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1])
    d = np.zeros(12)
    d[: min(12, cam.dist.size)] = cam.dist[:12]
    if cam.dist.size == 14:
        uv = np.full((len(world), 2), -1e9)
        uv[valid] = cam.project(world[valid].astype(np.float64))
        return uv, valid
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d
    r2 = x * x + y * y
    r4 = r2 * r2
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
    uv = np.stack([cam.fx * xd + cam.cx, cam.fy * yd + cam.cy], axis=1)
    return uv, valid


def _normalised_bounds(cam: Camera, margin: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Box around the undistorted normalised coordinates of the image border, widened by
    `margin` of its size (a conservative pinhole stand-in for the lens model)."""
    w, h = cam.width, cam.height
    t = np.linspace(0, 1, 33)
    border = np.concatenate(
        [
            np.stack([t * (w - 1), np.zeros_like(t)], 1),
            np.stack([t * (w - 1), np.full_like(t, h - 1)], 1),
            np.stack([np.zeros_like(t), t * (h - 1)], 1),
            np.stack([np.full_like(t, w - 1), t * (h - 1)], 1),
        ]
    )
    xy = cam.undistort_points(border)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    pad = margin * (hi - lo)
    return lo - pad, hi + pad


class VoxelGrid:
    """The capture volume as voxels, with each voxel's pixel in every camera's work image."""

    def __init__(
        self,
        cameras: list[Camera],
        work_sizes: dict[str, tuple[int, int]],
        volume: CaptureVolume,
        config: AssociationConfig,
    ):
        self.config = config
        self.volume = volume
        self.names = [c.name for c in cameras]
        self.cameras = {c.name: c for c in cameras}
        v = config.voxel_size
        self.dims = np.maximum(1, np.ceil((volume.hi - volume.lo) / v).astype(int))
        n_all = int(np.prod(self.dims))
        if n_all > 40_000_000:
            raise ValueError(
                f"capture volume {volume.hi - volume.lo} m at voxel {v} m has {n_all} voxels; "
                "use a larger voxel_size or a smaller volume"
            )
        ijk = np.indices(self.dims, dtype=np.int32).reshape(3, -1).T
        g = (volume.lo + (ijk + 0.5) * v).astype(np.float32)
        world = g @ volume.basis.astype(np.float32)  # basis is orthonormal: X = basis^T g
        self.work_sizes = dict(work_sizes)
        pix = {}
        focal = {}
        for cam in cameras:
            w, h = work_sizes[cam.name]
            sx, sy = w / cam.width, h / cam.height
            uv, ok = project_fast(cam, world)
            u = np.floor((uv[:, 0] + 0.5) * sx)
            r = np.floor((uv[:, 1] + 0.5) * sy)
            inside = ok & (u >= 0) & (u < w) & (r >= 0) & (r < h)
            u, r = (
                np.where(inside, u, 0),
                np.where(inside, r, 0),
            )  # points behind the camera project to NaN
            pix[cam.name] = np.where(inside, r.astype(np.int64) * w + u.astype(np.int64), -1)
            focal[cam.name] = cam.fx * sx
        seen = sum((p >= 0).astype(np.int16) for p in pix.values())
        keep = seen >= config.min_views
        self.kept = np.nonzero(keep)[0]  # flat grid index of each kept voxel
        self.ijk = ijk[keep]
        self.ground = g[keep, :2]
        self.up = g[keep, 2]
        self.world = world[keep]
        self.pixel = {n: p[keep].astype(np.int32) for n, p in pix.items()}
        self.focal = focal
        # Half the projected voxel size at the volume's middle: foreground that close to a
        # voxel's centre counts, so a coarse voxel is not lost to a thin or ragged silhouette.
        mid = (0.5 * (volume.lo + volume.hi)) @ volume.basis
        self.reach_px = {}
        for cam in cameras:
            depth = max(float(cam.to_camera(mid)[0, 2]), 0.5)
            self.reach_px[cam.name] = int(round(config.voxel_reach * focal[cam.name] * v / depth))

    def __len__(self) -> int:
        return len(self.kept)

    def occupancy(
        self, labels: dict[str, np.ndarray], active: set[str] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Occupancy of the kept voxels given per-camera label images (0 = background): the
        tolerant hull (up to `max_misses` cameras may disagree) and the strict one (none may).

        Cameras not in `active` (e.g. ones that never see anyone) neither vote nor veto.
        """
        cfg = self.config
        names = [n for n in self.names if (active is None or n in active) and n in labels]
        hits = np.zeros(len(self), dtype=np.int16)
        seen = np.zeros(len(self), dtype=np.int16)
        for name in names:
            p = self.pixel[name]
            vis = p >= 0
            fg = (labels[name] > 0).astype(np.uint8)
            r = self.reach_px[name]
            if r > 0:
                fg = cv2.dilate(
                    fg, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
                )
            hits += vis & (fg.reshape(-1)[np.where(vis, p, 0)] > 0)
            seen += vis
        enough = hits >= cfg.min_views
        return enough & (hits >= seen - cfg.max_misses), enough & (hits >= seen)

    def _split_component(self, vox: np.ndarray) -> list[np.ndarray]:
        """Split one 3D component into people at the peaks of its ground-plane density."""
        cfg = self.config
        v = cfg.voxel_size
        ij = self.ijk[vox, :2]
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

    def _person(self, vox: np.ndarray, strict: np.ndarray) -> Person3D:
        core = vox[strict[vox]]
        if len(core) < 0.2 * len(vox):  # too little agreement to trust: use everything
            core = vox
        up = self.up[vox]
        return Person3D(
            vox,
            core,
            self.world[core].mean(axis=0),
            self.ground[core].mean(axis=0),
            float(up.max() - up.min() + self.config.voxel_size),
        )

    def candidates(
        self,
        occupied: np.ndarray,
        strict: np.ndarray | None = None,
        labels: dict[str, np.ndarray] | None = None,
    ) -> list[Person3D]:
        """Person candidates among the occupied voxels: 3D components, split where several
        people touch, with pieces of one body merged back (pieces standing on one spot, and,
        given the `labels`, pieces that land on the same silhouettes in the cameras)."""
        cfg = self.config
        v = cfg.voxel_size
        strict = occupied if strict is None else strict
        grid = np.zeros(self.dims, dtype=bool)
        occ_idx = np.nonzero(occupied)[0]
        if len(occ_idx) == 0:
            return []
        grid.reshape(-1)[self.kept[occ_idx]] = True
        comp, n = ndimage.label(grid, structure=np.ones((3, 3, 3), dtype=bool))
        comp_of_kept = comp.reshape(-1)[self.kept[occ_idx]]
        order = np.argsort(comp_of_kept, kind="stable")
        bounds = np.searchsorted(comp_of_kept[order], np.arange(1, n + 2))
        out = []
        for k in range(n):
            vox = occ_idx[order[bounds[k] : bounds[k + 1]]]
            for part in self._split_component(vox):
                pieces = (
                    self._split_by_instances(part, labels)
                    if cfg.instance_split and labels
                    else [part]
                )
                out.extend(self._person(piece, strict) for piece in pieces)
        out = self._merge_stacked(out, strict)
        if labels is not None:
            out = self._merge_same_blobs(out, strict, labels)
        return [
            p
            for p in out
            if len(p.voxels) * v**3 >= cfg.min_person_volume and p.height >= cfg.min_person_height
        ]

    def _split_by_instances(
        self, vox: np.ndarray, labels: dict[str, np.ndarray]
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
        cfg = self.config
        names = [n for n in self.names if n in labels]
        lab = np.zeros((len(names), len(vox)), dtype=np.int64)
        for c, n in enumerate(names):
            p = self.pixel[n][vox]
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
        ground = self.ground[vox]
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

    def _merge_same_blobs(
        self, cands: list[Person3D], strict: np.ndarray, labels: dict[str, np.ndarray]
    ) -> list[Person3D]:
        """Merge pieces that never appear apart: in (nearly) every camera that sees both, most of
        their voxels land on the same silhouette blob. Two people stand apart in some view;
        the pieces of one person with a ragged silhouette (a lunge, clothes matching the
        background) do not."""
        slack = self.config.blob_merge_slack
        names = [n for n in self.names if n in labels]

        def main_blobs(c: Person3D) -> dict[str, int]:
            out = {}
            for n in names:
                p = self.pixel[n][c.core]
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
                        cands[a] = self._person(
                            np.concatenate([cands[a].voxels, cands[b].voxels]), strict
                        )
                        blobs[a] = main_blobs(cands[a])
                        del cands[b], blobs[b]
                        merged = True
                        break
                if merged:
                    break
        return cands

    def _merge_stacked(self, cands: list[Person3D], strict: np.ndarray) -> list[Person3D]:
        """Merge candidates whose ground positions are closer than `merge_radius`."""
        limit = self.config.merge_radius
        merged = True
        while merged and len(cands) > 1:
            merged = False
            for a in range(len(cands)):
                for b in range(a + 1, len(cands)):
                    if np.linalg.norm(cands[a].ground - cands[b].ground) < limit:
                        cands[a] = self._person(
                            np.concatenate([cands[a].voxels, cands[b].voxels]), strict
                        )
                        del cands[b]
                        merged = True
                        break
                if merged:
                    break
        return cands

    def footprint(
        self, name: str, person: Person3D, shape: tuple[int, int], voxels: np.ndarray | None = None
    ) -> np.ndarray:
        """Where a person's voxels (its core by default) land in camera `name` (boolean image),
        each voxel drawn as a disc about its projected size."""
        h, w = shape
        p = self.pixel[name][person.core if voxels is None else voxels]
        p = p[p >= 0]
        img = np.zeros((h, w), dtype=np.uint8)
        if len(p) == 0:
            return img.astype(bool)
        img.reshape(-1)[p] = 1
        depth = max(float(self.cameras[name].to_camera(person.centroid)[0, 2]), 1e-3)
        rad = max(1, int(round(0.6 * self.focal[name] * self.config.voxel_size / depth)))
        r, c = p // w, p % w
        y0, y1 = max(0, r.min() - rad), min(h, r.max() + rad + 1)
        x0, x1 = max(0, c.min() - rad), min(w, c.max() + rad + 1)
        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1))
        img[y0:y1, x0:x1] = cv2.dilate(img[y0:y1, x0:x1], disk)
        return img.astype(bool)

    def select(self, cands: list[Person3D], labels: dict[str, np.ndarray]) -> list[Person3D]:
        """Keep the candidates that explain the foreground; drop visual-hull ghosts.

        Greedy cover: repeatedly accept the candidate that explains the most foreground not yet
        explained, as long as it explains a fair share of its own footprint anew in at least
        `min_views` cameras. A ghost lies where real people's viewing cones cross, so once the
        real people are accepted, it explains almost nothing new.
        """
        cfg = self.config
        if cfg.instance_split:
            return self._select_instance_owners(cands, labels)
        names = [n for n in self.names if n in labels]
        fg = {n: labels[n] > 0 for n in names}
        feet = [{n: self.footprint(n, c, labels[n].shape) & fg[n] for n in names} for c in cands]
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

    def _instance_scores(self, name: str, labels: np.ndarray, cands: list[Person3D]) -> np.ndarray:
        """(candidates, instances + 1) IoU of each candidate's footprint in camera `name` with
        each instance mask (column 0, the background, is 0). A person's footprint matches its
        own instance; a ghost (where two people's viewing cones cross) covers only parts of
        theirs, and a bigger region than either."""
        flat = labels.reshape(-1)
        n_inst = int(flat.max()) + 1
        areas = np.bincount(flat, minlength=n_inst)
        scores = np.zeros((len(cands), n_inst))
        for k, c in enumerate(cands):
            foot = self.footprint(name, c, labels.shape).reshape(-1)
            inter = np.bincount(flat[foot], minlength=n_inst)
            scores[k] = inter / np.maximum(np.count_nonzero(foot) + areas - inter, 1)
        scores[:, 0] = 0
        return scores

    def _select_instance_owners(
        self, cands: list[Person3D], labels: dict[str, np.ndarray]
    ) -> list[Person3D]:
        """With instance masks: keep the candidates that claim an instance in enough cameras.

        Greedy, best first: the candidate whose footprints overlap unclaimed instances most
        (summed IoU over cameras, each camera's best instance with IoU >= 0.1) claims those
        instances, provided it gets one in `min_views` cameras and in at least half of the
        cameras that see it. A ghost, where two people's viewing cones cross, matches parts of
        their instances; once the people have claimed them it is left with nothing.
        """
        names = [n for n in self.names if n in labels]
        if not cands or not names:
            return []
        scores = {n: self._instance_scores(n, labels[n], cands) for n in names}
        seeing = np.zeros(len(cands), dtype=np.int64)
        for n in names:
            for k, c in enumerate(cands):
                p = self.pixel[n][c.core]
                seeing[k] += int(len(p) > 0 and np.mean(p >= 0) >= 0.5)
        need = np.maximum(self.config.min_views, np.ceil(0.5 * seeing))
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

    def person_labels(self, name: str, labels: np.ndarray, persons: list[Person3D]) -> np.ndarray:
        """Split camera `name`'s foreground blobs among the people; returns a label image with
        value k + 1 for persons[k] (uint8, so at most 254 people)."""
        cfg = self.config
        h, w = labels.shape
        out = np.zeros((h, w), dtype=np.uint8)
        if not persons:
            return out
        flat = labels.reshape(-1)
        n_blobs = int(flat.max()) + 1
        votes = np.zeros((len(persons), n_blobs), dtype=np.int64)
        proj = []
        for k, person in enumerate(persons):
            p = self.pixel[name][person.core]
            p = p[p >= 0]
            proj.append(p)
            if len(p):
                votes[k] = np.bincount(flat[p], minlength=n_blobs)
        votes[:, 0] = 0
        cam = self.cameras[name]
        depth = np.array([cam.to_camera(p.centroid)[0, 2] for p in persons])
        if cfg.instance_split:
            # A blob is one person's instance mask: it has one owner. One person, one instance
            # first (Hungarian on footprint IoU): someone half hidden behind another overlaps
            # the front person's instance too, yet their own sliver is theirs. Leftover
            # instances go to the person with the most core voxels on them.
            owner_of = np.full(n_blobs, -1)
            scores = self._instance_scores(name, labels, persons)
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
            return self._drop_small_views(out, len(persons))
        for b in range(1, n_blobs):
            top = votes[:, b].max()
            if top == 0:
                continue
            owners = np.nonzero(votes[:, b] >= max(1, cfg.owner_ratio * top))[0]
            blob = labels == b
            if len(owners) == 1:
                out[blob] = owners[0] + 1
                continue
            self._split_blob(out, blob, owners, proj, depth, self.focal[name])
        return self._drop_small_views(out, len(persons))

    def _drop_small_views(self, out: np.ndarray, n_persons: int) -> np.ndarray:
        """Unlabel people whose mask in this view is smaller than `min_mask_fraction`."""
        min_px = self.config.min_mask_fraction * out.size
        for k in range(n_persons):
            if 0 < np.count_nonzero(out == k + 1) < min_px:
                out[out == k + 1] = 0
        return out

    def person_views(
        self, name: str, person_labels: np.ndarray, persons: list[Person3D]
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
        cfg = self.config
        h, w = person_labels.shape
        r = self.reach_px[name]
        disk = (
            cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)) if r > 0 else None
        )
        out: list[tuple[np.ndarray, float] | None] = []
        for k, person in enumerate(persons):
            mask = person_labels == k + 1
            if not mask.any():
                out.append(None)
                continue
            near = (
                np.linalg.norm(self.ground[person.voxels] - person.ground, axis=1) <= cfg.box_radius
            )
            p = self.pixel[name][person.voxels[near]]
            p = p[p >= 0]
            reach = (
                cv2.dilate(mask.view(np.uint8), disk) if disk is not None else mask.view(np.uint8)
            )
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

    def _split_blob(
        self,
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
            rad = max(1, int(round(0.75 * focal * self.config.voxel_size / max(depth[k], 1e-3))))
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

    def associate(
        self, labels: dict[str, np.ndarray], active: set[str] | None = None
    ) -> FrameAssociation:
        """People in one frame and, per camera, which pixels belong to whom."""
        occupied, strict = self.occupancy(labels, active)
        persons = self.select(self.candidates(occupied, strict, labels), labels)
        result = FrameAssociation(persons)
        for name in self.names:
            if name in labels:
                result.labels[name] = self.person_labels(name, labels[name], persons)
                result.views[name] = self.person_views(name, result.labels[name], persons)
        return result


class PersonTracker:
    """Keeps person ids stable over time by matching ground-plane positions (Hungarian).

    A person may move `max_speed * step_seconds` per step plus `slack` (silhouettes that are
    partial in some frames make the centroid jitter); ids unseen for `max_gap` steps retire.
    """

    def __init__(
        self,
        max_speed: float = 8.0,
        step_seconds: float = 1 / 30,
        slack: float = 0.3,
        max_gap: int = 15,
        first_id: int = 1,
    ):
        self.max_speed = max_speed
        self.step_seconds = step_seconds
        self.slack = slack
        self.max_gap = max_gap
        self.next_id = first_id
        self.tracks: dict[int, tuple[np.ndarray, int]] = {}  # id -> (ground position, last step)
        self.step = 0

    def update(self, persons: list[Person3D]) -> list[int]:
        """Assign ids to this step's persons (also stored in `person.person_id`)."""
        self.step += 1
        self.tracks = {i: t for i, t in self.tracks.items() if self.step - t[1] <= self.max_gap + 1}
        ids = [-1] * len(persons)
        track_ids = list(self.tracks)
        if persons and track_ids:
            pos = np.array([p.ground for p in persons])
            tpos = np.array([self.tracks[i][0] for i in track_ids])
            gap = np.array([self.step - self.tracks[i][1] for i in track_ids], dtype=float)
            cost = np.linalg.norm(pos[:, None] - tpos[None], axis=-1)
            allowed = cost <= self.slack + self.max_speed * self.step_seconds * gap[None]
            # Between two tracks in reach, prefer the one seen most recently, so a stale
            # duplicate does not steal the id back and forth.
            cost = cost + 0.1 * (gap[None] - 1)
            rows, cols = linear_sum_assignment(np.where(allowed, cost, 1e6))
            for r, c in zip(rows, cols, strict=True):
                if allowed[r, c]:
                    ids[r] = track_ids[c]
        for k, person in enumerate(persons):
            if ids[k] < 0:
                ids[k] = self.next_id
                self.next_id += 1
            person.person_id = ids[k]
            self.tracks[ids[k]] = (person.ground.copy(), self.step)
        # A track not seen this step but sitting where someone was just seen is a stale
        # duplicate of that person (a fragment that got its own id): retire it, or the two ids
        # would take turns on the same person.
        fresh = [t[0] for t in self.tracks.values() if t[1] == self.step]
        for i in [i for i, t in self.tracks.items() if t[1] < self.step]:
            if any(np.linalg.norm(self.tracks[i][0] - f) <= self.slack for f in fresh):
                del self.tracks[i]
        return ids


def link_tracklets(
    tracks: dict[int, list[tuple[int, np.ndarray]]],
    step_seconds: float,
    speed: float,
    slack: float,
    max_gap: int,
    agree: float = 0.8,
) -> dict[int, int]:
    """Join id fragments of one person, offline: returns old id -> linked id.

    `tracks` maps an id to its (step, ground position) observations. Pieces are visited in
    order of their first step. A piece joins the earlier chain it never shares a step with and
    agrees with: for at least `agree` of its observations, the chain's observation nearest in
    time is at most `max_gap` steps away and within `slack + speed * gap * step_seconds` on the
    ground. Among agreeing chains the nearest (median distance) wins. This joins a person who
    was lost and found again, and ids that took turns on one person (interleaved pieces), but
    never two people seen together. Chains keep the id of their first piece.
    """
    order = sorted(tracks, key=lambda i: (min(o[0] for o in tracks[i]), i))
    chains: list[tuple[int, np.ndarray, np.ndarray]] = []  # (id, steps sorted, positions)
    mapping: dict[int, int] = {}
    for i in order:
        obs = sorted(tracks[i], key=lambda o: o[0])
        steps = np.array([o[0] for o in obs])
        pos = np.stack([np.asarray(o[1], dtype=np.float64) for o in obs])
        best, best_d = None, np.inf
        for k, (_, c_steps, c_pos) in enumerate(chains):
            if np.isin(steps, c_steps).any():
                continue
            j = np.clip(np.searchsorted(c_steps, steps), 1, len(c_steps)) - 1
            j2 = np.minimum(j + 1, len(c_steps) - 1)
            near = np.where(np.abs(c_steps[j2] - steps) < np.abs(c_steps[j] - steps), j2, j)
            gap = np.abs(c_steps[near] - steps)
            d = np.linalg.norm(pos - c_pos[near], axis=1)
            ok = (gap <= max_gap) & (d <= slack + speed * gap * step_seconds)
            if ok.mean() >= agree and np.median(d) < best_d:
                best, best_d = k, float(np.median(d))
        if best is None:
            chains.append((i, steps, pos))
            mapping[i] = i
            continue
        cid, c_steps, c_pos = chains[best]
        merged = np.argsort(np.concatenate([c_steps, steps]), kind="stable")
        chains[best] = (
            cid,
            np.concatenate([c_steps, steps])[merged],
            np.concatenate([c_pos, pos])[merged],
        )
        mapping[i] = cid
    return mapping

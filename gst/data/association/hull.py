"""Visual hull over a voxel grid: settings, people found in one frame, and the grid itself.

Every voxel of a grid over the capture volume is projected (once: the cameras are static) into
every camera's work image. A voxel is occupied when it lands on foreground in at least
`min_views` cameras and in all but `max_misses` of the cameras that see it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from calibration import Camera
from gst.data.association.volume import CaptureVolume, project_fast


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
                "min_views must be >= 2 (one view cannot place a person in 3D), "
                f"got {self.min_views}"
            )
        if self.max_misses < 0:
            raise ValueError(f"max_misses must be >= 0, got {self.max_misses}")
        if not 0 < self.instance_share < 1:
            raise ValueError(f"instance_share must be in (0, 1), got {self.instance_share}")


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

    def person(self, vox: np.ndarray, strict: np.ndarray) -> Person3D:
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

"""CPU mesh renderer: Embree ray casting of posed bodies inside an analytic room.

Rays go through the *undistorted* direction of every pixel (OpenCV's undistortPoints on pixel
centres), so any world point projected with `Camera.project` through the same calibration lands
on the pixel whose ray hits it, lens distortion included. Outputs per view: linear radiance, an
exact person-id mask (pixel centres, 0 = background) and camera-z depth in metres.

The room behind the people is static per camera, so it is rendered once (supersampled); each
frame only casts rays inside the people's bounding box in undistorted image coordinates, plus
soft-shadow rays toward an area light. People's silhouettes and the calibration board are
antialiased with n x n samples per pixel, whose directions are interpolated from the undistorted
pixel-corner grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration import Camera
from synth.appearance import BodyAtlas, Outfit, albedo, srgb_to_linear
from synth.board import BoardPose, BoardTexture, ChArUcoSpec
from synth.sampling import sample_image
from synth.stage import Stage


@dataclass(frozen=True)
class RenderOptions:
    """Quality knobs. `antialias` n gives n x n samples on silhouette and board pixels."""

    antialias: int = 2
    background_samples: int = 2
    shadow_samples: int = 4
    backend: str = "embree"  # "embree" or "trimesh" (see RayCaster)
    roi: bool = True  # cast primary rays only inside the people's bounding box (False: every pixel)

    def __post_init__(self):
        for name in ("antialias", "background_samples", "shadow_samples"):
            v = getattr(self, name)
            if not 1 <= v <= 8:
                raise ValueError(f"RenderOptions.{name} must be in 1..8, got {v}")
        if self.backend not in ("embree", "trimesh"):
            raise ValueError(
                f"RenderOptions.backend must be 'embree' or 'trimesh', got {self.backend!r}"
            )


@dataclass(frozen=True)
class PosedPerson:
    """One person in one frame: world mesh, its vertex normals and its look."""

    person_id: int  # mask value, 1..255
    vertices: np.ndarray  # (V, 3) float32
    normals: np.ndarray  # (V, 3) float32, unit
    faces: np.ndarray  # (F, 3) int32
    atlas: BodyAtlas
    outfit: Outfit


@dataclass
class Layers:
    """Rendered view: linear radiance (H, W, 3) float32, mask (H, W) uint8, depth (H, W) float32."""

    radiance: np.ndarray
    mask: np.ndarray
    depth: np.ndarray


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals for (..., V, 3) vertices (vectorised over leading axes)."""
    v = np.asarray(vertices, dtype=np.float32)
    tri = v[..., faces, :]  # (..., F, 3, 3)
    fn = np.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :])
    out = np.zeros_like(v)
    for k in range(3):
        idx = faces[:, k]
        for c in range(3):
            out[..., c] += _scatter_sum(fn[..., c], idx, v.shape[-2])
    n = np.linalg.norm(out, axis=-1, keepdims=True)
    return out / np.maximum(n, 1e-12)


def _scatter_sum(values: np.ndarray, idx: np.ndarray, n: int) -> np.ndarray:
    flat = values.reshape(-1, values.shape[-1])
    out = np.stack([np.bincount(idx, weights=row, minlength=n) for row in flat])
    return out.reshape(values.shape[:-1] + (n,)).astype(np.float32)


# ------------------------------------------------------------------------------------------------
# Ray casting backends


@dataclass(frozen=True)
class RayHits:
    """Nearest hits of N rays (`RayCaster.cast`): geom (N,) int32 mesh index (-1 = miss), prim
    (N,) int32 triangle of that mesh, u, v (N,) float32 barycentric of vertices 1 and 2, t (N,)
    float32 distance along the unit direction (inf on a miss)."""

    geom: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray
    t: np.ndarray

    def select(self, keep: np.ndarray) -> RayHits:
        """The hits of the rays `keep` selects (a boolean mask or indices)."""
        return RayHits(self.geom[keep], self.prim[keep], self.u[keep], self.v[keep], self.t[keep])


class RayCaster:
    """Nearest-hit ray casting against a list of meshes (one geometry id per mesh).

    Backends: "embree" calls embreex directly (barycentrics and distances come back from
    Embree); "trimesh" goes through trimesh's default intersector (Embree via
    trimesh.ray.ray_pyembree when embreex is installed), which recomputes hit points and
    barycentrics in numpy (slower; kept for comparison and as a fallback).
    """

    def __init__(self, meshes: list[tuple[np.ndarray, np.ndarray]], backend: str = "embree"):
        if backend not in ("embree", "trimesh"):
            raise ValueError(f"ray casting backend must be 'embree' or 'trimesh', got {backend!r}")
        self.backend = backend
        self.meshes = [
            (np.ascontiguousarray(v, dtype=np.float32), np.ascontiguousarray(f, dtype=np.int32))
            for v, f in meshes
        ]
        if backend == "embree":
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh

            self._scene = rtcore_scene.EmbreeScene()
            for v, f in self.meshes:
                TriangleMesh(self._scene, v, f)
            return
        import trimesh

        self._offsets = np.cumsum([0] + [len(f) for _, f in self.meshes])
        verts, faces, off = [], [], 0
        for v, f in self.meshes:
            verts.append(v.astype(np.float64))
            faces.append(f + off)
            off += len(v)
        self._mesh = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)
        self._tm = self._mesh.ray

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> RayHits:
        """Nearest hits (`RayHits`: geom (N,) (-1 = miss), prim (N,), u, v (barycentric of
        vertices 1 and 2) and t (distance along the unit direction, inf on a miss))."""
        n = len(dirs)
        out = RayHits(
            geom=np.full(n, -1, np.int32),
            prim=np.full(n, -1, np.int32),
            u=np.zeros(n, np.float32),
            v=np.zeros(n, np.float32),
            t=np.full(n, np.inf, np.float32),
        )
        if n == 0 or not self.meshes:
            return out
        o = np.ascontiguousarray(np.broadcast_to(origins, dirs.shape), dtype=np.float32)
        d = np.ascontiguousarray(dirs, dtype=np.float32)
        if self.backend == "embree":
            r = self._scene.run(o, d, output=1)
            geom = np.where(r["primID"] >= 0, r["geomID"], -1).astype(np.int32)
            return RayHits(
                geom=geom,
                prim=r["primID"].astype(np.int32),
                u=r["u"],
                v=r["v"],
                t=np.where(geom >= 0, r["tfar"], np.inf).astype(np.float32),
            )
        import trimesh

        o64, d64 = o.astype(np.float64), d.astype(np.float64)
        loc, ray, tri = self._tm.intersects_location(o64, d64, multiple_hits=False)
        if len(ray):
            # Keep the nearest hit per ray (guards against intersectors returning several).
            dist = np.linalg.norm(loc - o64[ray], axis=1)
            order = np.lexsort((dist, ray))
            first = order[np.r_[True, ray[order][1:] != ray[order][:-1]]]
            loc, ray, tri, dist = loc[first], ray[first], tri[first], dist[first]
            g = np.searchsorted(self._offsets, tri, side="right") - 1
            bary = trimesh.triangles.points_to_barycentric(self._mesh.triangles[tri], loc)
            out.geom[ray] = g
            out.prim[ray] = tri - self._offsets[g]
            out.u[ray], out.v[ray] = bary[:, 1], bary[:, 2]
            out.t[ray] = dist
        return out

    def occluded(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """True where a ray hits any mesh."""
        return self.cast(origins, dirs).geom >= 0


# ------------------------------------------------------------------------------------------------
# Floor shadows, shared by all cameras of a frame


@dataclass(frozen=True)
class FloorShadowMap:
    """Radiance factor (1 = fully lit) of the floor around one person, on a grid of cells
    `cell` metres wide starting at `origin` (x, y of the first cell centre)."""

    origin: tuple[float, float]
    cell: float
    factor: np.ndarray  # (ny, nx) float32

    def factor_at(self, xy: np.ndarray) -> np.ndarray:
        """Bilinear factor at world floor points (N, 2); 1 outside the map."""
        out = np.ones(len(xy), np.float32)
        ny, nx = self.factor.shape
        u = (xy[:, 0] - self.origin[0]) / self.cell
        v = (xy[:, 1] - self.origin[1]) / self.cell
        inside = (u > -1) & (u < nx) & (v > -1) & (v < ny)
        if inside.any():
            out[inside] = sample_image(
                self.factor, u[inside], v[inside], border=cv2.BORDER_CONSTANT, value=1.0
            )
        return out


def floor_shadow_maps(
    people: list[PosedPerson], caster: RayCaster, stage: Stage, samples: int, cell: float = 0.015
) -> list[FloorShadowMap]:
    """Soft shadows on the floor: shadow rays from a grid over each person's footprint (their
    bounding box swept along every light sample) toward the area light's samples."""
    lights = stage.light.samples(samples)
    lights = lights[lights[:, 2] > 1e-3]
    if len(lights) == 0:
        return []
    lz = lights[:, 2]
    full = stage.light.ambient + stage.light.key * lz.mean()
    maps = []
    for person in people:
        lo = person.vertices.min(0).astype(np.float64) - 0.05
        hi = person.vertices.max(0).astype(np.float64) + 0.05
        box = np.array(
            [
                [x, y, z]
                for x in (lo[0], hi[0])
                for y in (lo[1], hi[1])
                for z in (max(lo[2], 0.0), hi[2])
            ]
        )
        feet = np.concatenate([box[:, :2] - ld[None, :2] * (box[:, 2:3] / ld[2]) for ld in lights])
        flo, fhi = feet.min(0), feet.max(0)
        nx, ny = (
            int(np.ceil((fhi[0] - flo[0]) / cell)) + 1,
            int(np.ceil((fhi[1] - flo[1]) / cell)) + 1,
        )
        gx, gy = np.meshgrid(flo[0] + cell * np.arange(nx), flo[1] + cell * np.arange(ny))
        pts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, 1e-3)], -1)
        k = len(lights)
        occ = caster.occluded(np.repeat(pts, k, axis=0), np.tile(lights, (len(pts), 1))).reshape(
            -1, k
        )
        lit = stage.light.ambient + stage.light.key * ((~occ) * lz[None]).mean(1)
        maps.append(
            FloorShadowMap(
                (float(flo[0]), float(flo[1])),
                cell,
                (lit / full).reshape(ny, nx).astype(np.float32),
            )
        )
    return maps


# ------------------------------------------------------------------------------------------------
# Per-camera renderer


def _pixel_grids(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates of pixel centres (H*W, 2) and pixel corners
    ((H+1)*(W+1), 2). Pixel (u, v) covers [u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]."""
    w, h = camera.width, camera.height
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    centres = camera.undistort_points(np.stack([uu.ravel(), vv.ravel()], -1))
    uc, vc = np.meshgrid(
        np.arange(w + 1, dtype=np.float64) - 0.5, np.arange(h + 1, dtype=np.float64) - 0.5
    )
    corners = camera.undistort_points(np.stack([uc.ravel(), vc.ravel()], -1))
    return centres.astype(np.float32), corners.astype(np.float32)


def _dot3(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise dot of (N, 3) with a 3-vector, without BLAS."""
    return a[:, 0] * v[0] + a[:, 1] * v[1] + a[:, 2] * v[2]


def _subpixel_offsets(n: int) -> np.ndarray:
    """(n*n, 2) sample positions inside a pixel, fractions in (0, 1) from its top-left corner."""
    s = (np.arange(n) + 0.5) / n
    fx, fy = np.meshgrid(s, s)
    return np.stack([fx.ravel(), fy.ravel()], -1)


class ViewRenderer:
    """Renders one camera. Caches the camera's rays and the static room."""

    def __init__(self, camera: Camera, stage: Stage, options: RenderOptions = RenderOptions()):
        if not stage.contains(camera.center[None])[0]:
            raise ValueError(
                f"camera '{camera.name}' at {camera.center.round(2).tolist()} is outside the stage "
                f"box (+-{stage.half_x} x +-{stage.half_y} x {stage.height} m)"
            )
        self.camera, self.stage, self.options = camera, stage, options
        self.h, self.w = camera.height, camera.width
        self.origin = camera.center.astype(np.float64)
        self._Rf = camera.R.astype(np.float32)
        self.xy, self.corners = _pixel_grids(camera)
        self.light_dirs = stage.light.samples(options.shadow_samples)
        self._body_lights = stage.light.samples(max(1, options.shadow_samples // 2))
        self.zfac = (1.0 / np.sqrt(1.0 + (self.xy.astype(np.float64) ** 2).sum(1))).astype(
            np.float32
        )
        dirs = self.dirs_from_xy(self.xy)
        t, surf, _ = stage.intersect(self.origin, dirs)
        self.bg_points = (self.origin + dirs * t[:, None]).astype(np.float32)
        self.bg_depth = (t * self.zfac).astype(np.float32)
        self.bg_floor = surf == 0
        self._floor_idx = np.flatnonzero(self.bg_floor)
        self._floor_xy = self.bg_points[self._floor_idx, :2].copy()
        self.bg_radiance = self._background(options.background_samples).astype(np.float32)

    # -- rays -----------------------------------------------------------------------------------
    def dirs_from_xy(self, xy: np.ndarray) -> np.ndarray:
        """World unit directions (N, 3) for undistorted normalised coordinates (N, 2)."""
        # R^T (x, y, 1) / norm, written out: BLAS on (N, 3) x (3, 3) is slow and contends
        # for threads on a loaded machine.
        x, y = xy[:, 0:1].astype(np.float32), xy[:, 1:2].astype(np.float32)
        R = self._Rf
        d = x * R[0] + y * R[1] + R[2]
        d *= 1.0 / np.sqrt(1.0 + x * x + y * y)
        return d

    def subpixel_xy(self, pixels: np.ndarray, n: int) -> np.ndarray:
        """Undistorted coordinates (len(pixels) * n*n, 2) of n x n samples in each flat pixel
        index, bilinear between the pixel's undistorted corners."""
        rows, cols = np.divmod(pixels, self.w)
        W1 = self.w + 1
        c00 = self.corners[rows * W1 + cols]
        c01 = self.corners[rows * W1 + cols + 1]
        c10 = self.corners[(rows + 1) * W1 + cols]
        c11 = self.corners[(rows + 1) * W1 + cols + 1]
        f = _subpixel_offsets(n).astype(np.float32)
        fx, fy = f[None, :, 0:1], f[None, :, 1:2]
        xy = (1 - fy) * ((1 - fx) * c00[:, None] + fx * c01[:, None]) + fy * (
            (1 - fx) * c10[:, None] + fx * c11[:, None]
        )
        return xy.reshape(-1, 2)

    # -- static room ----------------------------------------------------------------------------
    def _background(self, n: int) -> np.ndarray:
        out = np.zeros((self.h * self.w, 3))
        chunk = max(1, 400_000 // (n * n))
        for s in range(0, self.h * self.w, chunk):
            pix = np.arange(s, min(self.h * self.w, s + chunk))
            xy = self.subpixel_xy(pix, n) if n > 1 else self.xy[pix]
            d = self.dirs_from_xy(xy)
            t, surf, normal = self.stage.intersect(self.origin, d)
            p = self.origin + d * t[:, None]
            amb, direct = self.stage.shade(self.stage.albedo(p, surf), normal, self.light_dirs)
            out[pix] = (amb + direct).reshape(len(pix), n * n, 3).mean(1)
        return out

    # -- people ---------------------------------------------------------------------------------
    def _roi(self, vertices: np.ndarray) -> np.ndarray:
        """Flat pixel indices whose ray may hit the given world points' convex hull."""
        cam = self.camera.to_camera(vertices)
        if not self.options.roi or cam[:, 2].min() < 0.05:
            return np.arange(self.h * self.w)
        xy = cam[:, :2] / cam[:, 2:3]
        margin = 2.0 / self.camera.fx
        lo, hi = xy.min(0) - margin, xy.max(0) + margin
        sel = (
            (self.xy[:, 0] >= lo[0])
            & (self.xy[:, 0] <= hi[0])
            & (self.xy[:, 1] >= lo[1])
            & (self.xy[:, 1] <= hi[1])
        )
        return np.flatnonzero(sel)

    def _shade_hits(
        self, hits: RayHits, dirs: np.ndarray, people: list[PosedPerson], caster: RayCaster
    ) -> np.ndarray:
        """Radiance (N, 3) of person hits (all entries of `hits` must be hits)."""
        n = len(dirs)
        rgb = np.zeros((n, 3))
        normal = np.zeros((n, 3))
        bary = np.stack([1 - hits.u - hits.v, hits.u, hits.v], -1).astype(np.float64)
        for g, person in enumerate(people):
            sel = hits.geom == g
            if not sel.any():
                continue
            tri = person.faces[hits.prim[sel]]
            nrm = (person.normals[tri] * bary[sel][..., None]).sum(1)
            normal[sel] = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            rgb[sel] = albedo(person.outfit, person.atlas, tri, bary[sel])
        # Face the viewer: interpolated normals can point away at silhouettes.
        flip = (normal * dirs).sum(1) > 0
        normal[flip] *= -1
        points = self.origin + dirs * hits.t[:, None].astype(np.float64)
        # Half the light samples on bodies: self-shadows are small and seen up close less often.
        lights = self._body_lights
        # Surfaces facing away from a light sample are unlit by it: no shadow ray needed.
        facing = (
            normal[:, 0:1] * lights[:, 0]
            + normal[:, 1:2] * lights[:, 1]
            + normal[:, 2:3] * lights[:, 2]
        ) > 0
        vis = self._visibility(points + normal * 2e-3, caster, lights, facing)
        amb, direct = self.stage.shade(rgb, normal, lights, vis)
        return amb + direct

    def _visibility(
        self,
        points: np.ndarray,
        caster: RayCaster,
        light_dirs: np.ndarray,
        needed: np.ndarray | None = None,
    ) -> np.ndarray:
        """(N, len(light_dirs)) 1 where the light sample is not blocked by a person; only the
        (point, light) pairs in `needed` are traced, the others are reported visible."""
        k = len(light_dirs)
        needed = np.ones((len(points), k), bool) if needed is None else needed
        pi, li = np.nonzero(needed)
        vis = np.ones((len(points), k))
        vis[pi, li] = ~caster.occluded(points[pi], light_dirs[li])
        return vis

    def _floor_shadows(
        self, shadows: list[FloorShadowMap], covered: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Floor pixels (flat ids) in the people's shadows and their radiance factor."""
        xy = self._floor_xy
        factor = np.ones(len(xy), np.float32)
        for sm in shadows:
            factor = np.minimum(factor, sm.factor_at(xy))
        keep = (factor < 0.999) & ~covered[self._floor_idx]
        return self._floor_idx[keep], factor[keep]

    def render_people(
        self,
        people: list[PosedPerson],
        caster: RayCaster | None = None,
        shadows: list[FloorShadowMap] | None = None,
    ) -> Layers:
        """Render the room with `people`. `caster` (their meshes, same order) and `shadows`
        (their floor shadow maps) are per frame and can be shared by all cameras."""
        npx = self.h * self.w
        radiance = self.bg_radiance.copy()
        mask = np.zeros(npx, np.uint8)
        depth = self.bg_depth.copy()
        if not people:
            return Layers(
                radiance.reshape(self.h, self.w, 3),
                mask.reshape(self.h, self.w),
                depth.reshape(self.h, self.w),
            )
        if caster is None:
            caster = RayCaster([(p.vertices, p.faces) for p in people], self.options.backend)
        if shadows is None:
            shadows = floor_shadow_maps(people, caster, self.stage, self.options.shadow_samples)
        roi = self._roi(np.concatenate([p.vertices for p in people]))
        dirs = self.dirs_from_xy(self.xy[roi])
        hits = caster.cast(self.origin[None], dirs)
        hit = (hits.geom >= 0) & (hits.t * self.zfac[roi] < self.bg_depth[roi])
        pix = roi[hit]
        h_sel = hits.select(hit)
        ids = np.array([p.person_id for p in people], np.uint8)
        mask[pix] = ids[h_sel.geom]
        depth[pix] = h_sel.t * self.zfac[pix]
        radiance[pix] = self._shade_hits(h_sel, dirs[hit], people, caster)
        covered = mask > 0
        sh_idx, sh_factor = self._floor_shadows(shadows, covered)
        radiance[sh_idx] *= sh_factor[:, None]
        if self.options.antialias > 1:
            self._antialias_edges(radiance, mask, people, caster, sh_idx, sh_factor)
        return Layers(
            radiance.reshape(self.h, self.w, 3),
            mask.reshape(self.h, self.w),
            depth.reshape(self.h, self.w),
        )

    def _antialias_edges(self, radiance, mask, people, caster, sh_idx, sh_factor) -> None:
        """Supersample pixels on a silhouette (any id change among the 4-neighbours)."""
        m = mask.reshape(self.h, self.w)
        edge = np.zeros_like(m, dtype=bool)
        edge[:, 1:] |= m[:, 1:] != m[:, :-1]
        edge[:, :-1] |= m[:, 1:] != m[:, :-1]
        edge[1:] |= m[1:] != m[:-1]
        edge[:-1] |= m[1:] != m[:-1]
        pix = np.flatnonzero(edge)
        if len(pix) == 0:
            return
        n = self.options.antialias
        xy = self.subpixel_xy(pix, n)
        dirs = self.dirs_from_xy(xy)
        hits = caster.cast(self.origin[None], dirs)
        owner = np.repeat(pix, n * n)
        bg_depth = self.bg_depth[owner]
        zf = np.repeat(self.zfac[pix], n * n)
        hit = (hits.geom >= 0) & (hits.t * zf < bg_depth)
        # Misses show the room as the pixel centre sees it (with its shadow).
        bg = self.bg_radiance[owner].astype(np.float64)
        shadow = np.ones(self.h * self.w)
        shadow[sh_idx] = sh_factor
        bg *= shadow[owner][:, None]
        samples = bg
        if hit.any():
            samples[hit] = self._shade_hits(hits.select(hit), dirs[hit], people, caster)
        radiance[pix] = samples.reshape(len(pix), n * n, 3).mean(1)

    # -- calibration board ----------------------------------------------------------------------
    def render_board(self, spec: ChArUcoSpec, pose: BoardPose, texture: BoardTexture) -> Layers:
        """Render the room with the board (no people). Mask is 1 on board pixels. Pixels on the
        board's outline or on a contrast edge of the print get n x n samples."""
        npx = self.h * self.w
        radiance = self.bg_radiance.copy()
        mask = np.zeros(npx, np.uint8)
        depth = self.bg_depth.copy()
        W, H = spec.size
        m = texture.margin
        outline = pose.to_world(
            np.array([[-m, -m, 0], [W + m, -m, 0], [-m, H + m, 0], [W + m, H + m, 0]])
        )
        roi = self._roi(outline)
        hit, t, colour = self._board_hits(spec, pose, texture, self.dirs_from_xy(self.xy[roi]))
        hit &= t * self.zfac[roi] < self.bg_depth[roi]
        pix = roi[hit]
        mask[pix] = 1
        depth[pix] = t[hit] * self.zfac[pix]
        radiance[pix] = colour[hit]
        n = self.options.antialias
        if n > 1 and len(pix):
            lum = radiance.reshape(self.h, self.w, 3).sum(-1)
            mk = mask.reshape(self.h, self.w)
            edge = np.zeros((self.h, self.w), bool)
            dx = (np.abs(lum[:, 1:] - lum[:, :-1]) > 0.03) | (mk[:, 1:] != mk[:, :-1])
            dy = (np.abs(lum[1:] - lum[:-1]) > 0.03) | (mk[1:] != mk[:-1])
            edge[:, 1:] |= dx
            edge[:, :-1] |= dx
            edge[1:] |= dy
            edge[:-1] |= dy
            edge &= cv2.dilate(mk, np.ones((3, 3), np.uint8)).astype(bool)  # only near the board
            sel = roi[edge.ravel()[roi]]
            dirs = self.dirs_from_xy(self.subpixel_xy(sel, n))
            owner = np.repeat(sel, n * n)
            s_hit, s_t, s_col = self._board_hits(spec, pose, texture, dirs)
            s_hit &= s_t * self.zfac[owner] < self.bg_depth[owner]
            samples = self.bg_radiance[owner].astype(np.float64)
            samples[s_hit] = s_col[s_hit]
            radiance[sel] = samples.reshape(len(sel), n * n, 3).mean(1)
        return Layers(
            radiance.reshape(self.h, self.w, 3),
            mask.reshape(self.h, self.w),
            depth.reshape(self.h, self.w),
        )

    def _board_hits(
        self,
        spec: ChArUcoSpec,
        pose: BoardPose,
        texture: BoardTexture,
        dirs: np.ndarray,
        colour: bool = True,
    ):
        """Ray-board intersection: hit (N,), distance (N,), radiance (N, 3)."""
        z = pose.R[:, 2]
        denom = _dot3(dirs, z)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = float((pose.t - self.origin) @ z) / denom
        rel = (self.origin - pose.t) + dirs * t[:, None]
        b = np.stack([_dot3(rel, pose.R[:, 0]), _dot3(rel, pose.R[:, 1])], -1)  # board coordinates
        W, H = spec.size
        m = texture.margin
        hit = (
            (np.abs(denom) > 1e-9)
            & (t > 0)
            & (b[:, 0] >= -m)
            & (b[:, 0] <= W + m)
            & (b[:, 1] >= -m)
            & (b[:, 1] <= H + m)
        )
        if not colour:
            return hit, t, None
        front = denom > 0  # travelling along +z: entering through the printed (-z) side
        rgb = np.zeros((len(dirs), 3))
        u, v = texture.pixel_coords(b[:, 0], b[:, 1])
        sel = hit & front
        if sel.any():
            val = (
                sample_image(texture.image, u[sel], v[sel], border=cv2.BORDER_REPLICATE).astype(
                    np.float64
                )
                / 255.0
            )
            alb = 0.03 + 0.82 * srgb_to_linear(val[:, None] * 255.0)
            rgb[sel] = alb
        back = hit & ~front
        rgb[back] = srgb_to_linear((90, 80, 70))
        normal = np.where(front[:, None], -z[None], z[None])
        amb, direct = self.stage.shade(rgb, normal, self.light_dirs)
        # Boards are matte paper; keep some light even when the key light is behind.
        return hit, t, amb + direct + 0.15 * rgb

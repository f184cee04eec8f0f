"""Joint bundle adjustment of a camera rig and board poses with pycolmap.

COLMAP's rig model fits board calibration exactly: the cameras are the sensors of one rig
(`sensor_from_rig` fixed over time, unknown), each board pose is a frame with its own
`rig_from_world`, where "world" is the board, and the board corners are 3D points whose
coordinates are known and held constant. One bundle adjustment refines every camera's
intrinsics and distortion, every camera's pose in the rig and every board pose. Observations
with large residuals are then dropped and the adjustment repeated until none are left, at most
`max_outlier_rounds` times.

COLMAP puts the centre of the top-left pixel at (0.5, 0.5), OpenCV at (0, 0): pixel
coordinates and principal points are shifted by 0.5 going in and out.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np
import pycolmap

from calibration.errors import CalibrationError
from calibration.intrinsics import LENS_MODELS


class BundleAdjustmentError(CalibrationError):
    """The bundle adjustment could not run or produced an unusable result."""


@dataclass(frozen=True)
class BAOptions:
    """Bundle adjustment settings.

    `loss` in {'trivial', 'huber', 'soft_l1', 'cauchy'}, scale in px.
    """

    loss: str = "cauchy"
    loss_scale_px: float = 1.0
    refine_principal_point: bool = True
    refine_distortion: bool = True
    max_iterations: int = 100
    outlier_sigmas: float = 4.0  # drop residuals above this many robust sigmas...
    min_outlier_px: float = 1.0  # ...but never below this many pixels
    max_outlier_rounds: int = 4
    num_threads: int = -1
    linear_solver: str | None = None  # a Ceres LinearSolverType name; None: COLMAP chooses


@dataclass
class CameraState:
    """One camera in the adjustment: OpenCV intrinsics and its pose in the rig."""

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    cam_from_rig: np.ndarray  # 4x4


@dataclass
class BAResult:
    cameras: dict[str, CameraState]
    rig_from_board: dict[int, np.ndarray]  # frame -> 4x4
    residuals: dict[str, np.ndarray]  # camera -> (N,) px, final inlier observations
    observations: dict[str, np.ndarray]  # camera -> (N, 2) px of those observations
    outliers: dict[str, np.ndarray]  # camera -> (M, 2) px of observations removed as outliers
    rounds: list[dict] = field(
        default_factory=list
    )  # per round: observations, rms, removed, seconds, termination (Ceres')

    def rms_px(self) -> dict[str, float]:
        return {
            c: float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")
            for c, r in self.residuals.items()
        }


def _rigid(T: np.ndarray) -> pycolmap.Rigid3d:
    return pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3])


def _matrix(r: pycolmap.Rigid3d) -> np.ndarray:
    T = np.eye(4)
    T[:3, :4] = r.matrix()
    return T


def _colmap_params(K: np.ndarray, dist: np.ndarray, lens_model: str) -> list[float]:
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5
    d = np.zeros(8)
    d[: min(len(dist), 8)] = dist[:8]
    n = LENS_MODELS[lens_model][1]
    return [fx, fy, cx, cy] + d[:n].tolist()


def _opencv_intrinsics(params: np.ndarray, lens_model: str) -> tuple[np.ndarray, np.ndarray]:
    fx, fy, cx, cy = params[:4]
    K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1.0]])
    extra = np.asarray(params[4:], dtype=np.float64)
    dist = (
        extra if lens_model == "full_opencv" else np.concatenate([extra, np.zeros(5 - len(extra))])
    )
    return K, dist


class BoardBundleAdjuster:
    """Builds the pycolmap reconstruction once, then adjusts and prunes it in rounds."""

    def __init__(
        self,
        cameras: dict[str, CameraState],
        reference: str,
        rig_from_board: dict[int, np.ndarray],
        object_points: np.ndarray,
        observations: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]],
        lens_model: str = "opencv",
        options: BAOptions | None = None,
    ):
        """`observations[camera][frame] = (corner ids, (M, 2) OpenCV pixels)`; every camera's
        `cam_from_rig` is relative to `reference` (whose own is the identity)."""
        self.options = options or BAOptions()
        self.lens_model = lens_model
        self.names = list(cameras)
        self.cam_id = {n: i + 1 for i, n in enumerate(self.names)}
        self.rec = rec = pycolmap.Reconstruction()
        model_name = LENS_MODELS[lens_model][0]
        for n, c in cameras.items():
            rec.add_camera(
                pycolmap.Camera(
                    model=model_name,
                    width=c.width,
                    height=c.height,
                    params=_colmap_params(c.K, c.dist, lens_model),
                    camera_id=self.cam_id[n],
                )
            )
        rig = pycolmap.Rig(rig_id=1)
        rig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, self.cam_id[reference]))
        for n, c in cameras.items():
            if n != reference:
                rig.add_sensor(
                    pycolmap.sensor_t(pycolmap.SensorType.CAMERA, self.cam_id[n]),
                    _rigid(c.cam_from_rig),
                )
        rec.add_rig(rig)

        # Images: one per (camera, frame) view; a frame groups the views of one board pose.
        frame_images: dict[int, list[tuple[int, str]]] = {}
        self.image_key: dict[int, tuple[str, int]] = {}
        self.image_obs: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # corner ids, OpenCV px
        self.alive: dict[int, np.ndarray] = {}  # observations in the adjustment
        self.removed: dict[int, np.ndarray] = {}  # observations removed as outliers
        self.object_points = np.asarray(object_points, dtype=np.float64)
        image_id = 0
        tracks: dict[int, list[tuple[int, int]]] = {}
        image_points: dict[int, np.ndarray] = {}
        for n in self.names:
            for f, (ids, px) in sorted(observations.get(n, {}).items()):
                if f not in rig_from_board:
                    continue
                image_id += 1
                self.image_key[image_id] = (n, f)
                frame_images.setdefault(f, []).append((image_id, n))
                image_points[image_id] = np.asarray(px, dtype=np.float64) + 0.5
                self.image_obs[image_id] = (
                    np.asarray(ids, dtype=np.int64).ravel(),
                    np.asarray(px, dtype=np.float64).reshape(-1, 2),
                )
                self.alive[image_id] = np.ones(len(self.image_obs[image_id][0]), dtype=bool)
                self.removed[image_id] = np.zeros(len(self.image_obs[image_id][0]), dtype=bool)
                for k, cid in enumerate(np.asarray(ids).ravel()):
                    tracks.setdefault(int(cid), []).append((image_id, k))
        self.frame_ids = {}
        for k, f in enumerate(sorted(frame_images)):
            frame = pycolmap.Frame(
                frame_id=k + 1, rig_id=1, rig_from_world=_rigid(rig_from_board[f])
            )
            for iid, n in frame_images[f]:
                frame.add_data_id(
                    pycolmap.data_t(
                        pycolmap.sensor_t(pycolmap.SensorType.CAMERA, self.cam_id[n]), iid
                    )
                )
            rec.add_frame(frame)
            self.frame_ids[f] = k + 1
        for f, images in frame_images.items():
            for iid, n in images:
                img = pycolmap.Image(
                    name=f"{n}/{f:06d}",
                    keypoints=image_points[iid],
                    camera_id=self.cam_id[n],
                    image_id=iid,
                )
                img.frame_id = self.frame_ids[f]
                rec.add_image(img)
        for fid in self.frame_ids.values():
            rec.register_frame(fid)
        self.point_ids: list[int] = []
        self.point_of: dict[tuple[int, int], int] = {}  # (image, observation) -> its 3D point
        for cid, elems in sorted(tracks.items()):
            if len(elems) < 2:  # COLMAP's adjuster takes no track of one: not adjusted
                for iid, k in elems:
                    self.alive[iid][k] = False
                continue
            track = pycolmap.Track()
            for iid, k in elems:
                track.add_element(iid, k)
            pid = rec.add_point3D(object_points[cid], track)
            self.point_ids.append(pid)
            for iid, k in elems:
                self.point_of[(iid, k)] = pid
        self.reference = reference
        if not self.point_ids:
            raise BundleAdjustmentError("no board observations to adjust")

    # -- solving --------------------------------------------------------------------------------
    def _options(self) -> pycolmap.BundleAdjustmentOptions:
        o = self.options
        opts = pycolmap.BundleAdjustmentOptions()
        opts.refine_focal_length = True
        opts.refine_principal_point = o.refine_principal_point
        opts.refine_extra_params = o.refine_distortion and self.lens_model != "pinhole"
        opts.refine_rig_from_world = True
        opts.refine_sensor_from_rig = True
        opts.refine_points3D = False
        opts.print_summary = False
        opts.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, o.loss.upper())
        opts.ceres.loss_function_scale = o.loss_scale_px
        opts.ceres.solver_options.max_num_iterations = o.max_iterations
        opts.ceres.solver_options.num_threads = o.num_threads
        if o.linear_solver is not None:
            solver_types = type(opts.ceres.solver_options.linear_solver_type).__members__
            if o.linear_solver not in solver_types:
                raise BundleAdjustmentError(
                    f"linear solver '{o.linear_solver}' is unknown, expected one "
                    f"of {sorted(solver_types)}"
                )
            opts.ceres.auto_select_solver_type = False
            opts.ceres.solver_options.linear_solver_type = solver_types[o.linear_solver]
        return opts

    def _config(self) -> pycolmap.BundleAdjustmentConfig:
        config = pycolmap.BundleAdjustmentConfig()
        for iid in self.rec.reg_image_ids():
            config.add_image(iid)
        for pid in self.rec.point3D_ids():
            config.add_constant_point(pid)  # board geometry is known
        return config

    def solve_once(self) -> pycolmap.BundleAdjustmentSummary:
        adjuster = pycolmap.create_default_bundle_adjuster(
            self._options(), self._config(), self.rec
        )
        summary = adjuster.solve()
        if not summary.is_solution_usable():
            raise BundleAdjustmentError(f"bundle adjustment failed: {summary.brief_report()}")
        return summary

    def _camera_opencv(self, camera_id: int) -> tuple[np.ndarray, np.ndarray]:
        return _opencv_intrinsics(np.asarray(self.rec.camera(camera_id).params), self.lens_model)

    def residuals(self) -> dict[int, np.ndarray]:
        """Per image: reprojection error (px) of each observation (inf behind the camera, NaN
        where removed), computed with OpenCV from the current state (vectorised per image)."""
        out = {}
        intr = {cid: self._camera_opencv(cid) for cid in self.cam_id.values()}
        for iid, (ids, px) in self.image_obs.items():
            img = self.rec.image(iid)
            T = img.cam_from_world().matrix()
            K, dist = intr[img.camera_id]
            pts = self.object_points[ids]
            err = np.full(len(ids), np.nan)
            alive = self.alive[iid]
            if alive.any():
                depth = pts[alive] @ T[2, :3] + T[2, 3]
                proj, _ = cv2.projectPoints(
                    pts[alive], cv2.Rodrigues(T[:, :3])[0], T[:, 3], K, dist
                )
                e = np.linalg.norm(proj.reshape(-1, 2) - px[alive], axis=1)
                err[alive] = np.where(depth > 0, e, np.inf)
            out[iid] = err
        return out

    def _remove(self, iid: int, idx: int) -> int:
        """Take one observation out of the adjustment; returns 1. COLMAP deletes the whole 3D
        point with the observation when its track had two elements: the other observation then
        leaves the adjustment too, and is marked so (else it was still counted in the residuals
        and the RMS, and deleting it later failed on the missing point)."""
        self.alive[iid][idx] = False
        self.removed[iid][idx] = True
        pid = self.point_of.pop((iid, idx), None)
        if pid is None or not self.rec.exists_point3D(pid):
            return 1
        partners = [
            (e.image_id, e.point2D_idx)
            for e in self.rec.point3D(pid).track.elements
            if (e.image_id, e.point2D_idx) != (iid, idx)
        ]
        self.rec.delete_observation(iid, idx)
        if not self.rec.exists_point3D(pid):
            for other in partners:
                self.alive[other[0]][other[1]] = False
                self.point_of.pop(other, None)
        return 1

    def run(self) -> list[dict]:
        """Adjust, drop outliers, repeat. Returns per-round statistics."""
        o = self.options
        rounds = []
        for k in range(o.max_outlier_rounds + 1):
            t0 = time.perf_counter()
            summary = self.solve_once()
            res = self.residuals()
            err = np.concatenate([e[self.alive[i]] for i, e in res.items()])
            finite = err[np.isfinite(err)]
            # Each camera's own noise sets its limit: one limit from every camera's residuals
            # cut a noisier camera's good corners (56 % of a 1 px camera's among 0.2 px ones)
            # and biased its focal length.
            limits = {}
            for name in self.names:
                own = [e[self.alive[i]] for i, e in res.items() if self.image_key[i][0] == name]
                own = np.concatenate(own) if own else np.zeros(0)
                own = own[np.isfinite(own)]
                sigma = float(np.median(own)) / np.sqrt(2 * np.log(2)) if len(own) else 0.0
                limits[name] = float(max(o.outlier_sigmas * sigma, o.min_outlier_px))  # Rayleigh
            last = k == o.max_outlier_rounds
            removed = 0
            if not last:
                for iid, e in res.items():
                    limit = limits[self.image_key[iid][0]]
                    for idx in np.flatnonzero(self.alive[iid] & ~(e <= limit)):
                        removed += self._remove(iid, int(idx))
            rounds.append(
                {
                    "round": k,
                    "observations": len(err),
                    "rms_px": float(np.sqrt(np.mean(finite**2))),
                    "limit_px": max(limits.values()),
                    "limit_px_by_camera": limits,
                    "removed": removed,
                    "seconds": time.perf_counter() - t0,
                    # NO_CONVERGENCE (the iteration limit) is "usable" to Ceres: said in the notes
                    "termination": summary.termination_type.name,
                }
            )
            if not removed:
                break
        return rounds

    # -- results --------------------------------------------------------------------------------
    def result(self, rounds: list[dict]) -> BAResult:
        rec = self.rec
        cams: dict[str, CameraState] = {}
        rig = rec.rig(1)
        for n in self.names:
            c = rec.camera(self.cam_id[n])
            K, dist = self._camera_opencv(self.cam_id[n])
            sensor = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, self.cam_id[n])
            T = np.eye(4) if n == self.reference else _matrix(rig.sensor_from_rig(sensor))
            cams[n] = CameraState(n, c.width, c.height, K, dist, T)
        frames = {f: _matrix(rec.frame(fid).rig_from_world) for f, fid in self.frame_ids.items()}
        res = self.residuals()
        residuals = {n: [] for n in self.names}
        obs = {n: [] for n in self.names}
        outliers = {n: [] for n in self.names}
        for iid, err in res.items():
            n = self.image_key[iid][0]
            px, alive = self.image_obs[iid][1], self.alive[iid]
            residuals[n].append(err[alive])
            obs[n].append(px[alive])
            outliers[n].append(px[self.removed[iid]])  # not: corners COLMAP could not adjust

        def cat(parts, shape):
            return np.concatenate(parts).reshape(shape) if parts else np.zeros(shape)

        return BAResult(
            cams,
            frames,
            {n: cat(v, (-1,)) for n, v in residuals.items()},
            {n: cat(v, (-1, 2)) for n, v in obs.items()},
            {n: cat(v, (-1, 2)) for n, v in outliers.items()},
            rounds,
        )


def reprojection_errors(
    K: np.ndarray,
    dist: np.ndarray,
    cam_from_board: np.ndarray,
    object_points: np.ndarray,
    pixels: np.ndarray,
) -> np.ndarray:
    """Per-point reprojection error (px) of board points under a pose, through OpenCV."""
    rvec = cv2.Rodrigues(cam_from_board[:3, :3])[0]
    proj, _ = cv2.projectPoints(object_points, rvec, cam_from_board[:3, 3], K, dist)
    return np.linalg.norm(proj.reshape(-1, 2) - pixels, axis=1)

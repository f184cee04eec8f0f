"""Calibrate a camera rig from board footage: detection, intrinsics, pose graph, bundle adjustment,
world frame.

World frame with `floor_world=True`: the board pose in `floor_frame` (by default the first frame
in which any camera found the board) is taken to lie flat on the floor, printed face up. The
world origin is that board's origin (its top-left outer corner as printed), x runs along the
board's rows, z points up out of the floor and y completes a right-handed frame; floor z = 0,
units are metres (scale from `BoardSpec.square_size`). With `floor_world=False` the world is the
first camera's frame (and `Rig.up` is that camera's -y, a guess).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from calibration.board import (
    BoardSpec,
    CameraDetections,
    FrameDetection,
    detect_in_sources,
    spans_plane,
)
from calibration.bundle import BAOptions, BAResult, BoardBundleAdjuster, CameraState
from calibration.camera import Camera, Rig
from calibration.checks import lens_findings
from calibration.errors import CalibrationError
from calibration.intrinsics import (
    LENS_MODELS,
    IntrinsicsError,
    board_pose,
    calibrate_intrinsics,
)
from calibration.posegraph import (
    chain_poses,
    invert,
    pairwise_edges,
    robust_mean_pose,
)

log = logging.getLogger(__name__)

# Board axes expressed in the floor world: x stays, y and z flip (board z points into the floor).
WORLD_FROM_FLOOR_BOARD_AXES = np.diag([1.0, -1.0, -1.0])

Progress = Callable[[str, int, int], None]

__all__ = [
    "BoardCalibration",
    "CalibrationError",
    "InitialSolution",
    "SolveOptions",
    "bundle_adjust",
    "calibrate_from_board",
    "calibrate_from_detections",
    "finish_calibration",
    "initialise_from_detections",
]


@dataclass(frozen=True)
class SolveOptions:
    """Knobs of the board calibration (defaults suit ChArUco boards and ordinary lenses)."""

    lens_model: str = "opencv"  # 'pinhole', 'opencv' (k1 k2 p1 p2) or 'full_opencv' (rational)
    min_corners: int = 6  # fewer corners in a view: the view is ignored
    max_intrinsic_views: int = 40  # views per camera for the initial cv2.calibrateCamera
    view_outlier_px: float = 3.0  # initial PnP: corners off by more (and 3x the camera's RMS) are
    # left out of that view's pose; a view still above it after that is dropped
    min_sharpness_ratio: float = 0.2  # blurred detections (vs the camera's median) are dropped
    ba: BAOptions = field(default_factory=BAOptions)


@dataclass
class BoardCalibration:
    """Result of a board calibration, with everything the report shows."""

    rig: Rig
    board: BoardSpec
    rms_px: dict[str, float]  # final per-camera reprojection RMS over inlier observations
    detections: dict[str, int]  # frames with a usable board detection, per camera
    detected_frames: dict[str, list[int]]  # those frames' indices
    frames_searched: dict[str, int]
    image_sizes: dict[str, tuple[int, int]]
    observations: dict[str, np.ndarray]  # (N, 2) px: inlier corners in the final adjustment
    residuals_px: dict[str, np.ndarray]  # (N,) reprojection error of those observations
    outliers: dict[str, np.ndarray]  # (M, 2) px: corners removed as outliers
    initial_rms_px: dict[str, float]  # per-camera RMS of the single-camera calibration
    world_from_board: dict[int, np.ndarray]  # frame -> 4x4 board pose in the world
    floor_frame: int | None
    timings: dict[str, float]  # seconds per step; 'bundle_adjustment' is the whole BA
    ba_rounds: list[dict]
    notes: list[str] = field(default_factory=list)
    # cameras that saw the board in fewer than MIN_ORIENTATIONS distinct orientations: their
    # intrinsics and pose are poorly determined (camera -> distinct orientations)
    weak_cameras: dict[str, int] = field(default_factory=dict)
    # cameras that lost more than MAX_OUTLIER_SHARE of their corners as outliers, most often
    # frames out of step with the others (camera -> share removed)
    suspect_cameras: dict[str, float] = field(default_factory=dict)

    @property
    def rms_px_overall(self) -> float:
        """RMS (px) over every camera's kept residuals; NaN when none is left (np.concatenate
        of nothing raised)."""
        parts = [v for v in self.residuals_px.values() if len(v)]
        if not parts:
            return float("nan")
        r = np.concatenate(parts)
        return float(np.sqrt(np.mean(r**2)))


def _clean(det: FrameDetection, board: BoardSpec, min_corners: int) -> FrameDetection | None:
    ids, uv = det.ids, det.corners
    ok = (ids >= 0) & (ids < board.n_corners) & np.all(np.isfinite(uv), axis=1)
    ids, uv = ids[ok], uv[ok]
    ids, first = np.unique(ids, return_index=True)  # a corner reported twice: keep the first
    uv = uv[first]
    if len(ids) < min_corners or not spans_plane(board.object_points()[ids, :2]):
        return None
    return FrameDetection(det.frame, ids, uv, det.sharpness)


# how far (px) a detected corner may lie beyond its image's outer edge (subpixel refinement)
CORNER_SLACK_PX = 1.0


def _check_image_size(
    name: str, size: tuple[int, int], detections: Sequence[FrameDetection]
) -> None:
    """CalibrationError where a detected corner lies outside the image of `size` (width,
    height): the size is wrong, most often given as (height, width), numpy's shape order. The
    rig was solved and written with its width and height swapped, without a word."""
    if not detections:
        return
    w, h = (int(v) for v in size)
    uv = np.concatenate([d.corners for d in detections])
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    if np.any(lo < -0.5 - CORNER_SLACK_PX) or np.any(hi > np.array([w, h]) - 0.5 + CORNER_SLACK_PX):
        raise CalibrationError(
            f"camera '{name}': board corners were found out to ({hi[0]:.0f}, {hi[1]:.0f}) px "
            f"(from ({lo[0]:.0f}, {lo[1]:.0f})), outside its given image size {w}x{h}; image "
            "sizes are (width, height), not an image's shape (height, width)"
        )


@dataclass
class InitialSolution:
    """Everything bundle adjustment starts from: cleaned detections, per-camera intrinsics,
    camera poses in the rig (relative to `reference`) and board poses in the rig."""

    names: list[str]
    board: BoardSpec
    detections: dict[str, list[FrameDetection]]
    frames_searched: dict[str, int]
    cameras: dict[str, CameraState]
    reference: str
    rig_from_board: dict[int, np.ndarray]
    observations: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]]
    initial_rms_px: dict[str, float]
    timings: dict[str, float]


def initialise_from_detections(
    detections: Mapping[str, Sequence[FrameDetection] | CameraDetections],
    image_sizes: Mapping[str, tuple[int, int]],
    board: BoardSpec,
    *,
    frames_searched: Mapping[str, int] | None = None,
    options: SolveOptions | None = None,
    progress: Progress | None = None,
) -> InitialSolution:
    """Steps before bundle adjustment: per-camera intrinsics (cv2.calibrateCamera, outlier
    views rejected), per-view board poses (robust PnP), camera poses from the pose graph and
    board poses in the rig. Raises CalibrationError / PoseGraphError naming cameras that never
    saw the board or share no frame with the others."""
    opts = options or SolveOptions()
    if opts.lens_model not in LENS_MODELS:
        raise CalibrationError(
            f"lens model '{opts.lens_model}' is unknown, expected one of {sorted(LENS_MODELS)}"
        )
    timings: dict[str, float] = {}
    names = list(detections)
    if not names:
        raise CalibrationError("no cameras given")
    searched = dict(frames_searched or {})
    dets: dict[str, list[FrameDetection]] = {}
    for n in names:
        raw = detections[n]
        if isinstance(raw, CameraDetections):
            searched.setdefault(n, raw.frames_searched)
            raw = raw.detections
        if n not in image_sizes:
            raise CalibrationError(f"camera '{n}': no image size given (expected (width, height))")
        dets[n] = [d for d in (_clean(d, board, opts.min_corners) for d in raw) if d is not None]
        _check_image_size(n, image_sizes[n], dets[n])
    blind = [n for n in names if not dets[n]]
    if blind:
        parts = [
            f"'{n}' ({searched[n]} frames searched)" if n in searched else f"'{n}'" for n in blind
        ]
        raise CalibrationError(
            f"camera {', '.join(parts)} never saw the board with at least {opts.min_corners} "
            "corners; check that the board is in view and in focus, and that the board spec "
            "matches it"
        )

    # 1. Intrinsics per camera, then the board pose in every view.
    t0 = time.perf_counter()
    intr, views, weights, initial_rms = {}, {}, {}, {}
    for i, n in enumerate(names):
        if progress:
            progress("intrinsics", i, len(names))
        intr[n] = calibrate_intrinsics(
            n,
            dets[n],
            board,
            tuple(image_sizes[n]),
            lens_model=opts.lens_model,
            max_views=opts.max_intrinsic_views,
        )
        initial_rms[n] = intr[n].rms_px
        limit = max(opts.view_outlier_px, 3.0 * intr[n].rms_px)
        poses = []
        for d in dets[n]:
            try:
                poses.append(
                    board_pose(
                        d, board, intr[n].K, intr[n].dist, outlier_px=limit,
                        min_corners=opts.min_corners,
                    )
                )  # fmt: skip
            except IntrinsicsError as exc:  # left out as a view above the limit is (it named
                log.warning("camera '%s': %s; the view is left out", n, exc)  # no camera)
        views[n] = {p.frame: p.matrix for p in poses if p.rms_px <= limit}
        weights[n] = {p.frame: float(p.n_corners) for p in poses if p.rms_px <= limit}
    timings["intrinsics"] = time.perf_counter() - t0

    # 2. Extrinsics: pose graph over cameras, then every board pose in the rig.
    t0 = time.perf_counter()
    cam_from_ref, reference = chain_poses(names, pairwise_edges(views, weights))
    frames = sorted({f for n in names for f in views[n]})
    rig_from_board = {}
    for f in frames:
        seen = [n for n in names if f in views[n]]
        est = np.stack([invert(cam_from_ref[n]) @ views[n][f] for n in seen])
        rig_from_board[f], _ = robust_mean_pose(est, np.array([weights[n][f] for n in seen]))
    timings["pose_graph"] = time.perf_counter() - t0
    states = {
        n: CameraState(
            n,
            int(image_sizes[n][0]),
            int(image_sizes[n][1]),
            intr[n].K,
            intr[n].dist,
            cam_from_ref[n],
        )
        for n in names
    }
    observations = {
        n: {d.frame: (d.ids, d.corners) for d in dets[n] if d.frame in views[n]} for n in names
    }
    return InitialSolution(
        names,
        board,
        dets,
        searched,
        states,
        reference,
        rig_from_board,
        observations,
        initial_rms,
        timings,
    )


MIN_ORIENTATIONS = 3  # distinct board planes (tilts) a camera needs to be determined...
ORIENTATION_STEP_DEG = 10.0  # ...their normals at least this far apart
# A camera whose frames are out of step with the others (a dropped image in its folder, an
# offset in its numbering) agrees with them on no board pose: the bundle adjustment removes its
# shared corners as outliers and places it by the frames no other camera saw, metres off, at a
# low RMS (40-42 % of its corners lost in the tests' cases, the cameras it pulled along 23-28 %).
# Healthy board footage loses a few per cent; the demo's rendered 480x360 boards up to 9 %.
MAX_OUTLIER_SHARE = 0.2


def distinct_orientations(rotations: Sequence[np.ndarray], step_deg: float) -> int:
    """How many board planes of the board poses `rotations` (board to rig) tilt more than
    `step_deg` from every one counted before: the angle between the boards' normals, either
    side. Views of parallel planes determine no focal length or principal point (Zhang), so a
    board only slid and turned on the floor counts once (counted by whole rotations, its 15
    degree turns made eight 'orientations' and a camera 0.9 m off passed unflagged)."""
    kept: list[np.ndarray] = []
    for R in rotations:
        normal = np.asarray(R, np.float64)[:, 2]
        angles = [np.degrees(np.arccos(min(1.0, abs(float(normal @ k))))) for k in kept]
        if all(a > step_deg for a in angles):
            kept.append(normal)
    return len(kept)


def bundle_adjust(init: InitialSolution, options: SolveOptions | None = None) -> BAResult:
    """Joint bundle adjustment (pycolmap) of an initial solution."""
    opts = options or SolveOptions()
    ba = BoardBundleAdjuster(
        init.cameras,
        init.reference,
        init.rig_from_board,
        init.board.object_points(),
        init.observations,
        opts.lens_model,
        opts.ba,
    )
    return ba.result(ba.run())


# A camera's image "up" points this far up the world's z axis at least (cos of its tilt: 0.3 is
# a camera looking 73 deg down) in a rig filmed standing upright around the scene.
MIN_UPRIGHT = 0.3


def _sideways_world(rig: Rig, floor_frame: int) -> list[str]:
    """A note when most cameras' image up is not the world's up: the floor board was held up
    facing the cameras (carried in first), not lying flat, so the world lies on its side. With
    every camera on the board's printed side, no camera is below the floor to give it away."""
    ups = {c.name: float(-c.R[1, 2]) for c in rig}  # image up (-y) in world z
    if np.median(list(ups.values())) >= MIN_UPRIGHT:
        return []
    shown = ", ".join(f"{n} {u:+.2f}" for n, u in ups.items())
    return [
        f"most cameras' image up does not point up the world's z axis (its z component: "
        f"{shown}; at least {MIN_UPRIGHT} for a camera looking less than 73 deg down): was the "
        f"board in frame {floor_frame}, which defines the floor, really lying flat? A board "
        "held up facing the cameras gives a world on its side; set calibrate.floor_frame to a "
        "frame where it lies on the floor (ignore this for cameras looking straight down or "
        "rolled on their side, people lying sideways in their images)"
    ]


# A camera's board corners reach at least this share of the way from the principal point to the
# farthest image corner, or its lens model moves that corner by at most MAX_GUESSED_PX; beyond
# the board the distortion is extrapolated. Tests: a wide lens (the model moves the corners
# 90-160 px) seen by a board that reached 54-59 % of the way was 40-1199 px off at the edges at
# an RMS of 0.4 px; a milder one (16-26 px) within 2 px everywhere at a reach of 77-91 %.
MIN_LENS_REACH = 0.7
MAX_GUESSED_PX = 50.0


def _corner_shift_px(state: CameraState) -> float:
    """How far the lens model moves the image corner it moves most (px): its ray's pinhole
    projection against its projection through the distortion."""
    w, h = state.width, state.height
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    rays = np.c_[(corners - state.K[:2, 2]) / np.diag(state.K)[:2], np.ones(4)]
    seen, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), state.K, state.dist)
    return float(np.linalg.norm(seen[:, 0] - corners, axis=1).max())


def _lens_reach_notes(ba: BAResult) -> list[str]:
    """A note per camera whose board never came near the edges of an image its lens distorts
    strongly there: the distortion at the edges is the model's guess, which can be far off."""
    notes = []
    for n, obs in ba.observations.items():
        state = ba.cameras[n]
        pp = state.K[:2, 2]
        w, h = state.width, state.height
        corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
        far = float(np.linalg.norm(corners - pp, axis=1).max())
        reach = float(np.linalg.norm(obs - pp, axis=1).max()) / far if len(obs) else 0.0
        shift = _corner_shift_px(state)
        if reach < MIN_LENS_REACH and shift > MAX_GUESSED_PX:
            notes.append(
                f"camera '{n}': the board's corners reached only {reach:.0%} of the way from the "
                f"image centre to its corners (at least {MIN_LENS_REACH:.0%} wanted), and its "
                f"lens model moves the image corners by {shift:.0f} px: that distortion is "
                "extrapolated and can be far off near the edges whatever the RMS; record the "
                "board near the image's edges and corners too"
            )
    return notes


def _unconverged_notes(ba: BAResult) -> list[str]:
    """The last adjustment stopped by its iteration limit, not converged: Ceres calls that a
    usable solution, and the rig was written without a word (its cameras may still be moving)."""
    last = ba.rounds[-1] if ba.rounds else {}
    if last.get("termination", "CONVERGENCE") in ("CONVERGENCE", "USER_SUCCESS"):
        return []
    return [
        f"the bundle adjustment stopped without converging (Ceres: {last['termination']}, round "
        f"{last['round']}): the rig may be short of its optimum; check the RMS per camera, or "
        "raise its iteration limit (SolveOptions.ba.max_iterations; the calibrate stage's "
        "ba_max_iterations)"
    ]


def finish_calibration(
    init: InitialSolution,
    ba: BAResult,
    *,
    floor_world: bool = True,
    floor_frame: int | None = None,
    timings: dict[str, float] | None = None,
) -> BoardCalibration:
    """Put the adjusted rig into its world frame (see the module docstring) and collect results."""
    names, board = init.names, init.board
    notes: list[str] = []
    cams_rig = {n: ba.cameras[n].cam_from_rig for n in names}
    if floor_world:
        if floor_frame is None:
            floor_frame = min(ba.rig_from_board)
        if floor_frame not in ba.rig_from_board:
            raise CalibrationError(
                f"floor frame {floor_frame} has no usable board detection; frames with "
                f"board poses: {sorted(ba.rig_from_board)[:20]}..."
            )
        board_from_world = invert(_world_from_floor_board())
        rig_from_world = ba.rig_from_board[floor_frame] @ board_from_world
        up = (0.0, 0.0, 1.0)
    else:
        floor_frame = None
        rig_from_world = invert(cams_rig[names[0]])  # world = first camera
        up = tuple(float(v) for v in -np.eye(3)[1])
    rms = ba.rms_px()
    cameras = []
    for n in names:
        s = ba.cameras[n]
        T = cams_rig[n] @ rig_from_world
        cameras.append(
            Camera.create(
                n,
                s.K,
                s.dist,
                T[:3, :3],
                T[:3, 3],
                s.width,
                s.height,
                {"source": "board-calibration", "rms_px": rms[n]},
            )
        )
    rig = Rig(
        tuple(cameras),
        up=up,
        meta={"source": "board-calibration", "board": board.to_dict(), "floor_frame": floor_frame},
    )
    if floor_world:
        below = [c.name for c in rig if c.center[2] <= 0]
        if below:
            notes.append(
                f"cameras {below} are below the floor: was the board in frame {floor_frame} "
                "really lying flat on the floor, printed side up?"
            )
        notes += _sideways_world(rig, floor_frame)
    # a lens model no lens has (the bundle adjustment refines every distortion term: the
    # rational ones can fold or reach a pole inside the image at a low RMS)
    for cam in rig:
        notes += [m for m in lens_findings(cam) if m is not None]
    # A camera that saw the board in one plane (held still, or only lying on the floor) fits
    # its views with any focal length and principal point: a low RMS and a wrong camera.
    weak = {}
    for n in names:
        # the views the adjustment used (`observations`): a view the PnP step dropped, of a
        # frame another camera placed, counted as one of this camera's orientations
        poses = [ba.rig_from_board[f][:3, :3] for f in init.observations[n]
                 if f in ba.rig_from_board]  # fmt: skip
        k = distinct_orientations(poses, ORIENTATION_STEP_DEG)
        if k < MIN_ORIENTATIONS:
            weak[n] = k
            notes.append(
                f"camera '{n}' saw the board in only {k} distinct orientation(s) "
                f"({len(poses)} views; board planes tilted {ORIENTATION_STEP_DEG:.0f} deg apart "
                "count as distinct, turns within one plane do not; "
                f"{MIN_ORIENTATIONS} are needed): its focal length, principal point and pose are "
                "poorly determined whatever its RMS; record the board tilted several ways in "
                "front of it"
            )
    notes += _lens_reach_notes(ba)
    notes += _unconverged_notes(ba)
    suspect = {}
    for n in names:
        kept, removed = len(ba.residuals[n]), len(ba.outliers[n])
        share = removed / max(kept + removed, 1)
        if share > MAX_OUTLIER_SHARE:
            suspect[n] = share
            notes.append(
                f"camera '{n}' lost {share:.0%} of its board corners as outliers ({removed} of "
                f"{kept + removed}; more than {MAX_OUTLIER_SHARE:.0%}): are its frames in step "
                "with the other cameras' (a dropped or extra image in its folder, an offset in "
                "its frame numbering)? A camera out of step is placed by the frames no other "
                "camera saw, wrongly, at a low RMS"
            )
    world_from_rig = invert(rig_from_world)
    return BoardCalibration(
        rig=rig,
        board=board,
        rms_px=rms,
        detections={n: len(init.detections[n]) for n in names},
        detected_frames={n: [d.frame for d in init.detections[n]] for n in names},
        frames_searched={
            n: int(init.frames_searched[n]) for n in names if n in init.frames_searched
        },
        image_sizes={n: (init.cameras[n].width, init.cameras[n].height) for n in names},
        observations=ba.observations,
        residuals_px=ba.residuals,
        outliers=ba.outliers,
        initial_rms_px=init.initial_rms_px,
        world_from_board={f: world_from_rig @ T for f, T in ba.rig_from_board.items()},
        floor_frame=floor_frame,
        timings=dict(timings or init.timings),
        ba_rounds=ba.rounds,
        notes=notes,
        weak_cameras=weak,
        suspect_cameras=suspect,
    )


def calibrate_from_detections(
    detections: Mapping[str, Sequence[FrameDetection] | CameraDetections],
    image_sizes: Mapping[str, tuple[int, int]],
    board: BoardSpec,
    *,
    floor_world: bool = True,
    floor_frame: int | None = None,
    frames_searched: Mapping[str, int] | None = None,
    options: SolveOptions | None = None,
    progress: Progress | None = None,
) -> BoardCalibration:
    """Calibrate a rig from board corners already found in each camera's frames.

    `detections[camera]` lists that camera's FrameDetection (frame indices shared across cameras
    mean the same instant); `image_sizes[camera] = (width, height)`. Cameras keep the order of
    `detections`. Raises CalibrationError naming any camera that never saw the board, and
    PoseGraphError naming cameras that share no board frame with the others.
    """
    init = initialise_from_detections(
        detections,
        image_sizes,
        board,
        frames_searched=frames_searched,
        options=options,
        progress=progress,
    )
    if progress:
        progress("bundle adjustment", 0, 1)
    t0 = time.perf_counter()
    ba = bundle_adjust(init, options)
    timings = {**init.timings, "bundle_adjustment": time.perf_counter() - t0}
    if progress:
        progress("bundle adjustment", 1, 1)
    return finish_calibration(
        init, ba, floor_world=floor_world, floor_frame=floor_frame, timings=timings
    )


def _world_from_floor_board() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = WORLD_FROM_FLOOR_BOARD_AXES
    return T


def calibrate_from_board(
    sources: Mapping[str, str | Path],
    board: BoardSpec,
    *,
    frame_step: int = 1,
    max_frames: int | None = None,
    floor_world: bool = True,
    progress: Progress | None = None,
    floor_frame: int | None = None,
    options: SolveOptions | None = None,
) -> BoardCalibration:
    """Calibrate a rig from synchronised board footage, one video file or image folder per camera.

    Every `frame_step`-th frame is searched, at most `max_frames` per camera. See the module
    docstring for the world frame. `progress(step, done, total)` reports detection per camera
    (step 'detect <camera>') and the solver steps.
    """
    opts = options or SolveOptions()
    t0 = time.perf_counter()
    found = detect_in_sources(
        dict(sources),
        board,
        frame_step=frame_step,
        max_frames=max_frames,
        min_corners=opts.min_corners,
        min_sharpness_ratio=opts.min_sharpness_ratio,
        progress=(lambda cam, i, n: progress(f"detect {cam}", i, n)) if progress else None,
    )
    t_detect = time.perf_counter() - t0
    result = calibrate_from_detections(
        found,
        {n: d.image_size for n, d in found.items()},
        board,
        floor_world=floor_world,
        floor_frame=floor_frame,
        options=opts,
        progress=progress,
    )
    result.timings = {"detection": t_detect, **result.timings}
    return result

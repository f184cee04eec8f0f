"""The body fit over a clip: one shape per person; pose and translation per frame.

All people and frames are one batch (CPU, float64), solved by Levenberg-Marquardt
(gst.fuse.solver) on the energy of gst.fuse.objective, with the joints-only body forward and its
analytic Jacobian (gst.body.kinematics). Two stages:

1. start: from the rigid start (gst.fuse.start), `init_iterations` steps against the
   triangulated landmarks (3D, robust): close to the answer in a few steps and free of the 2D
   stage's local minima (an arm fitted behind the body from one view's point of view);
2. fit: `view_rounds` x `iterations` steps against every camera's landmarks (2D reprojection,
   robust), with temporal smoothness, pose prior and joint limits; before each round, every
   view of a person-frame is weighted by how well the current body explains it as a whole
   (a partly occluded view, all of whose landmarks are a little off, counts less).

Frames inserted into gaps (no evidence) are started from their neighbours and held by the
smoothness; a person seen by one camera at a time is fitted by stage 2 alone and marked
single-view. The cost of an iteration is linear in person-frames and cameras (see
benchmarks/bench_fuse.py).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from gst.body.joint_limits import JOINT_LIMITS_DEG
from gst.body.kinematics import MarkerSkeleton
from gst.body.markers import MarkerModel
from gst.body.model import BodyModel
from gst.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from gst.body.skeleton import SMPL_JOINT_NAMES
from gst.fuse.floor import floor_clearance, stands_on
from gst.fuse.objective import (
    Coverage,
    Floor,
    Neighbours,
    Points,
    Views,
    Weights,
    cost,
    euler_xyz,
    linearise,
)
from gst.fuse.observations import PersonObservations
from gst.fuse.silhouettes import CropSilhouettes
from gst.fuse.solver import BodyState, levenberg_marquardt
from gst.fuse.start import (
    TORSO_LANDMARKS,
    dense_frames,
    dense_triangulation,
    nearest,
    rigid_start,
)
from gst.fuse.triangulate import PersonTriangulation

__all__ = ["FitOptions", "PersonFit", "fit_people", "euler_xyz_from_matrix"]

DTYPE = torch.float32  # float64 gives the same answers (demo, tuning worlds), 20 % slower
euler_xyz_from_matrix = euler_xyz  # the joint-limit angles (kept under its old name)


@dataclass(frozen=True)
class FitOptions:
    num_betas: int = 10
    iterations: int = 12  # LM iterations against the 2D landmarks, per view-weighting round
    init_iterations: int = 6  # LM iterations against the triangulated landmarks (the start)
    sigma_px: float | None = None  # Cauchy scale; None: sigma_factor x median triangulation error
    sigma_factor: float = 1.0
    min_sigma_px: float = 2.0
    min_confidence: float = 0.1
    w_pose: float = 1.0  # per rad^2 of local rotation
    w_limits: float = 100.0  # per rad^2 of excess over the joint limits
    w_betas: float = 1.0
    w_smooth: float = 1.0  # Cauchy weight of each marker's second difference
    smooth_scale_m: float = 0.02  # the second difference (at 30 fps) counted as one unit
    sigma_3d_m: float = 0.03  # Cauchy scale of the start stage (triangulated landmarks)
    start_sigma_factor: float = 10.0  # 2D kernel scale of the start where nothing triangulates
    view_weighting: bool = True  # reweigh whole views by their median residual (_weigh_views)
    view_rounds: int = 2
    # > 0: each person's own marker offsets are fitted over the clip (as MoSh does for mocap
    # markers), pulled towards the table with this weight per m^2; 0: the table as it is
    w_marker_offsets: float = 0.0
    # > 0: every marker, in every view with a crop, is pulled onto the people of that view
    # (gst.fuse.silhouettes; Cauchy scale silhouette_sigma_factor x the landmark kernel's)
    w_silhouette: float = 0.0
    silhouette_sigma_factor: float = 3.0
    static_tol_m: float = 0.005
    # frames where nobody saw the person, inside a gap of at most this long (seconds), are
    # filled by the fit (observed False); longer gaps are left out, the track resumes after them
    # (in crowds, frames filled over longer gaps were 150-400 mm off the truth: docs/fuse.md)
    max_gap_s: float = 0.1
    # with a floor (fit_people's `floor`; not in the start, whose rigid guess may lie anywhere):
    # energy per m^2 of a foot marker below its rest height above the soles (less
    # `floor_tolerance_m`), or of any other marker below the floor (gst.fuse.floor)
    w_floor: float = 1e5
    floor_tolerance_m: float = 0.01


@dataclass
class PersonFit:
    """One person's fitted body over their frames (T)."""

    person_id: int
    frames: np.ndarray  # (T,) int
    betas: np.ndarray  # (nb,)
    global_orient: np.ndarray  # (T, 3) axis-angle, body -> world
    body_pose: np.ndarray  # (T, 23, 3) axis-angle
    transl: np.ndarray  # (T, 3) metres
    joints: np.ndarray  # (T, 24, 3) world, metres
    markers: np.ndarray  # (T, M, 3) world, metres
    reprojection: np.ndarray  # (T, C, M) full-image px of the fitted markers (NaN: no detection)
    observed: np.ndarray  # (T,) bool: the frame had at least one crop (else gap-filled)
    static: np.ndarray  # (T,) bool: nobody moved since the previous frame
    single_view: bool  # no landmark ever triangulated from two views
    sigma_px: float
    marker_offsets: np.ndarray | None = None  # (M, 3) the person's own offsets minus the table's


_ARM_JOINTS = ("left_shoulder", "right_shoulder", "left_elbow", "right_elbow")


def _limits_tensor(body: BodyModel) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-axis limits (23, 3) of joints 1..23. The table's arm axes assume SMPL's T-pose rest
    (arm along x, elbow flexion about y); a body whose rest arms hang down (the Anny default)
    flexes its elbows about x instead, so its shoulder and elbow limits are left open."""
    names = SMPL_JOINT_NAMES[1:]
    lim = torch.tensor([JOINT_LIMITS_DEG[n] for n in names], dtype=DTYPE).deg2rad()
    with torch.no_grad():
        rest = body.rest_joints(torch.zeros(1, 1, dtype=body.dtype, device=body.device))[0]
    j = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
    arm = rest[j["left_wrist"]] - rest[j["left_shoulder"]]
    if float(arm[1]) < -0.5 * float(arm.norm()):  # rest arms point down
        for n in _ARM_JOINTS:
            lim[names.index(n), :, 0] = -np.pi
            lim[names.index(n), :, 1] = np.pi
    return lim[..., 0], lim[..., 1]


def _neighbours(frames: list[np.ndarray]) -> Neighbours:
    prev, nxt, off = [], [], 0
    for f in frames:
        i = np.arange(len(f)) + off
        step = np.diff(f) == 1
        prev.append(np.where(np.r_[False, step], i - 1, i))
        nxt.append(np.where(np.r_[step, False], i + 1, i))
        off += len(f)
    prev, nxt = np.concatenate(prev), np.concatenate(nxt)
    idx = np.arange(off)
    return Neighbours(
        torch.as_tensor(prev), torch.as_tensor(nxt),
        torch.as_tensor(prev != idx), torch.as_tensor(nxt != idx),
    )  # fmt: skip


def _fill_unobserved(state: BodyState, observed: np.ndarray, offsets: np.ndarray) -> BodyState:
    """Start frames without evidence from their nearest observed neighbours (linear in the
    translation and local rotations, nearest root rotation), per person."""
    root, transl, theta = state.root.clone(), state.transl.clone(), state.theta.clone()
    for a, b in zip(offsets[:-1], offsets[1:], strict=True):
        seen = np.flatnonzero(observed[a:b])
        if len(seen) == 0 or len(seen) == b - a:
            continue
        t = np.arange(b - a)
        for x in (transl, theta):
            flat = x[a:b].reshape(b - a, -1).numpy()
            filled = np.stack([np.interp(t, seen, flat[seen, k]) for k in range(flat.shape[1])], 1)
            x[a:b] = torch.as_tensor(filled.reshape(x[a:b].shape))
        near = nearest(seen, b - a)
        root[a:b] = root[a:b][torch.as_tensor(near)]
    return BodyState(root, transl, theta, state.betas, state.offsets)


def _weigh_views(state: BodyState, views: Views, sk: MarkerSkeleton, person, table) -> Views:
    """Views whose landmarks are broadly worse than the person's noise level (partly occluded,
    blurred) count less: each (frame, camera) weight is scaled by sigma^2 / max(sigma, median
    residual of the view)^2, a view-level reweighting beside the per-landmark kernel."""
    X, *_ = sk.forward(state.betas[person], state.root, state.theta, state.transl, offsets=table)
    r = views.residuals(X)
    r = torch.where(views.weight > 0, r, torch.full_like(r, float("nan")))
    med = torch.nanmedian(r, dim=-1).values.nan_to_num(0.0)  # (B, C)
    s = views.sigma[:, None]
    return replace(views, weight=views.weight * ((s / torch.maximum(med, s)) ** 2)[..., None])


def fit_people(
    body: BodyModel,
    markers: MarkerModel,
    people: list[PersonObservations],
    tris: list[PersonTriangulation | None],
    fps: float,
    options: FitOptions | None = None,
    start: list[PersonFit] | None = None,
    marker_offsets: list[np.ndarray | None] | None = None,
    silhouettes: CropSilhouettes | None = None,
    floor: tuple[np.ndarray, float] | None = None,
    up: np.ndarray | None = None,
) -> list[PersonFit]:
    """Fit every person's body over the clip at once (one batch). Deterministic on CPU.

    `start`: earlier fits of the same people over the same frames (e.g. the previous window of
    a long clip) to start from instead of the rigid start; the start stage is then skipped.
    `marker_offsets`: per person, (M, 3) corrections of the marker table (a person's offsets
    from an earlier fit), held fixed unless `w_marker_offsets` > 0 fits them further.
    `silhouettes`: the store's people per crop (gst.fuse.silhouettes), for `w_silhouette`.
    `floor`: (world up, height along it) of the ground nobody sinks into (`w_floor`).
    `up`: the world's up direction (`Rig.up`; default the floor's, else +Z), which the start of
    people that no two cameras triangulate stands along."""
    o = options or FitOptions()
    if not people:
        return []
    if up is None and floor is not None:
        up = np.asarray(floor[0], np.float64)
    sk = MarkerSkeleton(body, markers, o.num_betas, DTYPE)
    nb = o.num_betas
    with torch.no_grad():
        X0, J0, _, _ = sk.forward(
            torch.zeros(1, nb, dtype=DTYPE), torch.eye(3, dtype=DTYPE)[None],
            torch.zeros(1, 23, 3, dtype=DTYPE), torch.zeros(1, 3, dtype=DTYPE),
        )  # fmt: skip
    rest_markers, pelvis = X0[0].numpy(), J0[0, 0].numpy()
    ground = None
    if floor is not None and o.w_floor > 0:
        up, height = floor
        clearance = floor_clearance(body, markers, rest_markers, o.floor_tolerance_m)
        ground = Floor(
            torch.as_tensor(up, dtype=DTYPE), float(height),
            torch.as_tensor(clearance, dtype=DTYPE), o.w_floor,
        )  # fmt: skip
        # only for those who stand on it: someone on other ground (the room's floor beside a
        # raised plate at height 0) keeps their own legs
        on_floor = [stands_on(None if t is None else t.points, up, height) for t in tris]

    dense, dtris, starts, statics, sigmas, single = [], [], [], [], [], []
    for obs, tri in zip(people, tris, strict=True):
        d = dense_frames(obs, int(round(o.max_gap_s * fps)))
        tri_d = dense_triangulation(tri, obs.frames, d.frames) if tri is not None else None
        R0, c0, static = rigid_start(d, tri_d, rest_markers, pelvis, o.static_tol_m, up)
        dense.append(d)
        dtris.append(tri_d)
        starts.append((R0, c0))
        statics.append(static)
        if o.sigma_px is not None:
            sigma = o.sigma_px
        else:
            med = np.nanmedian(tri.error) if tri is not None and np.isfinite(tri.error).any() else 0
            sigma = o.sigma_factor * float(np.nan_to_num(med))
        sigmas.append(max(o.min_sigma_px, sigma))
        # single view: no landmark placed by two views (a second crop without usable landmarks,
        # e.g. one the extraction projected, is no second view)
        single.append(tri is None or not bool((tri.used.sum(-1) >= 2).any()))

    lengths = [len(d.frames) for d in dense]
    offsets = np.cumsum([0] + lengths)
    person = torch.as_tensor(np.repeat(np.arange(len(dense)), lengths))
    if ground is not None and not all(on_floor):
        rows = np.repeat(np.where(on_floor, ground.height, -np.inf), lengths)
        ground = replace(ground, height=torch.as_tensor(rows, dtype=DTYPE)[:, None])
    observed = np.concatenate([(d.rows >= 0).any(1) for d in dense])

    def cat(name: str) -> torch.Tensor:
        return torch.as_tensor(np.concatenate([getattr(d, name) for d in dense]), dtype=DTYPE)

    conf, uv, K, Rt, px_scale = (cat(n) for n in ("confidence", "uv", "K", "Rt", "px_scale"))
    # a camera that is not finite is no view (as the triangulation takes it), and its numbers
    # are replaced by finite ones: 0 x NaN is NaN, and one NaN made the batched solve fail for
    # everyone in the batch, leaving all of them at their start (+40 % MPJPE)
    camera_ok = (
        torch.isfinite(K).flatten(-2).all(-1)
        & torch.isfinite(Rt).flatten(-2).all(-1)
        & torch.isfinite(px_scale)
    )
    usable = (
        (conf >= o.min_confidence)
        & torch.isfinite(conf)
        & torch.isfinite(uv).all(-1)
        & camera_ok[..., None]
    )
    ok = camera_ok[..., None, None]
    views = Views(
        torch.where(ok, K, torch.eye(3, dtype=DTYPE)),
        torch.where(ok, Rt, torch.eye(3, 4, dtype=DTYPE)),
        torch.nan_to_num(uv), torch.where(usable, conf, torch.zeros_like(conf)),
        torch.where(camera_ok, px_scale, torch.ones_like(px_scale)),
        torch.as_tensor(np.repeat(sigmas, lengths), dtype=DTYPE),
    )  # fmt: skip
    coverage = None
    if silhouettes is not None and o.w_silhouette > 0:
        rows = np.concatenate([d.rows for d in dense])  # (B, C)
        fields = silhouettes.fields()[np.clip(rows, 0, None)]  # (B, C, 3, s, s)
        coverage = Coverage(
            views, torch.as_tensor(fields.reshape(-1, *fields.shape[2:])),
            torch.as_tensor((rows >= 0) * o.w_silhouette, dtype=DTYPE),
            views.sigma * o.silhouette_sigma_factor, silhouettes.crop_size,
        )  # fmt: skip
    lo, hi = _limits_tensor(body)
    weights = Weights(
        o.w_pose, o.w_limits, o.w_smooth, (fps / 30.0) ** 2 / o.smooth_scale_m, lo, hi
    )
    nbrs = _neighbours([d.frames for d in dense])

    if start is not None:
        if [len(f.frames) for f in start] != lengths:
            raise ValueError("fit_people: `start` must cover the same people and frames")

        def joined(k: str) -> torch.Tensor:
            return torch.as_tensor(np.concatenate([getattr(f, k) for f in start]), dtype=DTYPE)

        state = BodyState(
            axis_angle_to_matrix(joined("global_orient")), joined("transl"),
            joined("body_pose").reshape(-1, 23, 3),
            torch.as_tensor(np.stack([f.betas for f in start]), dtype=DTYPE),
        )  # fmt: skip
    else:
        state = BodyState(
            torch.as_tensor(np.concatenate([s[0] for s in starts]), dtype=DTYPE),
            torch.as_tensor(np.concatenate([s[1] for s in starts]), dtype=DTYPE),
            torch.zeros(int(offsets[-1]), 23, 3, dtype=DTYPE),
            torch.zeros(len(dense), nb, dtype=DTYPE),
        )

    M = len(sk.anchor)
    fixed = torch.zeros(len(dense), M, 3, dtype=DTYPE)
    for k, d in enumerate(marker_offsets or []):
        if d is not None:
            fixed[k] = torch.as_tensor(d, dtype=DTYPE)

    def marker_table(s: BodyState) -> torch.Tensor:
        own = fixed if s.offsets is None else fixed + s.offsets
        return (sk.offsets + own)[person]  # (B, M, 3)

    def solve(state: BodyState, evidence, w: Weights, iterations: int) -> BodyState:
        def energy(s: BodyState) -> torch.Tensor:
            X, _, _, local = sk.forward(
                s.betas[person], s.root, s.theta, s.transl, offsets=marker_table(s)
            )
            return cost(X, s.theta, local, evidence, nbrs, w)

        def lin(s: BodyState):
            X, _, G, local, dX = sk.forward(
                s.betas[person], s.root, s.theta, s.transl, True, marker_table(s)
            )
            turn = None if s.offsets is None else G[:, sk.frame]
            return linearise(X, dX, s.theta, local, evidence, nbrs, w, turn)

        prior = torch.full((nb,), o.w_betas, dtype=DTYPE)
        if state.offsets is not None:
            prior = torch.cat([prior, torch.full((3 * M,), o.w_marker_offsets, dtype=DTYPE)])
        return levenberg_marquardt(state, person, energy, lin, iterations, prior)

    with torch.no_grad():
        if start is None and o.init_iterations:
            pts = np.concatenate(
                [t.points if t is not None else np.full((n, 33, 3), np.nan)
                 for t, n in zip(dtris, lengths, strict=True)]
            )  # fmt: skip
            w3 = np.concatenate(
                [t.confidence if t is not None else np.zeros((n, 33))
                 for t, n in zip(dtris, lengths, strict=True)]
            )  # fmt: skip
            w3 = np.where(np.isfinite(pts).all(-1), w3, 0.0)
            start_evidence = [
                Points(
                    torch.as_tensor(np.nan_to_num(pts), dtype=DTYPE),
                    torch.as_tensor(w3, dtype=DTYPE),
                    o.sigma_3d_m,
                )
            ]
            # frames with no triangulated torso (one view at a time): the 2D landmarks with a
            # wide kernel, so that a start far from the answer still feels all of them
            no_tri = torch.as_tensor((w3[:, list(TORSO_LANDMARKS)] == 0).all(1) & observed)
            if bool(no_tri.any()):
                start_evidence.append(
                    replace(
                        views,
                        weight=views.weight * no_tri[:, None, None],
                        sigma=views.sigma * o.start_sigma_factor,
                    )
                )
            state = solve(state, start_evidence, replace(weights, smooth=0.0), o.init_iterations)
            state = _fill_unobserved(state, observed, offsets)
        if o.w_marker_offsets > 0:  # the person's own markers, from the 2D evidence only
            state = replace(state, offsets=torch.zeros(len(dense), M, 3, dtype=DTYPE))
        others = [e for e in (coverage, ground) if e is not None]  # beside the 2D landmarks
        if o.view_weighting and o.view_rounds:
            for _ in range(o.view_rounds):
                weighed = _weigh_views(state, views, sk, person, marker_table(state))
                state = solve(state, [weighed, *others], weights, o.iterations)
        else:
            state = solve(state, [views, *others], weights, o.iterations)
        X, J, _, _ = sk.forward(
            state.betas[person], state.root, state.theta, state.transl,
            offsets=marker_table(state),
        )  # fmt: skip
        own = fixed if state.offsets is None else fixed + state.offsets
        r = views.residuals(X)
        reproj = torch.where(views.weight > 0, r, torch.full_like(r, float("nan")))
        go = matrix_to_axis_angle(state.root)

    results = []
    for k, d in enumerate(dense):
        a, b = offsets[k], offsets[k + 1]
        results.append(
            PersonFit(
                person_id=d.person_id,
                frames=d.frames,
                betas=state.betas[k].numpy(),
                global_orient=go[a:b].numpy(),
                body_pose=state.theta[a:b].numpy().copy(),
                transl=state.transl[a:b].numpy(),
                joints=J[a:b].numpy(),
                markers=X[a:b].numpy(),
                reprojection=reproj[a:b].numpy(),
                observed=(d.rows >= 0).any(1),
                static=statics[k],
                single_view=single[k],
                sigma_px=sigmas[k],
                marker_offsets=own[k].numpy(),
            )
        )
    return results

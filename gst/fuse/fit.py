"""A body fit over the whole clip: one shape per person, pose and translation per frame.

All people and frames are one batch in torch (CPU), minimised with L-BFGS:

    E = sum_frames [ reprojection + w_smooth * smoothness + w_limits * joint limits
                     + w_pose * pose prior ] / frames  +  w_betas * |betas|^2 / people

- reprojection: the body's virtual markers (gst.body.markers) projected into EVERY camera that
  has a crop of the person in that frame (each crop's K_crop, R, t), against the detected
  landmarks, residuals in full-image pixels, confidence-weighted, through a Cauchy kernel
  log(1 + (r / sigma)^2) so wrong detections (left/right swaps, the other person) saturate;
  normalised per frame by the confidence mass;
- smoothness: second differences of the markers over consecutive frames, in units of
  `smooth_scale_m` at 30 fps (scaled by (30 / fps)^2, so a weight means the same at any rate),
  through the same Cauchy kernel (real accelerations of a sprinting wrist are not noise);
- joint limits: squared excess of each joint's X-Y-Z Euler angles over gst.body.joint_limits;
- pose prior: squared axis-angle of the body pose (the rest pose is the mode).

Initialisation: per frame, the rest-pose markers are rigidly aligned (Kabsch) to the
triangulated shoulders and hips; a frame where nobody moved (triangulated landmarks within
`static_tol_m` of the previous frame's) starts from the previous frame's start. Frames without
any crop between two seen frames (gaps up to `max_gap` frames) are inserted and filled by the
smoothness term alone; a person seen by one camera only is fitted with the same terms (there is
no triangulation to start from: the start is placed on the camera ray at the depth that gives
the landmarks a 1.7 m body) and marked single-view.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from gst.body.joint_limits import JOINT_LIMITS_DEG
from gst.body.markers import MarkerModel
from gst.body.model import BodyModel
from gst.body.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_rot6d,
    rot6d_to_matrix,
)
from gst.body.skeleton import SMPL_JOINT_NAMES
from gst.fuse.observations import PersonObservations
from gst.fuse.triangulate import PersonTriangulation

__all__ = ["FitOptions", "PersonFit", "fit_people", "euler_xyz_from_matrix", "TORSO_LANDMARKS"]

TORSO_LANDMARKS = (11, 12, 23, 24)  # shoulders and hips: the rigid start


@dataclass(frozen=True)
class FitOptions:
    num_betas: int = 10
    iterations: int = 200  # L-BFGS iterations of the full fit
    init_iterations: int = 30  # L-BFGS iterations of the root-only start
    sigma_px: float | None = None  # Cauchy scale; None: 2.5 x the median triangulation error
    min_sigma_px: float = 2.0
    min_confidence: float = 0.1
    w_smooth: float = 0.1
    smooth_scale_m: float = 0.05
    w_limits: float = 10.0
    w_pose: float = 0.02
    w_betas: float = 0.001
    static_tol_m: float = 0.005
    max_gap: int = 15


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
    static: np.ndarray  # (T,) bool: started from the previous frame (nobody moved)
    single_view: bool  # never seen by two cameras at once
    sigma_px: float


def euler_xyz_from_matrix(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 3) angles (a, b, c) with R = Rx(a) Ry(b) Rz(c) (joint_limits' order)."""
    b = torch.asin(R[..., 0, 2].clamp(-1 + 1e-6, 1 - 1e-6))
    a = torch.atan2(-R[..., 1, 2], R[..., 2, 2])
    c = torch.atan2(-R[..., 0, 1], R[..., 0, 0])
    return torch.stack([a, b, c], -1)


_ARM_JOINTS = ("left_shoulder", "right_shoulder", "left_elbow", "right_elbow")


def _limits_tensor(body: BodyModel) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-axis limits (23, 3) of joints 1..23. The table's arm axes assume SMPL's T-pose rest
    (arm along x, elbow flexion about y); a body whose rest arms hang down (the Anny default)
    flexes its elbows about x instead, so its shoulder and elbow limits are left open."""
    names = SMPL_JOINT_NAMES[1:]
    lim = torch.tensor([JOINT_LIMITS_DEG[n] for n in names], dtype=torch.float64).deg2rad()
    with torch.no_grad():
        rest = body.rest_joints(torch.zeros(1, 1, dtype=body.dtype, device=body.device))[0]
    j = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
    arm = rest[j["left_wrist"]] - rest[j["left_shoulder"]]
    if float(arm[1]) < -0.5 * float(arm.norm()):  # rest arms point down
        for n in _ARM_JOINTS:
            lim[names.index(n), :, 0] = -np.pi
            lim[names.index(n), :, 1] = np.pi
    return lim[..., 0].to(body.dtype), lim[..., 1].to(body.dtype)


def _kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, c with dst ~ R src + c (rotation only), src/dst (n, 3)."""
    ms, md = src.mean(0), dst.mean(0)
    H = (src - ms).T @ (dst - md)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1, 1, d]) @ U.T
    return R, md - R @ ms


@dataclass
class _Batch:
    """Everything the objective needs, for B person-frames in one batch."""

    person: torch.Tensor  # (B,) index into the people list
    K: torch.Tensor  # (B, C, 3, 3)
    Rt: torch.Tensor  # (B, C, 3, 4)
    uv: torch.Tensor  # (B, C, M, 2)
    weight: torch.Tensor  # (B, C, M) confidence (0: unobserved)
    scale: torch.Tensor  # (B, C) crop px -> full px
    prev: torch.Tensor  # (B,) batch index of the previous frame of the same person, -1 if none
    sigma: torch.Tensor  # (B,) Cauchy scale of this person, full px


def _dense_frames(obs: PersonObservations, max_gap: int) -> PersonObservations:
    """Insert unseen frames inside gaps of at most `max_gap` frames (filled by the fit)."""
    f = obs.frames
    if len(f) < 2:
        return obs
    full = np.concatenate(
        [f[:1]]
        + [
            np.arange(a + 1, b + 1) if b - a - 1 <= max_gap else np.array([b])
            for a, b in zip(f[:-1], f[1:], strict=True)
        ]
    )
    if len(full) == len(f):
        return obs
    idx = np.searchsorted(f, full)
    have = np.isin(full, f)
    src = np.where(have, idx, 0)

    def take(a: np.ndarray, fill) -> np.ndarray:
        out = a[src].copy()
        out[~have] = fill
        return out

    return PersonObservations(
        obs.person_id,
        full,
        take(obs.uv, np.nan),
        take(obs.confidence, 0.0),
        take(obs.K, np.eye(3)),
        take(obs.Rt, np.eye(3, 4)),
        take(obs.px_scale, 1.0),
        take(obs.rows, -1),
    )


def _start_pose(
    obs: PersonObservations,
    tri: PersonTriangulation | None,
    rest_markers: np.ndarray,
    pelvis: np.ndarray,
    tol: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame: root rotation (T, 3, 3), translation (T, 3) and the static flag (T,)."""
    T = len(obs.frames)
    R = np.tile(np.eye(3), (T, 1, 1))
    c = np.full((T, 3), np.nan)
    static = np.zeros(T, bool)
    torso = list(TORSO_LANDMARKS)
    src = rest_markers[torso] - pelvis
    if tri is not None:
        for i in range(T):
            X = tri.points[i, torso]
            ok = np.isfinite(X).all(1)
            if ok.sum() >= 3:
                R[i], c[i] = _kabsch(src[ok], X[ok])
        pts = tri.points
        for i in range(1, T):
            both = np.isfinite(pts[i]).all(1) & np.isfinite(pts[i - 1]).all(1)
            if both.sum() >= 8 and np.abs(pts[i][both] - pts[i - 1][both]).max() < tol:
                static[i] = True
                R[i], c[i] = R[i - 1], c[i - 1]
    missing = ~np.isfinite(c).all(1)
    if missing.all():
        R, c = _single_view_start(obs, rest_markers, pelvis)
    elif missing.any():  # nearest frame with a start
        good = np.flatnonzero(~missing)
        near = good[np.abs(np.arange(T)[:, None] - good[None]).argmin(1)]
        R[missing], c[missing] = R[near[missing]], c[near[missing]]
    return R, c - pelvis[None], static


def _single_view_start(
    obs: PersonObservations, rest_markers: np.ndarray, pelvis: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """No triangulation: upright, facing the camera, at the depth that makes the body 1.7 m."""
    T = len(obs.frames)
    R = np.tile(np.eye(3), (T, 1, 1))
    c = np.zeros((T, 3))
    last = None
    for i in range(T):
        cams = np.flatnonzero(obs.rows[i] >= 0)
        if not len(cams):
            continue
        k = cams[0]
        K, Rt = obs.K[i, k], obs.Rt[i, k]
        uv, w = obs.uv[i, k], obs.confidence[i, k] > 0.3
        if w.sum() < 4:
            continue
        height_px = np.ptp(uv[w, 1]) + 1e-6
        depth = K[1, 1] * 1.7 / height_px
        hips = uv[[23, 24]].mean(0)
        ray = np.linalg.solve(K, np.r_[hips, 1.0]) * depth  # camera frame
        Rc, tc = Rt[:, :3], Rt[:, 3]
        c[i] = Rc.T @ (ray - tc)
        # body axes in world: up = world z, forward = towards the camera (horizontal)
        to_cam = -Rc.T @ tc - c[i]
        fwd = np.r_[to_cam[:2], 0.0]
        fwd /= np.linalg.norm(fwd) + 1e-9
        up = np.array([0.0, 0.0, 1.0])
        left = np.cross(up, fwd)
        R[i] = np.stack([left, up, fwd], 1)  # columns: model x, y, z in world
        last = i
    if last is None:
        raise ValueError(f"person {obs.person_id}: no view with at least 4 confident landmarks")
    seen = np.any(obs.rows >= 0, 1) & np.isfinite(c).all(1) & (np.abs(c).sum(1) > 0)
    good = np.flatnonzero(seen)
    near = good[np.abs(np.arange(T)[:, None] - good[None]).argmin(1)]
    return R[near], c[near]


def _objective_terms(
    body: BodyModel,
    markers: MarkerModel,
    batch: _Batch,
    betas: torch.Tensor,
    root6d: torch.Tensor,
    pose: torch.Tensor,
    transl: torch.Tensor,
    opts: FitOptions,
    fps: float,
    lo: torch.Tensor,
    hi: torch.Tensor,
):
    B = root6d.shape[0]
    rot = axis_angle_to_matrix(pose.reshape(B, 23, 3))
    out = body(
        betas[batch.person],
        rot,
        rot6d_to_matrix(root6d),
        transl,
        vertex_ids=markers.vertex_ids,
        return_transforms=True,
    )
    X = markers.positions(out)  # (B, M, 3)
    cam = torch.einsum("bcij,bmj->bcmi", batch.Rt[..., :3], X) + batch.Rt[:, :, None, :, 3]
    z = cam[..., 2:].clamp_min(1e-3)
    uv = torch.einsum("bcij,bcmj->bcmi", batch.K, cam / z)[..., :2]
    r = (uv - batch.uv).norm(dim=-1) * batch.scale[..., None]  # (B, C, M) full px
    rho = torch.log1p((r / batch.sigma[:, None, None]) ** 2)
    w = batch.weight
    reproj = (w * rho).sum((1, 2)) / w.sum((1, 2)).clamp_min(1.0)
    # smoothness on markers: second differences where both neighbours exist
    has = batch.prev >= 0
    prev = torch.where(has, batch.prev, torch.arange(B))
    prev2 = torch.where(has & (batch.prev[prev] >= 0), batch.prev[prev], prev)
    ok2 = (has & (batch.prev[prev] >= 0)).to(X.dtype)
    acc = (X - 2 * X[prev] + X[prev2]) * (fps / 30.0) ** 2 / opts.smooth_scale_m
    smooth = ok2 * torch.log1p((acc**2).sum(-1)).mean(-1)
    ang = euler_xyz_from_matrix(rot)
    excess = torch.relu(lo - ang) + torch.relu(ang - hi)
    limits = (excess / 0.1).pow(2).sum((1, 2))
    prior = pose.pow(2).sum(-1)
    return out, X, r, reproj, smooth, limits, prior


def fit_people(
    body: BodyModel,
    markers: MarkerModel,
    people: list[PersonObservations],
    tris: list[PersonTriangulation | None],
    fps: float,
    options: FitOptions | None = None,
    start: list[PersonFit] | None = None,
) -> list[PersonFit]:
    """Fit every person's body over the clip at once (one batch). Deterministic on CPU.

    `start`: earlier fits of the same people over the same frames (e.g. a previous run) to
    start from instead of the rigid start; the root-only stage is then skipped."""
    o = options or FitOptions()
    if not people:
        return []
    dtype = body.dtype
    zero_betas = torch.zeros(1, o.num_betas, dtype=dtype)
    eye = torch.eye(3, dtype=dtype)[None]
    with torch.no_grad():
        rest = body(
            zero_betas,
            eye.expand(23, 3, 3)[None],
            eye,
            vertex_ids=markers.vertex_ids,
            return_transforms=True,
        )
        rest_markers = markers.positions(rest)[0].double().numpy()
        pelvis = rest.joints[0, 0].double().numpy()

    dense, starts, statics, sigmas, single = [], [], [], [], []
    for obs, tri in zip(people, tris, strict=True):
        d = _dense_frames(obs, o.max_gap)
        tri_d = _dense_tri(tri, obs.frames, d.frames) if tri is not None else None
        R0, c0, static = _start_pose(d, tri_d, rest_markers, pelvis, o.static_tol_m)
        dense.append(d)
        starts.append((R0, c0))
        statics.append(static)
        if o.sigma_px is not None:
            sigma = o.sigma_px
        else:
            med = np.nanmedian(tri.error) if tri is not None and np.isfinite(tri.error).any() else 0
            sigma = 2.5 * float(np.nan_to_num(med))
        sigmas.append(max(o.min_sigma_px, sigma))
        single.append(bool((np.asarray(obs.rows >= 0).sum(1) < 2).all()))

    lengths = [len(d.frames) for d in dense]
    offsets = np.cumsum([0] + lengths)
    prev = np.concatenate(
        [
            np.where(np.r_[False, np.diff(d.frames) == 1], np.arange(len(d.frames)) - 1 + off, -1)
            for d, off in zip(dense, offsets[:-1], strict=True)
        ]
    )

    def cat(name: str) -> torch.Tensor:
        return torch.as_tensor(np.concatenate([getattr(d, name) for d in dense]), dtype=dtype)

    conf = cat("confidence")
    uv = cat("uv")
    weight = torch.where(
        (conf >= o.min_confidence) & torch.isfinite(uv).all(-1), conf, torch.zeros_like(conf)
    )
    batch = _Batch(
        person=torch.as_tensor(np.repeat(np.arange(len(dense)), lengths)),
        K=cat("K"),
        Rt=cat("Rt"),
        uv=torch.nan_to_num(uv),
        weight=weight,
        scale=cat("px_scale"),
        prev=torch.as_tensor(prev),
        sigma=torch.as_tensor(np.repeat(sigmas, lengths), dtype=dtype),
    )
    B = int(offsets[-1])
    R0 = torch.as_tensor(np.concatenate([s[0] for s in starts]), dtype=dtype)
    root6d = matrix_to_rot6d(R0).clone()
    transl = torch.as_tensor(np.concatenate([s[1] for s in starts]), dtype=dtype).clone()
    pose = torch.zeros(B, 69, dtype=dtype)
    betas = torch.zeros(len(dense), o.num_betas, dtype=dtype)
    if start is not None:
        if [len(f.frames) for f in start] != lengths:
            raise ValueError("fit_people: `start` must cover the same people and frames")
        betas = torch.as_tensor(np.stack([f.betas for f in start]), dtype=dtype).clone()
        cat_start = lambda k: torch.as_tensor(  # noqa: E731
            np.concatenate([getattr(f, k) for f in start]), dtype=dtype
        )
        root6d = matrix_to_rot6d(axis_angle_to_matrix(cat_start("global_orient"))).clone()
        pose = cat_start("body_pose").reshape(B, 69).clone()
        transl = cat_start("transl").clone()
    lo, hi = _limits_tensor(body)

    def energy(params_betas, params_root, params_pose, params_transl):
        _, _, _, reproj, smooth, limits, prior = _objective_terms(
            body, markers, batch, params_betas, params_root, params_pose, params_transl,
            o, fps, lo, hi,
        )  # fmt: skip
        frame = reproj + o.w_smooth * smooth + o.w_limits * limits + o.w_pose * prior
        return frame.mean() + o.w_betas * params_betas.pow(2).sum(-1).mean()

    def run(params: list[torch.Tensor], iterations: int) -> None:
        for p in params:
            p.requires_grad_(True)
        opt = torch.optim.LBFGS(
            params, lr=1.0, max_iter=iterations, history_size=20,
            line_search_fn="strong_wolfe", tolerance_grad=1e-7, tolerance_change=1e-10,
        )  # fmt: skip

        def closure():
            opt.zero_grad()
            e = energy(betas, root6d, pose, transl)
            e.backward()
            return e

        opt.step(closure)
        for p in params:
            p.requires_grad_(False)

    if o.init_iterations and start is None:
        run([root6d, transl], o.init_iterations)
    run([betas, root6d, pose, transl], o.iterations)

    with torch.no_grad():
        out, X, r, *_ = _objective_terms(
            body, markers, batch, betas, root6d, pose, transl, o, fps, lo, hi
        )
        root = rot6d_to_matrix(root6d)
        go = matrix_to_axis_angle(root)
        observed_px = torch.where(batch.weight > 0, r, torch.full_like(r, float("nan")))
    results = []
    for k, d in enumerate(dense):
        a, b = offsets[k], offsets[k + 1]
        results.append(
            PersonFit(
                person_id=d.person_id,
                frames=d.frames,
                betas=betas[k].double().numpy(),
                global_orient=go[a:b].double().numpy(),
                body_pose=pose[a:b].reshape(-1, 23, 3).double().numpy(),
                transl=transl[a:b].double().numpy(),
                joints=out.joints[a:b].double().numpy(),
                markers=X[a:b].double().numpy(),
                reprojection=observed_px[a:b].double().numpy(),
                observed=(d.rows >= 0).any(1),
                static=statics[k],
                single_view=single[k],
                sigma_px=sigmas[k],
            )
        )
    return results


def _dense_tri(
    tri: PersonTriangulation, frames: np.ndarray, dense: np.ndarray
) -> PersonTriangulation:
    if len(frames) == len(dense):
        return tri
    idx = np.searchsorted(frames, dense)
    have = np.isin(dense, frames)
    src = np.where(have, idx, 0)

    def take(a: np.ndarray, fill) -> np.ndarray:
        out = a[src].copy()
        out[~have] = fill
        return out

    return PersonTriangulation(
        take(tri.points, np.nan),
        take(tri.used, False),
        take(tri.errors, np.nan),
        take(tri.error, np.nan),
        take(tri.confidence, 0.0),
    )

"""Robust, batched N-view triangulation of 2D landmarks, each view with its own camera.

Every observation carries its own camera (a crop's `K_crop` with the camera's R, t), so the
cameras are per point: `K (N, C, 3, 3)` and `Rt (N, C, 3, 4)`. The steps, all batched over the
N points (numpy):

1. confidence-weighted DLT in normalised coordinates (x = K^-1 [u, v, 1] against [R | t]),
   which keeps the homogeneous system well conditioned whatever the pixel scale;
2. pair consensus (optional, `consensus_views`; a RANSAC that tries every hypothesis): for a
   point seen by 3 or more views, every pair of its `consensus_views` most confident views is
   triangulated alone, and the pair whose point the most views see within `outlier_px` wins
   (ties: more confidence, then smaller errors); its agreeing views are kept. Leave-one-out
   alone cannot undo two wrong views out of six: the all-view point is dragged by both, and
   dropping either one still leaves the other (on the demo, a kicking leg's ankle wrong in 2 of
   6 views landed 0.5 m off);
3. leave-one-out rejection: while a point's worst used view misses by more than
   `outlier_px` and more than 2 views remain, every subset that drops one view is solved and
   the one whose own worst error is smallest is kept (an outlier view drags the all-view DLT
   towards itself, so the view with the largest residual is not necessarily the bad one);
4. Gauss-Newton refinement of the confidence-weighted reprojection error over the kept views.

Per point it records the views used, the reprojection error (in the observation's `px_scale`
units: full-image pixels when `px_scale` = crop side / crop size) and a confidence.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

__all__ = [
    "TriangulationOptions",
    "Triangulated",
    "PersonTriangulation",
    "triangulate_points",
    "triangulate_person",
    "project",
    "neighbour_mean",
]


@dataclass(frozen=True)
class TriangulationOptions:
    min_confidence: float = 0.3  # observations below it are not used
    outlier_px: float = 12.0  # worst-view error (px_scale units) above which a view is dropped
    # ... counted in crop pixels where a crop is larger than its stored size (px_scale > 1): the
    # landmark model's noise is about constant in crop pixels, and a fixed 12 full-image px
    # dropped good views of close or high-resolution cameras (px_scale 4: 45 % of clean points
    # lost a view, 3D error +26 %)
    outlier_scales_with_crop: bool = True
    # the widest angle between the used views' rays to the point under which its confidence is
    # scaled down (by angle / this): two cameras facing each other see a point near the line
    # through them along one ray, which it slides along without moving in either image
    # (within 5 cm of that line: median 0.5 m off, at full two-view confidence)
    min_ray_angle_deg: float = 5.0
    max_rejections: int = 2  # leave-one-out rounds
    refine_iterations: int = 5  # Gauss-Newton steps
    # pair hypotheses among this many most confident views of a point (0: no pair consensus).
    # Off here; the fusion turns it on with the people's silhouettes as votes
    # (gst.fuse.scene.FuseOptions, docs/fuse.md "Silhouettes"): alone it is no better on the
    # crowd scenes on average, with the silhouettes it is better on every scene measured.
    consensus_views: int = 0
    # with silhouettes (gst.fuse.silhouettes): each view whose people cover a hypothesis's
    # projection counts this much beside each view whose landmark agrees with it
    silhouette_weight: float = 1.0
    # > 0 (with triangulate_person): a second pass in which a hypothesis at the mean of the
    # point's neighbours in time (the first pass's, at frames t - 1 and t + 1) counts this much
    # more, less the farther it lies, nothing from `temporal_radius_m` on: a frame whose views
    # split evenly follows the frames around it
    temporal_weight: float = 0.0
    temporal_radius_m: float = 0.15


@dataclass
class Triangulated:
    """Batched result for N points seen by up to C views."""

    points: np.ndarray  # (N, 3) world; NaN where fewer than 2 views were usable
    used: np.ndarray  # (N, C) bool, the views kept
    errors: np.ndarray  # (N, C) reprojection error of every observed view (NaN: unobserved)
    error: np.ndarray  # (N,) mean error over the used views (NaN: not triangulated)
    confidence: np.ndarray  # (N,) in [0, 1]; 0 where not triangulated

    @property
    def n_views(self) -> np.ndarray:
        return self.used.sum(axis=1)


def project(P: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (..., C, 2) and depths (..., C) of points X (..., 3) through P (..., C, 3, 4)."""
    Xh = np.concatenate([X, np.ones_like(X[..., :1])], axis=-1)
    x = np.einsum("...cij,...j->...ci", P, Xh)
    z = x[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return x[..., :2] / z[..., None], z


def _dlt(Pn: np.ndarray, xn: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted DLT: Pn (N, C, 3, 4), xn (N, C, 2), w (N, C) >= 0 -> (N, 3) (NaN if < 2 views).
    Each view's rows are scaled by its w, so the algebraic least squares weighs it by w squared
    (the Gauss-Newton refinement by w): it leans harder on confident views for the start and
    the leave-one-out decisions."""
    rows_x = xn[..., 0:1] * Pn[..., 2, :] - Pn[..., 0, :]
    rows_y = xn[..., 1:2] * Pn[..., 2, :] - Pn[..., 1, :]
    A = np.concatenate([rows_x, rows_y], axis=-2) * np.concatenate([w, w], axis=-1)[..., None]
    A = np.nan_to_num(A)
    _, _, vt = np.linalg.svd(A)
    Xh = vt[..., -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[..., :3] / Xh[..., 3:4]
    X[(w > 0).sum(-1) < 2] = np.nan
    return X


MIN_DEPTH_M = 0.05  # a triangulated point nearer a camera that placed it is no point


def _errors(P: np.ndarray, uv: np.ndarray, X: np.ndarray, scale: np.ndarray) -> np.ndarray:
    return _errors_at(*project(P, X), uv, scale)


def _errors_at(proj, z, uv, scale) -> np.ndarray:
    """Reprojection errors of projections `proj` at depths `z` against `uv`, times `scale`."""
    err = np.linalg.norm(proj - uv, axis=-1) * scale
    return np.where(z > 0, err, np.inf)  # behind a camera: never acceptable


def _pair_consensus(
    P,
    Pn,
    xn,
    uv,
    conf,
    seen,
    scale,
    o: TriangulationOptions,
    silhouettes=None,
    expected=None,
    chunk=4096,
) -> np.ndarray:
    """(N, C) views to keep: those that agree with the best two-view hypothesis of each point
    seen by 3 or more views (the rest keep every seen view). With `silhouettes`
    (ViewSilhouettes of the N points), the views whose people cover a hypothesis vote for it
    too (`o.silhouette_weight` each): evidence that does not come from the landmarks."""
    outlier_px, max_views = o.outlier_px, o.consensus_views
    used = seen.copy()
    todo = np.flatnonzero(seen.sum(1) >= 3)
    V = min(max_views, seen.shape[1])
    if not len(todo) or V < 3:
        return used
    C = seen.shape[1]
    pairs = np.array(list(itertools.combinations(range(V), 2)))  # (Q, 2) ranks
    for start in range(0, len(todo), chunk):
        idx = todo[start : start + chunk]
        n = np.arange(len(idx))[:, None, None]
        rank = np.argsort(-np.where(seen[idx], conf[idx], -1.0), axis=1, kind="stable")[:, :V]
        views = rank[:, pairs]  # (n, Q, 2) view indices of each hypothesis
        ok = seen[idx][n, views].all(-1)  # (n, Q): both views really seen
        X = _dlt(Pn[idx][n, views], xn[idx][n, views], conf[idx][n, views] * ok[..., None])
        at, z = project(P[idx][:, None], X)  # (n, Q, C, 2), (n, Q, C)
        err = _errors_at(at, z, uv[idx][:, None], scale[idx][:, None])
        agree = (err <= outlier_px) & seen[idx][:, None] & ok[..., None]  # (n, Q, C)
        count = agree.sum(-1).astype(np.float64)
        if silhouettes is not None:
            covered = silhouettes.covered(idx, at) & (z > 0)
            count += o.silhouette_weight * covered.sum(-1)
        if expected is not None:  # a soft vote: whole at the expectation, none at the radius
            d = np.linalg.norm(X - expected[idx][:, None], axis=-1) / o.temporal_radius_m
            count += o.temporal_weight * np.nan_to_num(np.clip(1 - d, 0, 1))  # NaN: no idea
        # most agreeing views; then the most confidence (< 1 view's worth); then small errors
        key = (
            count
            + 0.5 * (agree * conf[idx][:, None]).sum(-1) / C
            - 0.01
            * np.where(seen[idx][:, None], np.minimum(err, outlier_px), 0).sum(-1)
            / (C * outlier_px)
        )
        key = np.where(ok & np.isfinite(X).all(-1), key, -np.inf)
        best = key.argmax(1)
        win = agree[np.arange(len(idx)), best]  # (n, C)
        good = win.sum(1) >= 2
        used[idx[good]] = win[good]
    return used


def _refine(P, uv, w, X, iterations: int) -> np.ndarray:
    """Gauss-Newton on sum_c w_c |proj_c(X) - uv_c|^2 (batched 3x3 normal equations)."""
    ok = np.isfinite(X).all(-1)
    X = X.copy()
    for _ in range(iterations):
        Xh = np.concatenate([X, np.ones_like(X[..., :1])], -1)
        x = np.einsum("ncij,nj->nci", P, np.nan_to_num(Xh))
        z = x[..., 2:3]
        z = np.where(np.abs(z) < 1e-9, 1e-9, z)
        r = x[..., :2] / z - uv  # (N, C, 2)
        # d(x_i / z)/dX = (P_i - (x_i / z) P_2)[:3] / z
        J = (P[..., :2, :3] - (x[..., :2] / z)[..., None] * P[..., 2:3, :3]) / z[..., None]
        W = np.nan_to_num(w)[..., None, None]
        H = np.einsum("ncki,nckj->nij", J * W, J)
        g = np.einsum("ncki,nck->ni", J * W, np.nan_to_num(r))
        # damping relative to H's own scale: views through one centre leave H singular there
        trace = np.trace(H, axis1=-2, axis2=-1)[..., None, None]
        H = H + (1e-9 * trace / 3 + 1e-12) * np.eye(3)
        step = np.linalg.solve(H[ok], g[ok][..., None])[..., 0]
        X[ok] = X[ok] - step
    return X


def triangulate_points(
    K: np.ndarray,
    Rt: np.ndarray,
    uv: np.ndarray,
    confidence: np.ndarray,
    px_scale: np.ndarray | None = None,
    options: TriangulationOptions | None = None,
    silhouettes=None,
    expected: np.ndarray | None = None,
) -> Triangulated:
    """Triangulate N points from C views.

    Args:
        K: (N, C, 3, 3) intrinsics of each observation (e.g. the crop's K_crop) and
        Rt: (N, C, 3, 4) its world-to-camera [R | t]; any finite values where unobserved.
        uv: (N, C, 2) pixels in the image P maps to; NaN where unobserved.
        confidence: (N, C) detection confidence in [0, 1]; 0 or NaN where unobserved.
        px_scale: (N, C) factor turning those pixels into reported pixels (e.g. a crop's
            side / size gives full-image pixels); default 1.
        silhouettes: a gst.fuse.silhouettes.ViewSilhouettes of the N points (their views'
            coverage by people, in the pixels of `uv`): votes in the pair consensus.
        expected: (N, 3) where each point is expected (NaN: no idea), e.g. from its neighbours
            in time: a vote of `temporal_weight` in the pair consensus.
    """
    o = options or TriangulationOptions()
    K = np.asarray(K, np.float64)
    Rt = np.asarray(Rt, np.float64)
    uv = np.asarray(uv, np.float64)
    conf = np.nan_to_num(np.asarray(confidence, np.float64))
    N, C = uv.shape[:2]
    if K.shape != (N, C, 3, 3) or Rt.shape != (N, C, 3, 4) or conf.shape != (N, C):
        raise ValueError(
            f"triangulate_points: K {K.shape}, Rt {Rt.shape}, uv {uv.shape} and confidence "
            f"{conf.shape} must be (N, C, 3, 3), (N, C, 3, 4), (N, C, 2) and (N, C)"
        )
    scale = np.ones((N, C)) if px_scale is None else np.asarray(px_scale, np.float64)
    # A view whose camera is not numbers is no evidence, and must not turn the others' sums NaN.
    calibrated = np.isfinite(K).all((-1, -2)) & np.isfinite(Rt).all((-1, -2))
    # nor is one whose K has no inverse (a zero focal length): no ray, and K^-1 below would fail
    # the whole batch with a bare 'Singular matrix'
    det_K = np.linalg.det(np.where(calibrated[..., None, None], K, np.eye(3)))
    calibrated &= np.abs(det_K) > 1e-12
    # a zero-confidence view weighs nothing in the DLT and the refinement: not seen, whatever
    # min_confidence (at 0 it counted as used and diluted the point's confidence)
    seen = np.isfinite(uv).all(-1) & (conf >= o.min_confidence) & (conf > 0) & calibrated
    uv0 = np.where(seen[..., None], uv, 0.0)
    # DLT rows in normalised coordinates (K^-1 [u, v, 1] against [R | t]): well conditioned.
    safe_K = np.where(calibrated[..., None, None], K, np.eye(3))
    Pn = np.where(calibrated[..., None, None], Rt, np.eye(3, 4))
    P = safe_K @ Pn
    xh = np.linalg.solve(safe_K, np.concatenate([uv0, np.ones((N, C, 1))], -1)[..., None])[..., 0]
    xn = xh[..., :2] / xh[..., 2:3]
    used = seen.copy()
    # the errors the outlier tests read: full-image px, or crop px on crops larger than stored
    test_scale = np.minimum(scale, 1.0) if o.outlier_scales_with_crop else scale
    if o.consensus_views:
        used = _pair_consensus(P, Pn, xn, uv0, conf, seen, test_scale, o, silhouettes, expected)
    X = _dlt(Pn, xn, np.where(used, conf, 0.0))
    for _ in range(o.max_rejections):
        err = np.where(used, _errors(P, uv0, X, test_scale), 0.0)
        worst = err.max(axis=1, initial=0.0)
        todo = np.flatnonzero((worst > o.outlier_px) & (used.sum(1) > 2))
        if not len(todo):
            break
        # (n, C candidates dropped, C views) weights: each candidate leaves one used view out.
        cand = used[todo][:, None, :] & ~np.eye(C, dtype=bool)[None]
        Xc = _dlt(
            np.repeat(Pn[todo][:, None], C, 1),
            np.repeat(xn[todo][:, None], C, 1),
            np.where(cand, conf[todo][:, None], 0.0),
        )
        ec = _errors(
            np.repeat(P[todo][:, None], C, 1),
            np.repeat(uv0[todo][:, None], C, 1),
            Xc,
            np.repeat(test_scale[todo][:, None], C, 1),
        )
        ec = np.where(cand, ec, 0.0).max(-1)
        ec = np.where(used[todo] & np.isfinite(Xc).all(-1), ec, np.inf)
        best = ec.argmin(1)
        gain = ec[np.arange(len(todo)), best] < worst[todo]
        rows, drop = todo[gain], best[gain]
        used[rows, drop] = False
        X[rows] = Xc[gain, drop]
    X = _refine(P, uv0, np.where(used, conf, 0.0), X, o.refine_iterations)
    X[used.sum(1) < 2] = np.nan
    # in front of every view that placed it (views through one centre put it on the centre)
    depth = project(P, np.nan_to_num(X))[1]
    X[(used & ~(depth > MIN_DEPTH_M)).any(1)] = np.nan
    # No point (one view, or degenerate geometry): nothing was triangulated, so no view counts
    # as used (else its error would read 0, its confidence full, and a landmark seen by one
    # camera would count as triangulated from it in the Parquet files and the report)
    used[~np.isfinite(X).all(-1)] = False
    errors = np.where(seen, _errors(P, uv0, np.nan_to_num(X), scale), np.nan)
    errors[~np.isfinite(X).all(-1)] = np.nan
    n_used = used.sum(1)
    with np.errstate(invalid="ignore"):
        error = np.where(n_used >= 2, np.nansum(np.where(used, errors, 0), 1) / n_used, np.nan)
        mean_conf = np.where(n_used > 0, (conf * used).sum(1) / np.maximum(n_used, 1), 0.0)
    # Confidence: the detections' own, discounted for few views and for a poor fit (the fit in
    # the outlier tests' units: the reported errors, full-image px, scaled as `test_scale` is)
    with np.errstate(invalid="ignore"):
        ratio = np.divide(test_scale, scale, out=np.ones_like(scale), where=scale != 0)
        tested = np.where(used, errors * ratio, 0.0)
        fit = np.where(n_used >= 2, tested.sum(1) / np.maximum(n_used, 1), np.nan)
    confidence_out = mean_conf * np.clip((n_used - 1) / 2, 0, 1)
    if o.min_ray_angle_deg > 0:
        angle = _widest_ray_angle_deg(Rt, np.nan_to_num(X), used)
        confidence_out *= np.clip(angle / o.min_ray_angle_deg, 0, 1)
    confidence_out *= np.exp(
        -np.square(np.minimum(np.nan_to_num(fit, nan=1e6), 1e6) / o.outlier_px)
    )
    return Triangulated(X, used, errors, error, np.nan_to_num(confidence_out))


def _widest_ray_angle_deg(Rt: np.ndarray, X: np.ndarray, used: np.ndarray) -> np.ndarray:
    """(N,) the widest angle (degrees, 0-90) between the lines from the used cameras' centres
    to each point (0 with fewer than two used views): lines, not rays, since a point between two
    cameras facing each other is seen along rays 180 degrees apart."""
    R, t = Rt[..., :3], Rt[..., 3]
    centres = -np.einsum("ncji,ncj->nci", np.nan_to_num(R), np.nan_to_num(t))  # -R^T t
    rays = X[:, None] - centres
    rays /= np.maximum(np.linalg.norm(rays, axis=-1, keepdims=True), 1e-12)
    cos = np.abs(np.einsum("nci,ndi->ncd", rays, rays))
    pair = used[:, :, None] & used[:, None, :]
    return np.degrees(np.arccos(np.clip(np.where(pair, cos, 1.0), 0, 1).min((1, 2))))


@dataclass
class PersonTriangulation:
    """Triangulated landmarks of one person: T frames, M landmarks, C cameras."""

    points: np.ndarray  # (T, M, 3) world, NaN where < 2 views
    used: np.ndarray  # (T, M, C) bool
    errors: np.ndarray  # (T, M, C) full-image px, NaN where unobserved
    error: np.ndarray  # (T, M) mean over used views
    confidence: np.ndarray  # (T, M)

    @property
    def n_views(self) -> np.ndarray:
        return self.used.sum(-1)


def triangulate_person(
    obs, options: TriangulationOptions | None = None, silhouettes=None
) -> PersonTriangulation:
    """Triangulate every landmark of a `gst.fuse.observations.PersonObservations`;
    `silhouettes`: the store's gst.fuse.silhouettes.CropSilhouettes (votes in the pair
    consensus), or None."""
    T, C, M = obs.uv.shape[:3]

    def per_point(a: np.ndarray) -> np.ndarray:  # (T, C, ...) camera -> (T * M, C, ...)
        return np.repeat(a[:, None], M, 1).reshape(T * M, C, *a.shape[2:])

    K, Rt = per_point(obs.K), per_point(obs.Rt)
    uv = np.moveaxis(obs.uv, 2, 1).reshape(T * M, C, 2)
    conf = np.moveaxis(obs.confidence, 2, 1).reshape(T * M, C)
    scale = np.repeat(obs.px_scale[:, None], M, 1).reshape(T * M, C)
    views = None if silhouettes is None else silhouettes.for_views(obs.rows, M)
    tri = triangulate_points(K, Rt, uv, conf, scale, options, views)
    o = options or TriangulationOptions()
    if o.temporal_weight > 0 and o.consensus_views and T >= 3:
        expected = neighbour_mean(tri.points.reshape(T, M, 3), np.asarray(obs.frames))
        tri = triangulate_points(K, Rt, uv, conf, scale, o, views, expected.reshape(T * M, 3))
    return PersonTriangulation(
        tri.points.reshape(T, M, 3),
        tri.used.reshape(T, M, C),
        tri.errors.reshape(T, M, C),
        tri.error.reshape(T, M),
        tri.confidence.reshape(T, M),
    )


def neighbour_mean(points: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """(T, M, 3): the mean of each point at the frames just before and after (consecutive
    frames only), NaN where either is missing."""
    out = np.full_like(points, np.nan)
    both = (np.diff(frames)[:-1] == 1) & (np.diff(frames)[1:] == 1)  # t - 1 and t + 1 exist
    mid = np.flatnonzero(both) + 1
    out[mid] = 0.5 * (points[mid - 1] + points[mid + 1])
    return out

"""People as a calibration target: small per-camera rotation corrections from the fitted bodies.

A rig calibrated (or imported) slightly wrong shows in the fit as a systematic offset of one
camera's landmarks against the fused bodies, the same for every person and frame. Holding the
bodies' markers fixed, each camera's rotation about its own centre is corrected by a robust
(Cauchy) Gauss-Newton fit of the reprojection error over every landmark it saw. The fit is
then run again with the corrected cameras (the bodies, fitted by all cameras, are the reference,
so the cameras that agree with each other hold the world in place). `fuse_scene` reports the
corrections in degrees: a large one is a calibration worth redoing.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gst.fuse.fit import PersonFit
from gst.fuse.observations import PersonObservations

__all__ = ["camera_corrections", "apply_corrections", "corrected_rig", "rotation_matrix"]


def _skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rotation_matrix(w: np.ndarray) -> np.ndarray:
    """Axis-angle (3,) -> (3, 3) (Rodrigues)."""
    t = float(np.linalg.norm(w))
    if t < 1e-12:
        return np.eye(3) + _skew(w)
    K = _skew(w / t)
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def camera_corrections(
    fits: list[PersonFit],
    people: list[PersonObservations],
    cameras: int,
    sigma_px: float = 10.0,
    min_confidence: float = 0.5,
    iterations: int = 5,
) -> np.ndarray:
    """(C, 3) rotation corrections (axis-angle, camera frame) that best align every camera's
    landmarks with the fitted markers; zero for a camera with fewer than 50 landmarks (all of
    them where nobody was fitted: the stage's readable people can be none)."""
    C = cameras
    cam_pts, uvs, Ks, scales = ([[] for _ in range(C)], [[] for _ in range(C)],
                                [[] for _ in range(C)], [[] for _ in range(C)])  # fmt: skip
    for f, p in zip(fits, people, strict=True):
        X = f.markers[np.isin(f.frames, p.frames)]  # (T, M, 3) on the observed frames
        cam = np.einsum("tcij,tmj->tcmi", p.Rt[..., :3], X) + p.Rt[:, :, None, :, 3]
        ok = (p.confidence >= min_confidence) & np.isfinite(p.uv).all(-1) & (cam[..., 2] > 0)
        for c in range(C):
            t, m = np.nonzero(ok[:, c])
            cam_pts[c].append(cam[t, c, m])
            uvs[c].append(p.uv[t, c, m])
            Ks[c].append(p.K[t, c])
            scales[c].append(p.px_scale[t, c])
    out = np.zeros((C, 3))
    for c in range(C):
        if sum(len(a) for a in cam_pts[c]) < 50:
            continue
        Xc = np.concatenate(cam_pts[c])
        uv, K, s = np.concatenate(uvs[c]), np.concatenate(Ks[c]), np.concatenate(scales[c])
        w = np.zeros(3)
        for _ in range(iterations):
            Y = Xc @ rotation_matrix(w).T
            q = np.einsum("nij,nj->ni", K, Y)
            p = q[:, :2] / q[:, 2:]
            r = (p - uv) * s[:, None]
            # d p / d Y = (K[:2] - p e3^T) / z ; d Y / d w = -[Y]x
            D = (K[:, :2, :] - p[:, :, None] * np.array([0.0, 0.0, 1.0])) / Y[:, 2, None, None]
            J = -np.einsum("nki,nij->nkj", D, np.stack([_skew(y) for y in Y])) * s[:, None, None]
            wt = 1.0 / (1.0 + (r**2).sum(-1) / sigma_px**2)
            H = np.einsum("nki,n,nkj->ij", J, wt, J)
            g = np.einsum("nki,n,nk->i", J, wt, r)
            dw = -np.linalg.solve(H + 1e-6 * np.eye(3), g)
            w = (rotation_matrix(dw) @ rotation_matrix(w)).dot(np.eye(3))
            w = _log(w)
        out[c] = w
    return out


def _log(R: np.ndarray) -> np.ndarray:
    cos = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    t = np.arccos(cos)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return v / 2 if t < 1e-9 else v * t / (2 * np.sin(t))


def apply_corrections(people: list[PersonObservations], corrections: np.ndarray) -> None:
    """Turn every camera about its centre: [R | t] <- exp(w) [R | t], in place."""
    Rw = np.stack([rotation_matrix(w) for w in corrections])  # (C, 3, 3)
    for p in people:
        p.Rt[:] = np.einsum("cij,tcjk->tcik", Rw, p.Rt)


def corrected_rig(rig, names: list[str], corrections: np.ndarray):
    """The calibration.Rig with cameras `names` turned by `corrections` (C, 3) as in the fit;
    its up axis and metadata are the rig's (a Y-down Panoptic world stays Y-down)."""
    turned = {n: rotation_matrix(w) for n, w in zip(names, corrections, strict=True)}
    return dataclasses.replace(
        rig,
        cameras=tuple(
            cam.replace(R=turned[cam.name] @ cam.R, t=turned[cam.name] @ cam.t)
            if cam.name in turned
            else cam
            for cam in rig
        ),
    )

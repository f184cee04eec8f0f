"""Compare an estimated rig with a reference rig, up to the choice of world frame.

A solved rig lives in its own world (e.g. the board's first pose), so it is first aligned to
the reference with the similarity transform that best maps its camera centres onto the
reference centres (Umeyama). Scale is fitted only when asked: a metric solve should not need it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.camera import Rig


@dataclass(frozen=True)
class RigComparison:
    names: list[str]
    focal_rel_error: np.ndarray  # (C,) max(|fx - fx_ref|/fx_ref, |fy - fy_ref|/fy_ref)
    center_error_m: np.ndarray  # (C,) after alignment, metres
    rotation_error_deg: np.ndarray  # (C,) angle of R_est_aligned R_ref^T
    rig_diameter_m: float  # max distance between reference camera centres
    scale: float  # fitted scale (1 when not fitted)

    def as_rows(self) -> list[dict]:
        return [
            dict(
                camera=n,
                focal_rel_error=float(f),
                center_error_m=float(c),
                rotation_error_deg=float(r),
            )
            for n, f, c, r in zip(
                self.names,
                self.focal_rel_error,
                self.center_error_m,
                self.rotation_error_deg,
                strict=True,
            )
        ]


def umeyama(
    src: np.ndarray, dst: np.ndarray, with_scale: bool
) -> tuple[float, np.ndarray, np.ndarray]:
    """s, R, t minimising sum |s R src_i + t - dst_i|^2 (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / xs.var(0).sum()) if with_scale else 1.0
    return s, R, mu_d - s * R @ mu_s


def compare_rigs(estimate: Rig, reference: Rig, fit_scale: bool = False) -> RigComparison:
    names = [n for n in reference.names if n in estimate.names]
    if len(names) < 3:
        raise ValueError(f"need at least 3 shared cameras to align rigs, found {names}")
    est = [estimate[n] for n in names]
    ref = [reference[n] for n in names]
    c_est = np.stack([c.center for c in est])
    c_ref = np.stack([c.center for c in ref])
    s, Ra, ta = umeyama(c_est, c_ref, fit_scale)
    center_err = np.linalg.norm((s * c_est @ Ra.T + ta) - c_ref, axis=1)
    rot_err = []
    for e, r in zip(est, ref, strict=True):
        # world_ref = s Ra world_est + ta, so the estimated camera in reference world has R_e Ra^T.
        delta = (e.R @ Ra.T) @ r.R.T
        rot_err.append(np.degrees(np.arccos(np.clip((np.trace(delta) - 1) / 2, -1, 1))))
    focal = [
        max(abs(e.fx - r.fx) / r.fx, abs(e.fy - r.fy) / r.fy) for e, r in zip(est, ref, strict=True)
    ]
    diam = float(max(np.linalg.norm(a - b) for a in c_ref for b in c_ref))
    return RigComparison(names, np.array(focal), center_err, np.array(rot_err), diam, s)

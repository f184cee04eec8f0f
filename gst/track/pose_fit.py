"""Fit each network body's pose to its crop's 2D landmarks (a short single-view refinement).

A single-image network regresses joint rotations down the kinematic chain, so small errors at
the hips and shoulders add up at the wrists and ankles: on footage unlike its training crops its
skeleton lies beside the person (the lab capture with the demo's model: the 13 compared joints a
median 15 crop px, about 40-60 px at 1088x1920, from the landmarks). The landmark model's 2D
points are sharper evidence for where the limbs are. `PoseFitter` moves the body's virtual
markers (gst.body.markers: where each BlazePose landmark lies on the body) onto the confident
landmarks: robust (Geman-McClure) reprojection in crop pixels, weighted by confidence, plus a
prior that keeps every local joint rotation near the network's (`pose_prior` per rad^2), over
the global orientation, the local rotations and the translation (the shape stays the
network's). Levenberg-Marquardt with the skeleton's analytic Jacobian (gst.body.kinematics),
batched over the crops: about 2-7 ms per crop on one core. Depth stays the network's (the fit
moves the translation across the image only; fitted to 2D scale it followed the pose being
fitted), as in SPIN-style refinement; the prior decides how far 2D evidence may bend a limb.

Measured (docs/track_evaluation.md, "Pose fit"): on the lab capture the demo's model agrees with
the rig's fused bodies 166.5 / 101.2 -> 132.5 / 87.4 mm (MPJPE / PA-MPJPE, root-aligned, 800
crops) and its joints lie 15.0 -> 4.2 crop px from the landmarks; on the demo's held-out frames
109.0 / 62.8 -> 104.4 / 65.9 mm; on synthetic crowds of 3-5 people it moves MPJPE by -1.4 to
+8.1 mm (occluded people's landmarks mislead it as often as they help), so `track` fits by
default only videos that are no calibrated camera of the scene (`track.fit_pose`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from gst.body.kinematics import N_POSE_PARAMS, MarkerSkeleton
from gst.body.markers import MarkerModel
from gst.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from gst.track.agreement import COMPARED_INDEX, landmark_targets

__all__ = ["PoseFitConfig", "PoseFitter", "FittedPoses", "disagreement"]

DEPTH = 5  # the fit's parameter index of the translation's z (camera depth)


@dataclass(frozen=True)
class PoseFitConfig:
    iterations: int = 8  # Levenberg-Marquardt steps
    pose_prior: float = 10.0  # per rad^2 of change of each local joint rotation
    sigma: float = 0.03  # robust scale: this share of the crop size
    min_confidence: float = 0.5  # landmarks below this are no evidence
    min_landmarks: int = 8  # fewer confident landmarks: the body stays the network's
    # only bodies whose compared joints lie a median of more than this share of the crop from
    # the landmarks are fitted (0: every body). Where the network already agrees with them the
    # fit has little to gain and occluded landmarks to lose by: 0.03 (at prior 30) halves its
    # loss on synthetic crowds and keeps most of its gain on the lab (docs/track_evaluation.md).
    min_disagreement: float = 0.0

    def __post_init__(self):
        if self.iterations < 1 or self.sigma <= 0:
            raise ValueError(f"PoseFitConfig: iterations and sigma must be > 0: {self}")
        if self.pose_prior < 0 or self.min_landmarks < 1 or self.min_disagreement < 0:
            raise ValueError(
                f"PoseFitConfig: pose_prior, min_disagreement >= 0, min_landmarks >= 1: {self}"
            )


@dataclass
class FittedPoses:
    """The fitted bodies (numpy, float32), and which crops were fitted (B,) bool."""

    rotmats: np.ndarray  # (B, 24, 3, 3); [:, 0] the global orientation in the crop's camera
    transl_cam: np.ndarray  # (B, 3)
    joints_cam: np.ndarray  # (B, 24, 3)
    fitted: np.ndarray  # (B,)


def disagreement(
    joints_cam: np.ndarray, K_crop: np.ndarray, landmarks: np.ndarray, min_confidence: float = 0.5
) -> np.ndarray:
    """(B,) median distance (crop px) of each body's projected joints from the landmarks of the
    same joints at least `min_confidence` sure (gst.track.agreement's 13 pairs); 0 with fewer
    than 4."""
    target, w = landmark_targets(landmarks, min_confidence)
    X = np.asarray(joints_cam, np.float64)[:, COMPARED_INDEX]
    z = np.maximum(X[..., 2:], 1e-3)
    uv = np.einsum("bij,bnj->bni", np.asarray(K_crop, np.float64), X / z)[..., :2]
    d = np.where(w > 0, np.linalg.norm(uv - target, axis=-1), np.nan)
    enough = (w > 0).sum(1) >= 4
    out = np.zeros(len(X))
    if enough.any():
        out[enough] = np.nanmedian(d[enough], axis=1)
    return out


class PoseFitter:
    """Fits bodies of one body model (SMPL layout) to BlazePose's 33 landmarks."""

    def __init__(self, body, config: PoseFitConfig = PoseFitConfig(), num_betas: int = 10):
        self.config = config
        self.markers = MarkerModel.load()
        self.skeleton = MarkerSkeleton(body, self.markers, num_betas, dtype=torch.float32)
        self.num_betas = num_betas

    def __call__(
        self,
        rotmats: np.ndarray,
        betas: np.ndarray,
        transl_cam: np.ndarray,
        joints_cam: np.ndarray,
        K_crop: np.ndarray,
        landmarks: np.ndarray,
        crop_size: int,
    ) -> FittedPoses:
        """rotmats (B, 24, 3, 3), betas (B, >= num_betas), transl_cam (B, 3), joints_cam
        (B, 24, 3), K_crop (B, 3, 3), landmarks (B, 33, 3: u, v crop px + confidence, NaN where
        none) -> fitted poses (unfitted bodies as they came)."""
        c = self.config
        B = len(rotmats)
        lm = np.asarray(landmarks, np.float32)
        if lm.shape != (B, len(self.markers), 3):
            raise ValueError(f"landmarks must be ({B}, {len(self.markers)}, 3), got {lm.shape}")
        conf = np.nan_to_num(lm[..., 2], nan=0.0)
        conf = np.where(np.isfinite(lm[..., :2]).all(-1) & (conf >= c.min_confidence), conf, 0.0)
        use = (conf > 0).sum(1) >= c.min_landmarks
        if c.min_disagreement > 0:  # 0: every body (disagreement() reads 0 where unmeasured)
            use &= (
                disagreement(joints_cam, K_crop, lm, c.min_confidence)
                > c.min_disagreement * crop_size
            )
        out = FittedPoses(
            np.asarray(rotmats, np.float32).copy(),
            np.asarray(transl_cam, np.float32).copy(),
            np.asarray(joints_cam, np.float32).copy(),
            use,
        )
        if not use.any():
            return out
        with torch.inference_mode(False), torch.no_grad():
            i = np.flatnonzero(use)
            beta = torch.as_tensor(np.asarray(betas, np.float32)[i, : self.num_betas])
            R, t = self._fit(
                torch.as_tensor(out.rotmats[i]), beta, torch.as_tensor(out.transl_cam[i]),
                torch.as_tensor(np.asarray(K_crop, np.float32)[i]),
                torch.as_tensor(np.nan_to_num(lm[i, :, :2])), torch.as_tensor(conf[i]), crop_size,
            )  # fmt: skip
            _, J, _, _ = self.skeleton.forward(beta, R[:, 0], matrix_to_axis_angle(R[:, 1:]), t)
        R, t, J = R.numpy(), t.numpy(), J.numpy()
        # a body the solve could not keep finite stays the network's
        ok = np.isfinite(R).all((1, 2, 3)) & np.isfinite(t).all(1) & np.isfinite(J).all((1, 2))
        i = i[ok]
        out.rotmats[i], out.transl_cam[i], out.joints_cam[i] = R[ok], t[ok], J[ok]
        out.fitted = use.copy()
        out.fitted[np.flatnonzero(use)[~ok]] = False
        return out

    def _cost(self, X, theta, theta0, K, uv, conf, sigma):
        """Per crop: robust reprojection (Geman-McClure, confidence-weighted) + pose prior;
        also the normalised residuals (n, M, 2) and the projection."""
        z = X[..., 2:].clamp_min(0.05)
        p = (X / z) @ K.transpose(1, 2)
        r = (p[..., :2] - uv) / sigma
        r2 = (r * r).sum(-1)
        cost = (conf * r2 / (1 + r2)).sum(1) + self.config.pose_prior * ((theta - theta0) ** 2).sum(
            (1, 2)
        )
        return cost, r, r2, z

    def _fit(self, R0, beta, t_root, K, uv, conf, crop_size):
        """Levenberg-Marquardt with the skeleton's analytic Jacobian (gst.body.kinematics),
        the robust kernel by iteratively reweighted least squares; per-crop damping, a step
        that raises a crop's cost is undone and its damping raised."""
        c = self.config
        n = len(R0)
        sigma = c.sigma * crop_size
        theta0 = matrix_to_axis_angle(R0[:, 1:])
        root, theta, t = R0[:, 0].clone(), theta0.clone(), t_root.clone()
        P = N_POSE_PARAMS
        prior = torch.zeros(P)
        prior[6:] = c.pose_prior
        mu = torch.full((n,), 1e-2)
        fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]
        X, _, _, _, dX = self.skeleton.forward(beta, root, theta, t, jacobian=True)
        cost, r, r2, z = self._cost(X, theta, theta0, K, uv, conf, sigma)
        for _ in range(c.iterations):
            w = conf / (1 + r2) ** 2  # IRLS weight of the Geman-McClure kernel
            Xz = X / z
            # d(normalised residual) / d(marker) (n, M, 2, 3)
            Jp = torch.zeros(n, X.shape[1], 2, 3)
            Jp[..., 0, 0] = fx / z[..., 0]
            Jp[..., 0, 2] = -fx * Xz[..., 0] / z[..., 0]
            Jp[..., 1, 1] = fy / z[..., 0]
            Jp[..., 1, 2] = -fy * Xz[..., 1] / z[..., 0]
            J = (Jp / sigma) @ dX[..., :P]  # (n, M, 2, P)
            Jw = J * w[..., None, None]
            H = torch.einsum("nmip,nmiq->npq", Jw, J)
            g = torch.einsum("nmip,nmi->np", Jw, r)
            g[:, 6:] += c.pose_prior * (theta - theta0).reshape(n, -1)
            H = H + torch.diag_embed(prior.expand(n, P))
            H = H + mu[:, None, None] * torch.diag_embed(torch.diagonal(H, dim1=1, dim2=2) + 1e-6)
            # depth stays the network's: 2D evidence alone sets it by the body's apparent size,
            # which the pose being fitted changes (a wrong limb moved it by up to 7 cm)
            H[:, DEPTH, :], H[:, :, DEPTH], g[:, DEPTH] = 0.0, 0.0, 0.0
            H[:, DEPTH, DEPTH] = 1.0
            step = -torch.linalg.solve(H, g)
            root_n = axis_angle_to_matrix(step[:, :3]) @ root
            t_n = t + step[:, 3:6]
            theta_n = theta + step[:, 6:].reshape(n, 23, 3)
            Xn, _, _, _, dXn = self.skeleton.forward(beta, root_n, theta_n, t_n, jacobian=True)
            cost_n, rn, r2n, zn = self._cost(Xn, theta_n, theta0, K, uv, conf, sigma)
            ok = torch.isfinite(cost_n) & (cost_n <= cost)
            k = ok[:, None]
            root = torch.where(ok[:, None, None], root_n, root)
            t = torch.where(k, t_n, t)
            theta = torch.where(ok[:, None, None], theta_n, theta)
            X = torch.where(ok[:, None, None], Xn, X)
            dX = torch.where(ok[:, None, None, None], dXn, dX)
            cost = torch.where(ok, cost_n, cost)
            r = torch.where(ok[:, None, None], rn, r)
            r2 = torch.where(k, r2n, r2)
            z = torch.where(ok[:, None, None], zn, z)
            mu = torch.where(ok, mu * 0.3, mu * 10).clamp(1e-6, 1e6)
        R = R0.clone()
        R[:, 0] = root
        R[:, 1:] = axis_angle_to_matrix(theta)
        return R, t

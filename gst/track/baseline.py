"""A pixel-free baseline predictor: a standing T-pose skeleton placed where the crop says.

It reads only K_crop. The detection box's longer side spans S / 1.2 crop pixels (the crop
convention), so a person of `height_m` standing upright at depth Z = fx_crop * height_m / (S / 1.2)
fills it; the pelvis sits on the ray through the crop centre. Use it to measure the cost of the
tracking loop without a network, and to test tracking and writing end to end.
"""

from __future__ import annotations

import numpy as np

from gst.data.crop import CROP_ENLARGE

# Approximate SMPL-layout rest joints (T-pose, metres, body frame: x = body left, y up, z forward),
# pelvis at the origin; rough adult anthropometry, not taken from any model file.
REST_JOINTS = np.array(
    [
        [0.00, 0.00, 0.00],
        [0.06, -0.09, 0.00],
        [-0.06, -0.09, 0.00],
        [0.00, 0.11, -0.01],
        [0.10, -0.47, 0.00],
        [-0.10, -0.47, 0.00],
        [0.00, 0.24, 0.00],
        [0.09, -0.87, -0.04],
        [-0.09, -0.87, -0.04],
        [0.00, 0.30, 0.02],
        [0.12, -0.93, 0.08],
        [-0.12, -0.93, 0.08],
        [0.00, 0.51, -0.01],
        [0.08, 0.42, 0.00],
        [-0.08, 0.42, 0.00],
        [0.00, 0.58, 0.04],
        [0.18, 0.44, -0.01],
        [-0.18, 0.44, -0.01],
        [0.43, 0.43, -0.03],
        [-0.43, 0.43, -0.03],
        [0.68, 0.44, -0.03],
        [-0.68, 0.44, -0.03],
        [0.76, 0.43, -0.04],
        [-0.76, 0.43, -0.04],
    ]
)

# Upright and facing the camera: body y (up) -> camera -y, body z (forward) -> camera -z.
UPRIGHT_FACING_CAMERA = np.diag([1.0, -1.0, -1.0])


class BoxDepthPredictor:
    """predict(crops, K_crop) -> standing skeleton at the depth the crop size implies."""

    def __init__(self, height_m: float = 1.7, num_betas: int = 10):
        self.height_m = float(height_m)
        self.num_betas = int(num_betas)

    def __call__(self, crops: np.ndarray, K_crop: np.ndarray) -> dict:
        B, S = crops.shape[0], crops.shape[1]
        K_crop = np.asarray(K_crop, dtype=np.float64)
        depth = K_crop[:, 1, 1] * self.height_m / (S / CROP_ENLARGE)
        centre = np.array([(S - 1) / 2.0, (S - 1) / 2.0, 1.0])
        rays = np.linalg.solve(K_crop, np.broadcast_to(centre, (B, 3))[..., None])[..., 0]
        transl = rays / rays[:, 2:3] * depth[:, None]
        rotmats = np.broadcast_to(np.eye(3), (B, 24, 3, 3)).copy()
        rotmats[:, 0] = UPRIGHT_FACING_CAMERA
        joints = REST_JOINTS @ UPRIGHT_FACING_CAMERA.T + transl[:, None]
        return {
            "rotmats": rotmats,
            "betas": np.zeros((B, self.num_betas)),
            "transl_cam": transl,
            "joints_cam": joints,
        }

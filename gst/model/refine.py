"""Reprojection feedback on the landmark path (ours; HMR's iterative error feedback with the
error made explicit, as in learned-gradient-descent body fitting).

The SMPL head regresses rotations, and small rotation errors add up along the limbs: trained on
simulated detections, its body's joints projected back into the crop lay 1.9 % of the crop from
where clean landmarks put them, and 2.4 % from noisy ones (docs/landmark_prior.md, "Reprojection
feedback"). The refiner closes that loop inside the network: it poses the predicted body's
virtual markers (gst.body.markers: where on the body each BlazePose landmark lies), projects them
into the crop with the predicted camera, and a residual MLP reads the confidence-weighted
difference to the input landmarks together with the current parameters and the landmark input,
and returns corrections to pose, shape and camera. `iterations` rounds share the weights; the
last layer starts at zero, so a fresh refiner passes the head's answer through unchanged.

It is part of the network's forward: the output is still the network's own estimate from the
crop's landmarks (no fitting at test time), and samples without usable landmarks keep the
head's output exactly (`GSTNetwork.forward`).

The skeleton (rest joints and their shape directions) and the marker table are buffers, filled
from the body model when the network is built (`set_body`) and saved with it, so a checkpoint
carries what it was trained with; a refiner whose body was never set refuses to run.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from gst.body.kinematics import pose_markers, tree_levels
from gst.body.markers import BLAZEPOSE_NAMES, MarkerModel
from gst.body.model import BodyModel
from gst.body.rotations import rot6d_to_matrix
from gst.body.skeleton import SMPL_PARENTS
from gst.model.landmarks import LandmarkInput, landmark_ids

# rounds the landmark networks are built with (gst.lift.recipe.lift_network): 2 were as good as 3
# and cheaper, 1 clearly less (docs/landmark_prior.md, "Reprojection feedback")
DEFAULT_ROUNDS = 2
_MIN_DEPTH = 0.1  # metres: a body behind or at the camera would divide by ~0


class ReprojectionRefiner(nn.Module):
    """`forward(pose6d (B, 24, 6), betas (B, nb), cam (B, 3), landmarks) -> the same, refined`."""

    # buffers that hold NaN until `set_body` gives them the body's skeleton and markers
    BODY_BUFFERS = ("rest_joints", "shape_joints", "marker_offset")

    def __init__(
        self,
        num_landmarks: int,
        num_betas: int,
        iterations: int,
        width: int = 256,
        blocks: int = 2,
        gravity: bool = True,
    ):
        super().__init__()
        if iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {iterations}")
        self.iterations = iterations
        # read the camera's up direction only where the network does (`landmark_gravity`):
        # callers pass it only to networks that read it (gst.model.inference.accepts_up)
        self.gravity = gravity
        self.num_betas = num_betas
        ids = landmark_ids(num_landmarks)
        n = len(ids)
        nan = math.nan
        self.register_buffer("rest_joints", torch.full((24, 3), nan))
        self.register_buffer("shape_joints", torch.full((24, 3, num_betas), nan))
        self.register_buffer("marker_anchor", torch.zeros(n, dtype=torch.long))
        self.register_buffer("marker_frame", torch.zeros(n, dtype=torch.long))
        self.register_buffer("marker_offset", torch.full((n, 3), nan))
        self._ids = ids
        self.register_buffer(
            "_parent_index", torch.as_tensor([max(p, 0) for p in SMPL_PARENTS]), persistent=False
        )
        for k, (level, par) in enumerate(tree_levels(SMPL_PARENTS)):
            self.register_buffer(f"_level{k}", level, persistent=False)
            self.register_buffer(f"_par{k}", par, persistent=False)
        self._depth = k + 1
        # residual (n x 2) and its weight (n), pose (144), shape, camera, the landmark input
        # (n x 3), the crop's camera (3), the up direction and whether it is known (4)
        inputs = 3 * n + 144 + num_betas + 3 + 3 * n + 3 + 4
        self.inp = nn.Sequential(nn.Linear(inputs, width), nn.GELU())
        self.blocks = nn.ModuleList(
            nn.Sequential(
                nn.LayerNorm(width), nn.Linear(width, width), nn.GELU(), nn.Linear(width, width)
            )
            for _ in range(blocks)
        )
        self.out = nn.Linear(width, 144 + num_betas + 3)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    @torch.no_grad()
    def set_body(self, body: BodyModel, markers: MarkerModel | None = None) -> None:
        """Take the skeleton of `body` (SMPL layout) and the marker table (default: the fitted
        BlazePose table, `MarkerModel.load()`)."""
        if body.num_joints != 24 or [int(p) for p in body.parents] != list(SMPL_PARENTS):
            raise ValueError("the reprojection refiner needs a body model in the SMPL layout")
        if body.num_betas < self.num_betas:
            raise ValueError(
                f"the network uses {self.num_betas} shape coefficients, the body has "
                f"{body.num_betas}"
            )
        markers = markers or MarkerModel.load()
        rows = [list(markers.names).index(BLAZEPOSE_NAMES[i]) for i in self._ids]
        self.rest_joints.copy_(body.J_template)
        self.shape_joints.copy_(body.J_shapedirs[..., : self.num_betas])
        self.marker_anchor.copy_(markers.anchors[rows])
        self.marker_frame.copy_(markers.frames[rows])
        self.marker_offset.copy_(markers.offsets[rows])

    def project_markers(
        self, pose6d: torch.Tensor, betas: torch.Tensor, cam: torch.Tensor, camera: torch.Tensor
    ) -> torch.Tensor:
        """The body's markers (B, n, 2) in the landmark input's normalised crop coordinates
        (x, y in [-1, 1] over the crop; `LandmarkInput.camera` says where the crop sits)."""
        if not bool(torch.isfinite(self.rest_joints).all()):
            raise RuntimeError(
                "the reprojection refiner has no body: build the network with "
                "gst.train.recipe.build_network or load it from a checkpoint"
            )
        R = rot6d_to_matrix(pose6d)
        rest = self.rest_joints + torch.einsum("bl,jkl->bjk", betas, self.shape_joints)
        # the weak-perspective camera as a translation (gst.model.assemble.camera_translation):
        # tz = 2 f / (S s), and 2 f / S is 1 / camera[:, 0]
        s = cam[:, 0].clamp_min(1e-2)
        transl = torch.stack([cam[:, 1], cam[:, 2], 1.0 / (camera[:, 0] * s)], -1)
        levels = [
            (getattr(self, f"_level{k}"), getattr(self, f"_par{k}")) for k in range(self._depth)
        ]
        X, _, _, _ = pose_markers(
            rest, R[:, 0], R[:, 1:], transl, levels, self._parent_index,
            self.marker_anchor, self.marker_frame, self.marker_offset,
        )  # fmt: skip
        # pixel u = f X / Z + cx, normalised ((u + 0.5) / S * 2 - 1): (X / Z - camera_x) / camera_0
        xy = X[..., :2] / X[..., 2:].clamp_min(_MIN_DEPTH)
        return (xy - camera[:, None, 1:]) / camera[:, None, :1]

    def forward(
        self,
        pose6d: torch.Tensor,
        betas: torch.Tensor,
        cam: torch.Tensor,
        landmarks: LandmarkInput,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        B = pose6d.shape[0]
        # unusable points zeroed first, as the encoder does: a masked NaN times 0 is NaN (the
        # whole sample's pose and camera came out NaN), and torch.where keeps gradients finite
        points = torch.where(landmarks.usable[..., None], landmarks.points, 0.0)
        target = points[..., :2]
        weight = points[..., 2] * landmarks.usable.float()
        up = landmarks.up if self.gravity and landmarks.up is not None else None
        up = up if up is not None else pose6d.new_zeros(B, 3)
        known = (up.norm(dim=-1, keepdim=True) > 0).to(pose6d.dtype)
        fixed = torch.cat(
            [
                points.flatten(1),
                landmarks.camera,
                up,
                known,
            ],
            -1,
        )
        for _ in range(self.iterations):
            residual = (target - self.project_markers(pose6d, betas, cam, landmarks.camera)) * (
                weight[..., None]
            )
            x = torch.cat([residual.flatten(1), weight, pose6d.flatten(1), betas, cam, fixed], -1)
            h = self.inp(x)
            for block in self.blocks:
                h = h + block(h)
            d = self.out(h)
            pose6d = pose6d + d[:, :144].view(B, 24, 6)
            betas = betas + d[:, 144 : 144 + self.num_betas]
            cam = cam + d[:, 144 + self.num_betas :]
        return pose6d, betas, cam

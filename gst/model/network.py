"""The GST network: ViT backbone, HMR2 SMPL head, and 5K Gaussian tokens with linear heads.

Outputs are in the input crop's camera frame and the body's rest frame; `gst.model.assemble`
turns them into posed Gaussians in the world. Key names under `backbone.` and `smpl_head.`
match HMR2 checkpoints (see `gst.model.hmr2_import`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from gst.body.rotations import rot6d_to_matrix
from gst.model.decoder import LandmarkContext, TokenDecoder
from gst.model.landmarks import LandmarkEncoder, LandmarkInput
from gst.model.presets import GSTConfig
from gst.model.refine import ReprojectionRefiner
from gst.model.vit import ViT

GAUSSIAN_ATTRIBUTES = ("color", "rotation", "opacity", "scale", "offset")
_ATTR_DIMS = {"color": 3, "rotation": 4, "opacity": 1, "scale": 3, "offset": 3}


@dataclass
class GaussianParams:
    """Per-Gaussian attributes in the body's rest frame (offsets and rotations are posed later)."""

    colors: torch.Tensor  # (B, V, 3) in [0, 1]
    quats: torch.Tensor  # (B, V, 4) unit wxyz, normalised per Gaussian
    opacities: torch.Tensor  # (B, V) in (0, 1)
    scales: torch.Tensor  # (B, V, 3) metres, in [min_scale, max_scale]
    offsets: torch.Tensor  # (B, V, 3) metres, rest frame


@dataclass
class GSTOutput:
    body_pose_6d: torch.Tensor  # (B, 24, 6): global orient (camera frame) + 23 body joints
    rotmats: torch.Tensor  # (B, 24, 3, 3)
    betas: torch.Tensor  # (B, num_betas)
    cam: torch.Tensor  # (B, 3): (s, tx, ty), HMR2's weak-perspective camera
    gaussians: GaussianParams | None = None


def _mean_pose_6d() -> torch.Tensor:
    """Identity body pose; global orient = 180 deg about x, so a SMPL body (y up, facing +z)
    stands upright in an OpenCV camera (y down) and faces it."""
    rot = torch.eye(3).repeat(24, 1, 1)
    rot[0] = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
    return torch.cat([rot[:, :, 0], rot[:, :, 1]], dim=-1).reshape(1, 144)


class SMPLHead(nn.Module):
    """HMR2's SMPL head: decoder + linear decoders as residuals on mean parameters."""

    def __init__(self, cfg: GSTConfig):
        super().__init__()
        dim = cfg.decoder.dim
        self.transformer = TokenDecoder(cfg.decoder, landmarks=cfg.landmark_tokens)
        self.decpose = nn.Linear(dim, 24 * 6)
        self.decshape = nn.Linear(dim, cfg.num_betas)
        self.deccam = nn.Linear(dim, 3)
        for lin in (self.decpose, self.decshape, self.deccam):
            nn.init.xavier_uniform_(lin.weight, gain=0.01)
            nn.init.zeros_(lin.bias)
        self.register_buffer("init_body_pose", _mean_pose_6d())
        self.register_buffer("init_betas", torch.zeros(1, cfg.num_betas))
        self.register_buffer("init_cam", torch.tensor([[0.9, 0.0, 0.0]]))

    def forward(
        self, context: torch.Tensor | None, landmarks: LandmarkContext | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        token = self.transformer.smpl_token(context, landmarks)
        pose = self.decpose(token) + self.init_body_pose
        return (
            pose.view(-1, 24, 6),
            self.decshape(token) + self.init_betas,
            self.deccam(token) + self.init_cam,
        )


class GaussianHead(nn.Module):
    """5K learned tokens (K groups x 5 attributes) decoded through the SMPL head's stack in
    their own pass, then one linear head per attribute maps a group token to its Gaussians."""

    def __init__(self, cfg: GSTConfig, group_index: np.ndarray):
        super().__init__()
        self.cfg = cfg
        k = cfg.num_groups
        group_index = np.asarray(group_index, dtype=np.int64)
        if group_index.ndim != 1 or group_index.min() < 0 or group_index.max() >= k:
            raise ValueError(
                f"group_index must be (V,) with values in [0, {k}), got shape {group_index.shape}"
            )
        counts = np.bincount(group_index, minlength=k)
        if counts.min() == 0:
            raise ValueError(
                f"every one of the {k} Gaussian groups needs vertices; counts {counts.tolist()}"
            )
        self.group_size = int(counts.max())
        # slot of each vertex inside its group (its rank among the group's vertices)
        order = np.argsort(group_index, kind="stable")
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        slot = np.empty_like(group_index)
        slot[order] = np.arange(len(group_index)) - starts[group_index[order]]
        self.register_buffer(
            "flat_index", torch.from_numpy(group_index * self.group_size + slot), persistent=False
        )
        dim = cfg.decoder.dim
        self.tokens = nn.Parameter(torch.randn(1, len(GAUSSIAN_ATTRIBUTES) * k, dim) * 0.02)
        self.heads = nn.ModuleDict(
            {a: nn.Linear(dim, self.group_size * _ATTR_DIMS[a]) for a in GAUSSIAN_ATTRIBUTES}
        )
        for lin in self.heads.values():
            nn.init.xavier_uniform_(lin.weight, gain=0.01)
            nn.init.zeros_(lin.bias)
        with torch.no_grad():
            self.heads["rotation"].bias.view(self.group_size, 4)[:, 0] = 1.0  # identity quaternions
            self.heads["opacity"].bias.fill_(math.log(cfg.init_opacity / (1 - cfg.init_opacity)))
            frac = (cfg.init_scale - cfg.min_scale) / (cfg.max_scale - cfg.min_scale)
            self.heads["scale"].bias.fill_(math.log(frac / (1 - frac)))
            self.heads["color"].bias.fill_(0.0)

    @property
    def num_tokens(self) -> int:
        return self.tokens.shape[1]

    def forward(
        self,
        decoder: TokenDecoder,
        context: torch.Tensor | None,
        landmarks: LandmarkContext | None = None,
    ) -> GaussianParams:
        b = (context if context is not None else landmarks.tokens).shape[0]
        k = self.cfg.num_groups
        out = decoder.decode(self.tokens.expand(b, -1, -1), context, landmarks)  # (B, 5K, dim)
        per_attr = {}
        for i, a in enumerate(GAUSSIAN_ATTRIBUTES):
            raw = self.heads[a](out[:, i * k : (i + 1) * k])  # (B, K, G * d)
            raw = raw.reshape(b, k * self.group_size, _ATTR_DIMS[a])
            per_attr[a] = raw[:, self.flat_index]  # (B, V, d)
        c = self.cfg
        quats = per_attr["rotation"]
        # Normalise each Gaussian's own quaternion (not across vertices: that was a defect of
        # the public GST code), with an epsilon so a zero vector stays finite.
        quats = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        return GaussianParams(
            colors=torch.sigmoid(per_attr["color"]),
            quats=quats,
            opacities=torch.sigmoid(per_attr["opacity"][..., 0]),
            scales=c.min_scale + (c.max_scale - c.min_scale) * torch.sigmoid(per_attr["scale"]),
            offsets=c.max_offset * torch.tanh(per_attr["offset"]),
        )


class GSTNetwork(nn.Module):
    """`forward(images (B, 3, H, W) ImageNet-normalised, with_gaussians, landmarks) -> GSTOutput`.

    With `cfg.landmark_tokens` the decoder also attends to landmark tokens
    (`gst.model.landmarks`); `images=None` is the landmark-only mode (no image tokens, for the
    render-free pretraining), and landmarks that are None or masked give exactly the
    image-only output. With `cfg.landmark_refine` the head's answer goes through that many
    rounds of reprojection feedback (`gst.model.refine`) for samples that have landmarks."""

    def __init__(self, cfg: GSTConfig, group_index: np.ndarray):
        super().__init__()
        self.cfg = cfg
        self.backbone = ViT(cfg.vit)
        self.smpl_head = SMPLHead(cfg)
        self.gaussian_head = GaussianHead(cfg, group_index)
        self.landmark_encoder = (
            LandmarkEncoder(
                cfg.num_landmarks,
                cfg.decoder.dim,
                cfg.landmark_lift_tokens,
                cfg.landmark_width,
                point_tokens=cfg.landmark_point_tokens,
                gravity=cfg.landmark_gravity,
            )
            if cfg.landmark_tokens
            else None
        )
        self.refiner = (
            ReprojectionRefiner(
                cfg.num_landmarks,
                cfg.num_betas,
                cfg.landmark_refine,
                gravity=cfg.landmark_gravity,
            )
            if cfg.landmark_tokens and cfg.landmark_refine > 0
            else None
        )

    @property
    def num_query_tokens(self) -> int:
        """5K Gaussian tokens + 1 SMPL token."""
        return self.gaussian_head.num_tokens + 1

    def freeze_backbone(self, frozen: bool = True) -> None:
        for p in self.backbone.parameters():
            p.requires_grad_(not frozen)

    def forward(
        self,
        images: torch.Tensor | None,
        with_gaussians: bool = True,
        landmarks: LandmarkInput | None = None,
        image_for_pose: bool = True,
    ) -> GSTOutput:
        """`image_for_pose` False (pose only, with landmarks): samples that have a usable landmark
        skip the image path (the ViT and the SMPL token's image cross-attention) and take the
        landmark-only mode; the others take the image path as usual (gst.model.inference)."""
        if landmarks is not None and self.landmark_encoder is None:
            raise ValueError("landmarks given to a network built without landmark_tokens")
        if not (image_for_pose or with_gaussians or images is None or landmarks is None):
            return self._pose_from_landmarks_where_possible(images, landmarks)
        if images is None and landmarks is None:
            raise ValueError("the network needs images, landmarks or both")
        context = self.backbone(images) if images is not None else None
        lm = self.landmark_encoder(landmarks) if landmarks is not None else None
        if images is None and not bool(lm.active.all()):
            raise ValueError("landmark-only mode: every sample needs at least one landmark")
        pose6d, betas, cam = self.smpl_head(context, lm)
        if self.refiner is not None and landmarks is not None:
            pose6d, betas, cam = self._refine(pose6d, betas, cam, landmarks)
        gaussians = (
            self.gaussian_head(self.smpl_head.transformer, context, lm) if with_gaussians else None
        )
        return GSTOutput(
            body_pose_6d=pose6d,
            rotmats=rot6d_to_matrix(pose6d),
            betas=betas,
            cam=cam,
            gaussians=gaussians,
        )

    def _refine(self, pose6d, betas, cam, landmarks: LandmarkInput):
        """The refiner's answer for the samples with a usable landmark; the others keep the
        head's output exactly (the image-only path stays bit for bit)."""
        has = landmarks.has_landmarks
        if bool(has.all()):
            return self.refiner(pose6d, betas, cam, landmarks)
        if not bool(has.any()):
            return pose6d, betas, cam
        idx = has.nonzero()[:, 0]
        refined = self.refiner(pose6d[idx], betas[idx], cam[idx], landmarks.rows(idx))
        return tuple(
            full.index_put((idx,), part)
            for full, part in zip((pose6d, betas, cam), refined, strict=True)
        )

    def _pose_from_landmarks_where_possible(
        self, images: torch.Tensor, landmarks: LandmarkInput
    ) -> GSTOutput:
        has = landmarks.has_landmarks
        if bool(has.all()):
            return self(None, with_gaussians=False, landmarks=landmarks)
        if not bool(has.any()):
            return self(images, with_gaussians=False, landmarks=landmarks)
        parts = [
            (has, self(None, with_gaussians=False, landmarks=landmarks.rows(has))),
            (~has, self(images[~has], with_gaussians=False, landmarks=landmarks.rows(~has))),
        ]
        merged = {}
        for name in ("body_pose_6d", "rotmats", "betas", "cam"):
            first = getattr(parts[0][1], name)
            out = first.new_empty((len(has), *first.shape[1:]))
            for rows, part in parts:
                out[rows] = getattr(part, name)
            merged[name] = out
        return GSTOutput(**merged)

"""Landmark tokens: a crop's 2D landmarks as extra context for GST's decoder
(docs/landmark_prior.md).

The SMPL token and the Gaussian tokens attend to the ViT's image tokens as in the paper and, in
a second cross-attention per decoder layer, to these tokens: one per landmark (its normalised
position and confidence, plus a learned identity) and `lift_tokens` more made by a residual MLP
over all landmarks at once (a Martinez-style lifting network: the whole 2D skeleton is what
tells the 3D pose) together with where the crop sits in its camera (so the orientation in the
camera frame can be read from a crop cut off-centre). The same MLP also gives a query added to
the SMPL token's input: a short path from the lifting MLP to the pose (measured: a transformer
decoder reading only the lift tokens learns several times slower than an MLP,
docs/landmark_prior.md). Landmarks come from BlazePose
(`gst.detect`), in the simulated form during the render-free pretraining (`gst.lift`).

`LandmarkInput.masked()` or `landmarks=None` gives exactly the image-only network's output.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from gst.model.decoder import LandmarkContext

# BlazePose landmarks fed by default: shoulders, elbows, wrists, hips, knees, ankles (left/right
# alternating; gst.lift.errors.LIMB_LANDMARKS, the set the noise model is measured on).
LIMB_LANDMARK_IDS: tuple[int, ...] = (11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28)
N_BLAZEPOSE = 33  # BlazePose's landmarks, MediaPipe order (the crops' `landmarks`)


# Landmarks farther than this many crop widths from the crop are masked (no reading): real
# detections of limbs cut off by the crop stay within one or two.
MAX_CROP_WIDTHS = 10.0


@dataclass
class LandmarkInput:
    """Network-side landmarks: points (B, L, 3) = x, y in [-1, 1] over the crop and confidence;
    camera (B, 3) = crop half-width over focal, and the crop centre's ray (x, y over focal);
    mask (B, L) bool = landmarks the network may use; up (B, 3) = the world's up direction in the
    crop's camera frame (unit; a zero row where the camera is not calibrated), or None for none
    known (read only by networks built with `landmark_gravity`)."""

    points: torch.Tensor
    camera: torch.Tensor
    mask: torch.Tensor
    up: torch.Tensor | None = None

    @classmethod
    def from_pixels(
        cls,
        landmarks: torch.Tensor,
        K_crop: torch.Tensor,
        crop_size: int,
        mask: torch.Tensor | None = None,
        up: torch.Tensor | None = None,
    ) -> LandmarkInput:
        """(B, L, 3) u, v in crop pixels (pixel centres at integers) + confidence, with the
        crops' intrinsics (B, 3, 3) and, where known, the world's up direction in each crop's
        camera frame (B, 3) (`camera_up`)."""
        if landmarks.ndim != 3 or landmarks.shape[-1] != 3:
            raise ValueError(f"landmarks must be (B, L, 3), got {tuple(landmarks.shape)}")
        if K_crop.shape != (landmarks.shape[0], 3, 3):
            raise ValueError(
                f"K_crop must be ({landmarks.shape[0]}, 3, 3), got {tuple(K_crop.shape)}"
            )
        xy = (landmarks[..., :2] + 0.5) / crop_size * 2 - 1
        conf = landmarks[..., 2:].clamp(0, 1)
        f = K_crop[:, 0, 0]
        centre = (crop_size - 1) / 2
        camera = torch.stack(
            [crop_size / (2 * f), (centre - K_crop[:, 0, 2]) / f, (centre - K_crop[:, 1, 2]) / f],
            -1,
        )
        if mask is None:
            mask = torch.ones(landmarks.shape[:2], dtype=torch.bool, device=landmarks.device)
        if up is not None:
            up = torch.as_tensor(up, dtype=torch.float32, device=landmarks.device)
            if up.shape != (landmarks.shape[0], 3):
                raise ValueError(f"up must be ({landmarks.shape[0]}, 3), got {tuple(up.shape)}")
            up = torch.nan_to_num(up)  # a non-finite row: not known
            norm = up.norm(dim=-1, keepdim=True)
            up = torch.where(norm > 1e-6, up / norm.clamp_min(1e-6), torch.zeros_like(up))
        return cls(torch.cat([xy, conf], -1), camera, mask.bool(), up)

    @classmethod
    def from_detections(
        cls,
        landmarks: torch.Tensor | np.ndarray,
        K_crop: torch.Tensor | np.ndarray,
        crop_size: int,
        num_landmarks: int,
        up: torch.Tensor | np.ndarray | None = None,
    ) -> LandmarkInput:
        """BlazePose's 33 landmarks per crop, (B, 33, 3) u, v in crop pixels + confidence
        (visibility x presence; NaN where the detector gave nothing), as the network's input:
        the network's landmark set is picked (`select_landmarks`) and non-finite points are
        masked (a crop without any landmark takes the image-only path exactly); `up` as in
        `from_pixels`."""
        lm = torch.as_tensor(landmarks, dtype=torch.float32)
        K = torch.as_tensor(K_crop, dtype=torch.float32, device=lm.device)
        lm = select_landmarks(lm, num_landmarks)
        finite = torch.isfinite(lm).all(-1)
        # a point this many crop widths out is no reading either (a damaged cache's 1e30 became
        # inf in the lifting's LayerNorm and failed the whole batch, not its row)
        finite &= (lm[..., :2].abs() <= MAX_CROP_WIDTHS * crop_size).all(-1)
        lm = torch.where(finite[..., None], lm, torch.zeros_like(lm))
        return cls.from_pixels(lm, K, crop_size, mask=finite, up=up)

    def to(self, device) -> LandmarkInput:
        up = None if self.up is None else self.up.to(device)
        return LandmarkInput(
            self.points.to(device), self.camera.to(device), self.mask.to(device), up
        )

    @property
    def usable(self) -> torch.Tensor:
        """(B, L) bool: landmarks the network may use and that were detected (confidence > 0)."""
        return self.mask & (self.points[..., 2] > 0)

    @property
    def has_landmarks(self) -> torch.Tensor:
        """(B,) bool: samples with at least one usable landmark, the ones whose pose can come from
        the landmarks alone (`GSTNetwork.forward` with `image_for_pose` False)."""
        return self.usable.any(1)

    def rows(self, index: torch.Tensor) -> LandmarkInput:
        """The samples `index` (a (B,) bool mask or integer indices) of this input."""
        up = None if self.up is None else self.up[index]
        return LandmarkInput(self.points[index], self.camera[index], self.mask[index], up)

    def masked(self, samples: torch.Tensor | None = None) -> LandmarkInput:
        """A copy with every landmark of `samples` (B,) bool (default: all) masked out."""
        drop = (
            torch.ones(self.mask.shape[0], dtype=torch.bool, device=self.mask.device)
            if samples is None
            else samples.bool()
        )
        return LandmarkInput(self.points, self.camera, self.mask & ~drop[:, None], self.up)


# Training hides the camera's up direction of every this-many-th sample, so that a gravity-aware
# network also serves uncalibrated video.
UNCALIBRATED_EVERY = 5


def hide_up(up: torch.Tensor, every: int = UNCALIBRATED_EVERY) -> torch.Tensor:
    """A copy of (B, 3) up directions with every `every`-th row zeroed (not known): rows
    every - 1, 2 every - 1, ..., so floor(B / every) of a batch of B (none below `every`)."""
    up = up.clone()
    up[every - 1 :: every] = 0.0
    return up


def camera_up(R: torch.Tensor, world_up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """The world's up axis in each camera's frame: (B, 3, 3) world-to-camera rotations -> (B, 3)
    unit vectors (`world_up`: the rig's up axis, `calibration.Rig.up`)."""
    w = torch.as_tensor(world_up, dtype=R.dtype, device=R.device)
    return R @ (w / w.norm())


def landmark_ids(num_landmarks: int) -> tuple[int, ...]:
    """The BlazePose landmarks (MediaPipe ids) a network of `num_landmarks` takes: all 33, or
    the 12 limb landmarks (`LIMB_LANDMARK_IDS`)."""
    if num_landmarks == N_BLAZEPOSE:
        return tuple(range(N_BLAZEPOSE))
    if num_landmarks == len(LIMB_LANDMARK_IDS):
        return LIMB_LANDMARK_IDS
    raise ValueError(
        f"no landmark set of {num_landmarks} landmarks (networks take {N_BLAZEPOSE} or "
        f"{len(LIMB_LANDMARK_IDS)})"
    )


def select_landmarks(landmarks: torch.Tensor, num_landmarks: int) -> torch.Tensor:
    """(B, 33, C) BlazePose landmarks -> the (B, num_landmarks, C) a network takes
    (`landmark_ids`)."""
    if landmarks.ndim != 3 or landmarks.shape[1] != N_BLAZEPOSE:
        raise ValueError(
            f"landmarks must be (B, {N_BLAZEPOSE}, C) BlazePose landmarks, "
            f"got {tuple(landmarks.shape)}"
        )
    ids = landmark_ids(num_landmarks)
    return landmarks if num_landmarks == N_BLAZEPOSE else landmarks[:, list(ids)]


def landmark_input(
    network: nn.Module,
    landmarks: torch.Tensor | np.ndarray | None,
    K_crop: torch.Tensor | np.ndarray,
    crop_size: int,
    up: torch.Tensor | np.ndarray | None = None,
) -> LandmarkInput | None:
    """The input a network's landmark tokens take from (B, 33, 3) crop landmarks (and the
    cameras' up directions where known), or None when there are none or the network has no
    landmark tokens (the paper's image-only network ignores them). `network` may be wrapped
    (DistributedDataParallel)."""
    net = getattr(network, "module", network)
    if landmarks is None or getattr(net, "landmark_encoder", None) is None:
        return None
    return LandmarkInput.from_detections(landmarks, K_crop, crop_size, net.cfg.num_landmarks, up=up)


class _Residual(nn.Module):
    def __init__(self, width: int):
        super().__init__()
        self.net = nn.Sequential(
            nn.LayerNorm(width), nn.Linear(width, width), nn.GELU(), nn.Linear(width, width)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.net(x)


class LandmarkEncoder(nn.Module):
    """LandmarkInput -> LandmarkContext (tokens of the decoder's width)."""

    def __init__(
        self,
        num_landmarks: int,
        dim: int,
        lift_tokens: int = 4,
        width: int = 512,
        blocks: int = 2,
        point_tokens: bool = True,
        gravity: bool = False,
    ):
        super().__init__()
        self.num_landmarks, self.lift_tokens, self.dim = num_landmarks, lift_tokens, dim
        self.point_tokens, self.gravity = point_tokens, gravity
        if point_tokens:
            self.point = nn.Sequential(nn.Linear(3, dim), nn.GELU(), nn.Linear(dim, dim))
            self.identity = nn.Parameter(torch.randn(1, num_landmarks, dim) * 0.02)
        self.lift = nn.Sequential(
            # the landmarks, the crop's camera and, with `gravity`, the up vector and its flag
            nn.Linear(num_landmarks * 3 + 3 + (4 if gravity else 0), width),
            *[_Residual(width) for _ in range(blocks)],
            nn.LayerNorm(width),
        )
        self.to_tokens = nn.Linear(width, lift_tokens * dim)
        self.to_query = nn.Linear(width, dim)

    def forward(self, inp: LandmarkInput) -> LandmarkContext:
        B, L, _ = inp.points.shape
        if L != self.num_landmarks:
            raise ValueError(f"the network takes {self.num_landmarks} landmarks, got {L}")
        # Landmarks the network may not use are zeroed before anything sees them, so the lift
        # tokens cannot leak them either; confidence 0 means "not detected".
        valid = inp.usable
        pts = torch.where(valid[..., None], inp.points, torch.zeros_like(inp.points))
        features = [pts.reshape(B, -1), inp.camera]
        if self.gravity:
            up = inp.points.new_zeros(B, 3) if inp.up is None else inp.up
            known = (up.norm(dim=-1, keepdim=True) > 0.5).to(up.dtype)
            features += [up * known, known]
        h = self.lift(torch.cat(features, -1))
        lift = self.to_tokens(h).view(B, self.lift_tokens, self.dim)
        # the lift tokens are always attendable, so no sample's attention is empty (no NaN)
        key_mask = valid.new_ones(B, self.lift_tokens)
        tokens = lift
        if self.point_tokens:
            tokens = torch.cat([self.point(pts) + self.identity, lift], 1)
            key_mask = torch.cat([valid, key_mask], 1)
        return LandmarkContext(tokens, key_mask, inp.has_landmarks, self.to_query(h))

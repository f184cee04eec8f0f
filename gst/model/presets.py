"""Model presets, from CPU-friendly `tiny` to `huge` (HMR2's exact ViT-H + SMPL head layout)."""

from __future__ import annotations

from dataclasses import dataclass, replace

from gst.model.decoder import DecoderConfig
from gst.model.vit import ViTConfig


@dataclass(frozen=True)
class GSTConfig:
    name: str
    vit: ViTConfig
    decoder: DecoderConfig
    vertex_preset: str = "6890"  # which body vertices carry a Gaussian (gst.body.subsets)
    num_groups: int = 26  # K: 5K Gaussian tokens + 1 SMPL token
    num_betas: int = 10
    min_scale: float = 1e-3  # metres; scales are bounded on both sides for stability
    max_scale: float = 0.05
    max_offset: float = 0.10  # metres, |offset| per axis (tanh-bounded, then tightness-regularised)
    init_scale: float = 0.012
    init_opacity: float = 0.9
    # Landmark tokens (gst.model.landmarks, ours): 2D landmarks as extra decoder context. Off:
    # the paper's image-only network, parameter for parameter.
    landmark_tokens: bool = False
    num_landmarks: int = 12  # gst.model.landmarks.LIMB_LANDMARK_IDS
    landmark_lift_tokens: int = 4
    landmark_width: int = 512
    # One token per landmark besides the lift tokens (local evidence for the Gaussian tokens);
    # they are most of the landmark path's compute (docs/landmark_prior.md, "Speed").
    landmark_point_tokens: bool = True
    # The world's up direction in the crop's camera frame as one more input of the lifting MLP,
    # when the camera is calibrated (zeros and a flag when not): without it a person below a
    # camera that looks down cannot be told from a leaning person seen level, and the network
    # took a camera's downward pitch only halfway into the body's orientation
    # (docs/landmark_prior.md, "Gravity"). Off in checkpoints written before it existed.
    landmark_gravity: bool = False
    # Rounds of reprojection feedback after the SMPL head (gst.model.refine, ours): the body's
    # virtual markers projected into the crop against the input landmarks, read by a residual
    # MLP that corrects pose, shape and camera (docs/landmark_prior.md, "Reprojection
    # feedback"). 0: none (the head's answer, as in checkpoints written before it existed).
    landmark_refine: int = 0

    @property
    def image_size(self) -> tuple[int, int]:
        return self.vit.image_size


def _preset(name, vit, dec, vertex_preset) -> GSTConfig:
    return GSTConfig(
        name=name, vit=vit, decoder=replace(dec, context_dim=vit.dim), vertex_preset=vertex_preset
    )


PRESETS: dict[str, GSTConfig] = {
    "tiny": _preset(
        "tiny",
        ViTConfig(image_size=(128, 96), dim=192, depth=6, heads=3),
        DecoderConfig(dim=256, depth=2, heads=4, dim_head=64, mlp_dim=512),
        "1723",
    ),
    "small": _preset(
        "small",
        ViTConfig(image_size=(256, 192), dim=384, depth=12, heads=6),
        DecoderConfig(dim=512, depth=4, heads=8, dim_head=64, mlp_dim=1024),
        "3445",
    ),
    "base": _preset(
        "base",
        ViTConfig(image_size=(256, 192), dim=768, depth=12, heads=12),
        DecoderConfig(dim=1024, depth=6, heads=8, dim_head=64, mlp_dim=1024),
        "6890",
    ),
    # HMR2 / ViTPose-H: width 1280, depth 32, 16 heads; SMPL head width 1024, depth 6, 8x64 heads.
    "huge": _preset(
        "huge",
        ViTConfig(image_size=(256, 192), dim=1280, depth=32, heads=16),
        DecoderConfig(dim=1024, depth=6, heads=8, dim_head=64, mlp_dim=1024),
        "6890",
    ),
}


def get_preset(name: str, **overrides) -> GSTConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown model preset '{name}' (presets: {', '.join(PRESETS)})")
    return replace(PRESETS[name], **overrides)

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

    @property
    def image_size(self) -> tuple[int, int]:
        return self.vit.image_size


# One row per preset: the ViT (input size, width, depth, heads), the SMPL head's decoder (width,
# depth, heads, head width, MLP width: `DecoderConfig`'s field order; its context width is the
# ViT's) and the vertex preset. `huge` is HMR2 / ViTPose-H: width 1280, depth 32, 16 heads; SMPL
# head width 1024, depth 6, 8x64 heads.
# fmt: off
_PRESET_TABLE = {
    #          ViT                          decoder                 vertices
    "tiny":  (((128, 96), 192, 6, 3),      (256, 2, 4, 64, 512),   "1723"),
    "small": (((256, 192), 384, 12, 6),    (512, 4, 8, 64, 1024),  "3445"),
    "base":  (((256, 192), 768, 12, 12),   (1024, 6, 8, 64, 1024), "6890"),
    "huge":  (((256, 192), 1280, 32, 16),  (1024, 6, 8, 64, 1024), "6890"),
}
# fmt: on


def _preset(name: str, vit: tuple, decoder: tuple, vertices: str) -> GSTConfig:
    size, width, depth, heads = vit
    return GSTConfig(
        name=name,
        vit=ViTConfig(image_size=size, dim=width, depth=depth, heads=heads),
        decoder=DecoderConfig(*decoder, context_dim=width),
        vertex_preset=vertices,
    )


PRESETS: dict[str, GSTConfig] = {name: _preset(name, *row) for name, row in _PRESET_TABLE.items()}


def get_preset(name: str, **overrides) -> GSTConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown model preset '{name}' (presets: {', '.join(PRESETS)})")
    return replace(PRESETS[name], **overrides)

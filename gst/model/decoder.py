"""HMR2-style cross-attention decoder: query tokens attend to each other and to image tokens.

Attribute names follow HMR2's `smpl_head.transformer.*` checkpoint keys: `to_token_embedding`,
`pos_embedding`, and `transformer.layers.L.{0, 1, 2}` = pre-norm self-attention (`to_qkv`, no
bias), cross-attention (`to_q`, `to_kv`, no bias) and feed-forward (`net.0`, `net.3`), each
as `.norm` + `.fn`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn


@dataclass(frozen=True)
class DecoderConfig:
    dim: int = 1024
    depth: int = 6
    heads: int = 8
    dim_head: int = 64
    mlp_dim: int = 1024
    context_dim: int = 1280


def _split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    b, n, d = x.shape
    return x.view(b, n, heads, d // heads).transpose(1, 2)  # not -1: a batch of 0 has no size


def _merge_heads(x: torch.Tensor) -> torch.Tensor:
    b, h, n, d = x.shape
    return x.transpose(1, 2).reshape(b, n, h * d)


class SelfAttention(nn.Module):
    def __init__(self, cfg: DecoderConfig):
        super().__init__()
        inner = cfg.heads * cfg.dim_head
        self.heads = cfg.heads
        self.to_qkv = nn.Linear(cfg.dim, inner * 3, bias=False)
        self.to_out = nn.Sequential(nn.Linear(inner, cfg.dim), nn.Dropout(0.0))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        q, k, v = (_split_heads(t, self.heads) for t in self.to_qkv(x).chunk(3, dim=-1))
        return self.to_out(_merge_heads(F.scaled_dot_product_attention(q, k, v)))


class CrossAttention(nn.Module):
    def __init__(self, cfg: DecoderConfig, context_dim: int | None = None):
        super().__init__()
        inner = cfg.heads * cfg.dim_head
        self.heads = cfg.heads
        self.to_q = nn.Linear(cfg.dim, inner, bias=False)
        self.to_kv = nn.Linear(context_dim or cfg.context_dim, inner * 2, bias=False)
        self.to_out = nn.Sequential(nn.Linear(inner, cfg.dim), nn.Dropout(0.0))

    def forward(
        self, x: torch.Tensor, context: torch.Tensor, key_mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """`key_mask` (B, T) bool: context tokens a query may attend to (every row needs one)."""
        k, v = (_split_heads(t, self.heads) for t in self.to_kv(context).chunk(2, dim=-1))
        q = _split_heads(self.to_q(x), self.heads)
        mask = None if key_mask is None else key_mask[:, None, None, :]
        return self.to_out(_merge_heads(F.scaled_dot_product_attention(q, k, v, attn_mask=mask)))


class FeedForward(nn.Module):
    def __init__(self, cfg: DecoderConfig):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(cfg.dim, cfg.mlp_dim),
            nn.GELU(),
            nn.Dropout(0.0),
            nn.Linear(cfg.mlp_dim, cfg.dim),
            nn.Dropout(0.0),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class PreNorm(nn.Module):
    def __init__(self, dim: int, fn: nn.Module):
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.fn = fn

    def forward(self, x: torch.Tensor, **kwargs) -> torch.Tensor:
        return self.fn(self.norm(x), **kwargs)


@dataclass
class LandmarkContext:
    """Landmark tokens (B, T, dim) beside the image tokens, with the tokens each sample may
    attend to (B, T) bool, the samples that have any landmark at all (B,) bool, and optionally
    a query (B, dim) added to the SMPL token's input (a short path from the lifting MLP to the
    pose: the decoder then refines it)."""

    tokens: torch.Tensor
    key_mask: torch.Tensor
    active: torch.Tensor
    query: torch.Tensor | None = None


class CrossAttnStack(nn.Module):
    """HMR2's stack; with `landmarks=True` each layer also cross-attends to landmark tokens
    (`landmark_layers.L`, new keys: HMR2 checkpoints still load into `layers`)."""

    def __init__(self, cfg: DecoderConfig, landmarks: bool = False):
        super().__init__()
        self.layers = nn.ModuleList(
            nn.ModuleList(
                [
                    PreNorm(cfg.dim, SelfAttention(cfg)),
                    PreNorm(cfg.dim, CrossAttention(cfg)),
                    PreNorm(cfg.dim, FeedForward(cfg)),
                ]
            )
            for _ in range(cfg.depth)
        )
        self.landmark_layers = (
            nn.ModuleList(
                PreNorm(cfg.dim, CrossAttention(cfg, context_dim=cfg.dim)) for _ in range(cfg.depth)
            )
            if landmarks
            else None
        )

    def forward(
        self,
        x: torch.Tensor,
        context: torch.Tensor | None,
        landmarks: LandmarkContext | None = None,
        image_gate: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """`context` None: no image tokens (the landmark-only mode). A sample without landmarks
        (`landmarks.active` False) takes exactly the image-only path: its landmark update is
        not added (selected away, not multiplied by zero). `image_gate` (depth,): a factor on
        each layer's image update of the samples that have landmarks (others: exactly 1)."""
        if context is None and landmarks is None:
            raise ValueError("the decoder needs image tokens, landmark tokens or both")
        if landmarks is not None and self.landmark_layers is None:
            raise ValueError("landmark tokens given to a decoder built without landmark layers")
        for i, (self_attn, cross_attn, ff) in enumerate(self.layers):
            x = self_attn(x) + x
            if context is not None:
                upd = cross_attn(x, context=context)
                if image_gate is not None and landmarks is not None:
                    upd = torch.where(landmarks.active[:, None, None], upd * image_gate[i], upd)
                x = upd + x
            if landmarks is not None:
                upd = self.landmark_layers[i](
                    x, context=landmarks.tokens, key_mask=landmarks.key_mask
                )
                x = torch.where(landmarks.active[:, None, None], upd + x, x)
            x = ff(x) + x
        return x


class TokenDecoder(nn.Module):
    """The SMPL token path of HMR2: one zero input token, embedded, plus a learned position.

    `decode(tokens (B, T, dim), context)` runs any set of already-embedded query tokens through
    the same stack; GST uses it for its Gaussian tokens in a separate pass, so the SMPL token
    never attends to them and pose-only inference can skip them exactly.
    """

    def __init__(self, cfg: DecoderConfig, landmarks: bool = False):
        super().__init__()
        self.cfg = cfg
        self.to_token_embedding = nn.Linear(1, cfg.dim)
        self.pos_embedding = nn.Parameter(torch.randn(1, 1, cfg.dim))
        self.transformer = CrossAttnStack(cfg, landmarks=landmarks)
        # With landmark tokens: a factor per layer on the image evidence the SMPL token takes
        # from crops that have landmarks (the Gaussian tokens and crops without landmarks always
        # see the image fully). 1 at construction; the lift recipe starts it at 0 so a
        # landmark-trained pose is kept until scene training learns how much to trust the image
        # (docs/landmark_prior.md).
        self.smpl_image_gate = nn.Parameter(torch.ones(cfg.depth)) if landmarks else None

    def smpl_token(
        self, context: torch.Tensor | None, landmarks: LandmarkContext | None = None
    ) -> torch.Tensor:
        ref = context if context is not None else landmarks.tokens
        zero = ref.new_zeros(ref.shape[0], 1, 1)
        x = self.to_token_embedding(zero) + self.pos_embedding
        if landmarks is not None and landmarks.query is not None:
            x = torch.where(landmarks.active[:, None, None], x + landmarks.query[:, None], x)
        return self.transformer(x, context, landmarks, self.smpl_image_gate)[:, 0]

    def decode(
        self,
        tokens: torch.Tensor,
        context: torch.Tensor | None,
        landmarks: LandmarkContext | None = None,
    ) -> torch.Tensor:
        return self.transformer(tokens, context, landmarks)

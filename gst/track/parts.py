"""One person, one id: is a detection a second person, or a part of one already tracked?

A detector sometimes reports a piece of a person as another person (a box on their legs, a
second region on their upper body). Such a box lies mostly inside the person's own box, in the
same frame. So does a real second person standing behind them, so the box alone cannot decide:

- with landmarks (the learned person model), the inner detection is a part when most of its
  confident limb joints, on its left side and on its right side alike, lie on the outer
  person's skeleton (within `width` x their body size of a bone or the torso): a leg box's
  "person" is made of the outer person's legs, while a person half behind someone has at least
  one side of their own, off the front person's bones (one side alone can line up with the
  front person's limbs). Measured on the lab capture (docs/track_evaluation.md): the
  duplicate regions of cam04 score 0.67-0.83 in 7 of their 8 frames, the two real people
  0.00-0.50 in cam01 and cam04, but up to 0.83 in 8 frames of cam03, where the man's landmarks
  run through the woman (so a real person who first appeared there would be delayed).
- without landmarks (supplied boxes, the background model), it is a part unless its appearance
  and its 3D position both disagree with the outer person's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gst.detect.boxes import containment
from gst.detect.persons import BONES, LIMB_JOINTS, TORSO, body_size

# Segments a point is compared with: the limb bones and the torso outline.
_SEGMENTS = np.array(BONES + tuple(zip(TORSO, TORSO[1:] + TORSO[:1], strict=True)))
# LIMB_JOINTS alternate left, right: shoulders, elbows, wrists, hips, knees, ankles.
_SIDES = (LIMB_JOINTS[0::2], LIMB_JOINTS[1::2])


@dataclass(frozen=True)
class PartConfig:
    containment: float = 0.6  # share of the inner box inside the outer one ("mostly inside")
    width: float = 0.1  # joints within this share of the outer body size of its skeleton
    share: float = 0.6  # share of the inner's confident limb joints on the outer skeleton, per side
    min_confidence: float = 0.5  # landmark confidence for a joint to count
    appearance: float = 0.35  # boxes only: Hellinger distance above which clothing disagrees

    def __post_init__(self):
        for name in ("containment", "share", "min_confidence"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"parts: {name} must be in (0, 1], got {getattr(self, name)}")
        if self.width <= 0 or not 0 < self.appearance <= 1:
            raise ValueError(
                f"parts: width > 0 and appearance in (0, 1] expected, got {self.width}, "
                f"{self.appearance}"
            )


def distance_to_skeleton(points: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """(N,) distance in pixels of (N, 2) points to the nearest bone or torso edge of a skeleton
    given by (33, >=2) landmarks."""
    a = landmarks[_SEGMENTS[:, 0], :2].astype(np.float64)  # (S, 2)
    b = landmarks[_SEGMENTS[:, 1], :2].astype(np.float64)
    ab = b - a
    p = np.asarray(points, np.float64)[:, None, :]  # (N, 1, 2)
    t = np.clip(np.sum((p - a) * ab, -1) / np.maximum(np.sum(ab * ab, -1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1).min(axis=1)


def skeleton_share(inner: np.ndarray, outer: np.ndarray, cfg: PartConfig) -> float:
    """The smaller of the two sides' shares of `inner`'s confident limb joints lying on
    `outer`'s skeleton (a side without a confident joint counts 1.0: no evidence of a person)."""
    reach = cfg.width * max(body_size(outer), 1.0)
    shares = []
    for side in _SIDES:
        joints = inner[list(side)]
        ok = joints[:, 2] >= cfg.min_confidence
        if ok.any():
            d = distance_to_skeleton(joints[ok, :2], outer)
            shares.append(float(np.mean(d <= reach)))
    return min(shares, default=1.0)


def is_part(
    inner_box: np.ndarray,
    outer_box: np.ndarray,
    inner_landmarks: np.ndarray | None,
    outer_landmarks: np.ndarray | None,
    appearance_distance: float,
    position_disagrees: bool,
    cfg: PartConfig,
) -> bool:
    """Whether the inner detection is a part of the outer person (see the module doc)."""
    if containment(inner_box, outer_box) < cfg.containment:
        return False
    if inner_landmarks is not None and outer_landmarks is not None:
        return skeleton_share(inner_landmarks, outer_landmarks, cfg) >= cfg.share
    return not (appearance_distance > cfg.appearance and position_disagrees)

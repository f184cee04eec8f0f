"""Fused bodies against a synthetic scene's exact truth: MPJPE, PA-MPJPE, vertex error.

Fused people carry the extraction's ids, not the scene's, and an extraction id may switch
between people; so every frame is matched on its own: fused and truth bodies of that frame are
paired by the Hungarian method on the mean joint distance, pairs further apart than `max_match_m`
are not counted (reported as unmatched). Truth people the fusion missed are counted too: of the
truth person-frames seen in some camera (`seen_truth_views`), in the frames the
extraction considered (`expected`), those no fused body was paired with (`truth_missed`; an
MPJPE over fewer people is no better fusion). Errors are in millimetres over all 24 joints (world
frame, no alignment for MPJPE; similarity Procrustes for PA-MPJPE, gst.metrics.pose) and over
all mesh vertices (same body model as the scene's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from gst.body.model import BodyModel
from gst.data.extract.crops import seen_truth_views
from gst.fuse.fit import PersonFit
from gst.metrics.pose import mpjpe, pa_mpjpe, vertex_error
from synth.truth import SceneTruth, TruthViews

__all__ = ["TruthComparison", "compare_with_truth", "visible_person_frames"]


@dataclass
class TruthComparison:
    mpjpe_mm: float
    pa_mpjpe_mm: float
    vertex_error_mm: float
    per_joint_mm: dict[str, float]
    matched: int  # person-frames compared
    unmatched: int  # fused person-frames with no truth body within max_match_m
    per_person: dict[int, dict[str, float]]  # fused id -> mpjpe_mm, pa_mpjpe_mm, frames
    # truth person-frames expected (seen by a camera) and those no fused body was paired with
    # (None: not counted, no `expected` given)
    truth_expected: int | None = None
    truth_missed: int | None = None

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def visible_person_frames(
    views: TruthViews, frames, cameras: list[str] | None = None
) -> set[tuple[int, int]]:
    """(frame, truth person id) of the `frames` in which the person is seen (`seen_truth_views`,
    as the extraction counts missed views) in at least one camera: of `cameras`, the store's,
    when given (a camera the extraction did not read sees no one for the fusion)."""
    keep = seen_truth_views(views) & np.isin(views.frame, list(frames))
    if cameras is not None:
        keep &= np.isin(views.camera.astype(str), list(cameras))
    return {(int(f), int(p)) for f, p in zip(views.frame[keep], views.person_id[keep], strict=True)}


def compare_with_truth(
    fits: list[PersonFit],
    truth: SceneTruth,
    body: BodyModel | None = None,
    max_match_m: float = 0.5,
    joints: str = "joints",
    expected: set[tuple[int, int]] | None = None,
) -> TruthComparison:
    """Per-frame matched errors of `fits` (their `joints`, or another (T, 24, 3) attribute);
    with `expected` (`visible_person_frames`), how many of those no fused body was paired with."""
    pairs = []  # (fit index, row in fit, truth row)
    unmatched = 0
    frames = sorted({int(f) for fit in fits for f in fit.frames})
    by_frame = {}
    for k, fit in enumerate(fits):
        for i, f in enumerate(fit.frames):
            by_frame.setdefault(int(f), []).append((k, i))
    for f in frames:
        mine = by_frame[f]
        rows = np.flatnonzero(truth.frame == f)
        if not len(rows):
            unmatched += len(mine)
            continue
        pred = np.stack([getattr(fits[k], joints)[i] for k, i in mine])
        cost = np.linalg.norm(pred[:, None] - truth.joints_world[rows][None], axis=-1).mean(-1)
        a, b = linear_sum_assignment(cost)
        good = cost[a, b] <= max_match_m
        unmatched += len(mine) - int(good.sum())
        pairs += [(*mine[i], rows[j]) for i, j in zip(a[good], b[good], strict=True)]
    missed = None
    if expected is not None:
        paired = {(int(truth.frame[r]), int(truth.person_id[r])) for *_, r in pairs}
        missed = len(expected - paired)
    n_expected = None if expected is None else len(expected)
    if not pairs:
        nan = float("nan")
        return TruthComparison(nan, nan, nan, {}, 0, unmatched, {}, n_expected, missed)
    pred = torch.as_tensor(np.stack([getattr(fits[k], joints)[i] for k, i, _ in pairs]))
    gt = torch.as_tensor(truth.joints_world[[r for *_, r in pairs]], dtype=pred.dtype)
    e = mpjpe(pred, gt) * 1000
    pa = pa_mpjpe(pred, gt) * 1000
    per_joint = (pred - gt).norm(dim=-1).mean(0) * 1000
    ve = float("nan")
    if body is not None:
        ve = _vertex_error(fits, pairs, truth, body)
    fit_of = np.array([k for k, *_ in pairs])
    per_person = {
        int(fits[k].person_id): {
            "mpjpe_mm": float(e[fit_of == k].mean()),
            "pa_mpjpe_mm": float(pa[fit_of == k].mean()),
            "frames": int((fit_of == k).sum()),
        }
        for k in np.unique(fit_of)
    }
    return TruthComparison(
        mpjpe_mm=float(e.mean()),
        pa_mpjpe_mm=float(pa.mean()),
        vertex_error_mm=ve,
        per_joint_mm={n: float(v) for n, v in zip(truth.joint_names, per_joint, strict=True)},
        matched=len(pairs),
        unmatched=unmatched,
        per_person=per_person,
        truth_expected=n_expected,
        truth_missed=missed,
    )


@torch.no_grad()
def _vertex_error(fits, pairs, truth: SceneTruth, body: BodyModel, batch: int = 32) -> float:
    total, n = 0.0, 0
    for s in range(0, len(pairs), batch):
        chunk = pairs[s : s + batch]
        fk = [fits[k] for k, *_ in chunk]
        idx = [i for _, i, _ in chunk]
        nb = fk[0].betas.shape[0]
        betas = torch.as_tensor(np.stack([f.betas for f in fk]), dtype=body.dtype)
        pred = body(
            betas[:, :nb],
            torch.as_tensor(np.stack([f.body_pose[i] for f, i in zip(fk, idx, strict=True)])),
            torch.as_tensor(np.stack([f.global_orient[i] for f, i in zip(fk, idx, strict=True)])),
            torch.as_tensor(np.stack([f.transl[i] for f, i in zip(fk, idx, strict=True)])),
        ).vertices
        gt = truth.vertices(body, np.array([r for *_, r in chunk]))
        total += float(vertex_error(pred.float(), gt.float()).sum()) * 1000
        n += len(chunk)
    return total / n

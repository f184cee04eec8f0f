"""Scoring extracted persons against ground-truth id masks: mask IoU and association accuracy."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment


@dataclass(frozen=True)
class CropTruth:
    """How one predicted person mask relates to the truth in its camera and frame."""

    frame: int
    camera: str
    person_id: int  # predicted (tracker) id
    truth_id: int  # majority truth id under the predicted mask, 0 if it covers no one
    iou: float  # IoU with the truth mask of `truth_id` (0 when truth_id is 0)
    # where the view came from in the keypoint association (gst.data.keypoints.people:
    # 'refined', 'detected', 'projected' or 'single'); '' for the visual hull
    source: str = ""


def match_truth(pred: np.ndarray, truth: np.ndarray) -> tuple[int, float]:
    """(majority truth id under `pred`, IoU of `pred` with that truth person) for boolean `pred`
    and a uint8 truth id image of the same size."""
    if pred.shape != truth.shape:
        raise ValueError(f"predicted mask {pred.shape} and truth mask {truth.shape} differ in size")
    ids = truth[pred]
    ids = ids[ids > 0]
    if len(ids) == 0:
        return 0, 0.0
    tid = int(np.bincount(ids).argmax())
    gt = truth == tid
    inter = np.count_nonzero(pred & gt)
    union = np.count_nonzero(pred | gt)
    return tid, inter / union if union else 0.0


def association_accuracy(rows: list[CropTruth]) -> tuple[float, int]:
    """Fraction of crops whose person matches across cameras, and the number of crops scored.

    Per frame, each predicted id is paired one-to-one (Hungarian, by vote count) with a truth
    id. A crop is correct when its own truth id is its predicted id's partner, so a person split
    into two ids, two people merged into one id, a swap between cameras and a ghost all count
    as errors.
    """
    if not rows:
        return float("nan"), 0
    correct = 0
    by_frame: dict[int, list[CropTruth]] = {}
    for r in rows:
        by_frame.setdefault(r.frame, []).append(r)
    for frame_rows in by_frame.values():
        pids = sorted({r.person_id for r in frame_rows})
        tids = sorted({r.truth_id for r in frame_rows if r.truth_id > 0})
        if not tids:
            continue
        votes = np.zeros((len(pids), len(tids)))
        for r in frame_rows:
            if r.truth_id > 0:
                votes[pids.index(r.person_id), tids.index(r.truth_id)] += 1
        pi, ti = linear_sum_assignment(-votes)
        partner = {pids[a]: tids[b] for a, b in zip(pi, ti, strict=True) if votes[a, b] > 0}
        correct += sum(
            1 for r in frame_rows if r.truth_id > 0 and partner.get(r.person_id) == r.truth_id
        )
    return correct / len(rows), len(rows)

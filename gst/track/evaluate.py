"""Tracks of a synthetic scene's camera scored against the scene's exact truth.

`evaluate_tracks(tracks_parquet, scene_dir, camera_name)` reads one tracks file
(docs/formats/tracks_parquet.md) and the scene's `truth/people.parquet` and `truth/views.parquet`
(docs/formats/synth_scene.md), matches tracked rows to truth people frame by frame, and reports
pose accuracy (world joints, millimetres), detection recall and precision, and identity
consistency (id switches, fragments, ids per person). Definitions: docs/track_evaluation.md.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import torch
from scipy.optimize import linear_sum_assignment

from calibration import Camera
from gst.data.camera_view import TrackingView
from gst.detect.boxes import box_iou
from gst.metrics.flips import mirrored_landmarks
from gst.metrics.pose import mpjpe, pa_mpjpe
from gst.track.read import column_array, landmark_array, read_metadata
from synth.truth import TruthViews, read_scene_truth, read_truth_views

__all__ = [
    "PersonEvaluation",
    "TrackEvaluation",
    "evaluate_tracks",
    "match_frame",
    "identity_counts",
]

PELVIS = 0


def _mask_boxes(scene_dir: str | Path, camera_name: str, min_mask_area: int) -> TruthViews:
    """The truth people `camera_name` sees (rows with at least `min_mask_area` mask pixels), their
    mask boxes moved from views.parquet's pixel-centre edges (`min column - 0.5`) to the tracks'
    pixel corners (`min column`)."""
    views = read_truth_views(scene_dir, camera_name)
    keep = (views.mask_area >= max(min_mask_area, 1)) & np.isfinite(views.box).all(1)
    views = views.rows(keep)
    return replace(views, box=views.box + 0.5)


def match_frame(
    track_boxes: np.ndarray, truth_boxes: np.ndarray, min_iou: float
) -> list[tuple[int, int]]:
    """(track index, truth index) pairs of one frame, each with box IoU >= `min_iou`: the most
    such matches, then the largest total IoU among them (pairs below the threshold are excluded
    before assigning, as CLEAR MOT does, so a high-IoU pair never costs two valid ones)."""
    if len(track_boxes) == 0 or len(truth_boxes) == 0:
        return []
    iou = box_iou(np.asarray(track_boxes, np.float64), np.asarray(truth_boxes, np.float64))
    return _assign(iou, min_iou)


def _assign(iou: np.ndarray, min_iou: float) -> list[tuple[int, int]]:
    """`match_frame` from the (tracks, truth) IoU matrix."""
    allowed = iou >= min_iou
    # the most allowed pairs first (each worth more than any IoU sum), then the largest IoU
    gain = np.where(allowed, 1.0 + iou.size + iou, 0.0)
    rows, cols = linear_sum_assignment(gain, maximize=True)
    return [(int(r), int(c)) for r, c in zip(rows, cols, strict=True) if allowed[r, c]]


def _continued_matches(
    iou: np.ndarray,
    rows: np.ndarray,
    vrows: np.ndarray,
    track_ids: np.ndarray,
    person_ids: np.ndarray,
    last: dict[int, int],
    min_iou: float,
) -> dict[int, int]:
    """One frame's matches, truth view row -> tracks row, as CLEAR MOT makes them: a person
    keeps the track they were last matched with while its box still overlaps theirs by
    `min_iou`, and only the rest are assigned afresh (`_assign`). Matching every frame afresh
    by the largest total IoU made two overlapping people's tracks trade places for a frame and
    counted switches that the tracker never made."""
    matched: dict[int, int] = {}
    taken_r, taken_c = set(), set()
    for c, v in enumerate(vrows):
        tid = last.get(int(person_ids[v]))
        for r in np.flatnonzero(track_ids[rows] == tid) if tid is not None else ():
            if r not in taken_r and iou[r, c] >= min_iou:
                matched[int(v)] = int(rows[r])
                taken_r.add(r)
                taken_c.add(c)
                break
    free_r = [r for r in range(len(rows)) if r not in taken_r]
    free_c = [c for c in range(len(vrows)) if c not in taken_c]
    if free_r and free_c:
        for r, c in _assign(iou[np.ix_(free_r, free_c)], min_iou):
            matched[int(vrows[free_c[c]])] = int(rows[free_r[r]])
    return matched


def identity_counts(matched_ids: list[int | None]) -> tuple[int, int, int]:
    """(id switches, fragments, distinct ids) of one truth person from the track id matched in each
    processed frame where the person is visible (None: visible but unmatched), in frame order.

    A switch is a change of id between consecutive *matched* frames (a gap in between is not a
    switch by itself). A fragment is a resumption: a matched frame after one or more unmatched
    frames that followed a matched frame."""
    switches = fragments = 0
    last_id: int | None = None
    gap = False
    for tid in matched_ids:
        if tid is None:
            gap = gap or last_id is not None
            continue
        if last_id is not None:
            switches += tid != last_id
            fragments += gap
        last_id, gap = tid, False
    return switches, fragments, len({t for t in matched_ids if t is not None})


@dataclass(frozen=True)
class PersonEvaluation:
    """Per truth person: frames visible to the camera, frames matched, the track ids matched
    (in order of first appearance), switches, fragments and mean pose errors (mm) over matches."""

    truth_person_id: int
    frames_visible: int
    frames_matched: int
    track_ids: tuple[int, ...]
    id_switches: int
    fragments: int
    mpjpe_mm: float | None
    pa_mpjpe_mm: float | None
    root_error_mm: float | None


@dataclass(frozen=True)
class TrackEvaluation:
    """Scores of one tracks file against a synthetic scene's truth (definitions in
    docs/track_evaluation.md). Pose errors are None when nothing matched or the tracks are not in
    the world frame (an uncalibrated video)."""

    video: str
    camera: str
    min_iou: float
    frames: int  # processed frames that have truth
    truth_instances: int  # (frame, person) pairs visible to the camera in those frames
    track_rows: int  # tracked rows in those frames
    matches: int
    recall: float
    # identity F1 (Ristani et al. 2016): truth people and track ids paired one to one for the whole
    # video so that the most frames overlap (box IoU >= min_iou); 2 IDTP / (truth + rows)
    idf1: float
    id_true_positives: int  # IDTP: frames of overlap under that pairing
    # the truth instances with at least half their 24 joints visible (`TruthViews.visible`), how
    # many of them are matched, and the share: people mostly hidden behind others are the usual
    # misses
    half_visible: int
    half_visible_matched: int
    recall_half_visible: float
    precision: float
    mota: float
    id_switches: int
    fragments: int
    ids_per_person: float  # mean distinct track ids per truth person that was matched at least once
    track_ids: int  # distinct track ids in the file
    joints_frame: str  # "world" or "camera"
    mpjpe_mm: float | None  # pelvis-aligned, mean over matched rows
    pa_mpjpe_mm: float | None
    root_error_mm: float | None  # world pelvis position error, mean over matched rows
    root_error_median_mm: float | None
    persons: tuple[PersonEvaluation, ...]
    # matched rows whose landmarks are left/right mirrored against the truth (gst.metrics.flips,
    # the truth joints projected with the file's calibrated camera; 0 without landmarks or
    # calibration), and the pelvis-aligned MPJPE over the other matched rows
    mirrored_rows: int = 0
    mpjpe_mm_not_mirrored: float | None = None
    # matched rows with a non-finite pose error (NaN joints in the tracks file), left out of the
    # pose means (each error keeps the rows where it is finite)
    pose_not_finite: int = 0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["persons"] = [asdict(p) for p in self.persons]
        for p in d["persons"]:
            p["track_ids"] = list(p["track_ids"])
        return d


def _identity_true_positives(overlaps: dict[tuple[int, int], int]) -> int:
    """IDTP: the most frames of overlap under a one-to-one pairing of truth people and track
    ids (`overlaps`: frames each (person, id) pair overlaps)."""
    if not overlaps:
        return 0
    people = sorted({p for p, _ in overlaps})
    ids = sorted({i for _, i in overlaps})
    count = np.zeros((len(people), len(ids)))
    for (p, i), n in overlaps.items():
        count[people.index(p), ids.index(i)] = n
    rows, cols = linear_sum_assignment(count, maximize=True)
    return int(count[rows, cols].sum())


def _processed_frames(meta: dict, truth_frames: np.ndarray) -> np.ndarray:
    video = meta.get("video") or {}
    first, stride = int(video.get("first_frame", 0)), int(video.get("stride", 1))
    end = video.get("end_frame")
    end = int(truth_frames.max()) + 1 if end is None else int(end)
    frames = np.arange(first, end, max(stride, 1))
    return frames[np.isin(frames, truth_frames)]


def _finite_mm(x: np.ndarray, reduce=np.mean) -> float | None:
    # over the finite errors only: one row with NaN joints made the whole mean NaN (written as
    # null, like an uncalibrated video); such rows are counted in `pose_not_finite` instead
    x = x[np.isfinite(x)]
    return float(reduce(x) * 1000.0) if len(x) else None


def evaluate_tracks(
    tracks_parquet: str | Path,
    scene_dir: str | Path,
    camera_name: str,
    min_iou: float = 0.3,
    min_mask_area: int = 1,
    camera: Camera | None = None,
) -> TrackEvaluation:
    """Score one tracks file of `camera_name`'s video against the synthetic scene in `scene_dir`.

    Each processed frame's tracked rows are matched to the truth people visible in that camera
    (mask area >= `min_mask_area` px) by the Hungarian assignment on box IoU (tracked bbox vs the
    truth mask box), pairs below `min_iou` rejected. Over matched rows:
    - mpjpe_mm: mean per-joint error of the 24 joints after moving both skeletons' pelvis to the
      origin; pa_mpjpe_mm: after the best similarity transform (gst.metrics.pose);
    - root_error_mm: distance between tracked and true world pelvis (absolute placement).
    recall = matches / truth instances, precision = matches / tracked rows,
    mota = 1 - (misses + false rows + id switches) / truth instances.
    Per truth person, over the processed frames where the camera sees them, in frame order:
    an id switch is a change of matched track id between consecutive matched frames (unmatched
    frames in between are skipped: a miss is not a switch), a fragment is a match resumed after
    unmatched frames, and track_ids lists the distinct ids matched to them.
    mirrored_rows counts the matched rows whose landmarks are left/right mirrored against the
    truth joints projected with `camera` (default: the file's calibrated camera; 0 for an
    uncalibrated video without one).
    """
    tracks_parquet = Path(tracks_parquet)
    if not tracks_parquet.is_file():
        raise FileNotFoundError(f"{tracks_parquet}: no tracks file")
    if not 0.0 < min_iou <= 1.0:
        raise ValueError(f"min_iou must be in (0, 1], got {min_iou}")
    meta = read_metadata(tracks_parquet)
    table = pq.read_table(tracks_parquet, partitioning=None)
    truth = read_scene_truth(scene_dir)
    views = _mask_boxes(scene_dir, camera_name, min_mask_area)
    joints_frame = (meta.get("axes") or {}).get("joints3d", "camera")

    frames = _processed_frames(meta, truth.frame)
    t_frame = table.column("frame").to_numpy().astype(np.int64)
    t_pid = table.column("person_id").to_numpy().astype(np.int64)
    t_box = column_array(table, "bbox").astype(np.float64)
    t_joints = column_array(table, "joints3d").astype(np.float64)
    in_eval = np.isin(t_frame, frames)
    truth_row = {
        (int(f), int(p)): i
        for i, (f, p) in enumerate(zip(truth.frame, truth.person_id, strict=True))
    }
    v_in = np.isin(views.frame, frames)

    half = views.visible.mean(axis=1) >= 0.5
    half_matched = 0
    overlaps: dict[tuple[int, int], int] = {}  # (truth person, track id) -> frames they overlap
    pairs: list[tuple[int, int]] = []  # (tracks row, scene truth row)
    history: dict[int, list[int | None]] = {int(p): [] for p in np.unique(views.person_id[v_in])}
    last: dict[int, int] = {}  # truth person -> the track id they were last matched with
    for f in frames:
        rows = np.flatnonzero(t_frame == f)
        vrows = np.flatnonzero(views.frame == f)
        matched = {}
        if len(rows) and len(vrows):
            iou = box_iou(t_box[rows].astype(np.float64), views.box[vrows].astype(np.float64))
            matched = _continued_matches(iou, rows, vrows, t_pid, views.person_id, last, min_iou)
            for r, c in zip(*np.nonzero(iou >= min_iou), strict=True):
                key = (int(views.person_id[vrows[c]]), int(t_pid[rows[r]]))
                overlaps[key] = overlaps.get(key, 0) + 1
        for v in vrows:
            person = int(views.person_id[v])
            r = matched.get(int(v))
            history[person].append(None if r is None else int(t_pid[r]))
            if r is not None:
                last[person] = int(t_pid[r])
            half_matched += int(r is not None and half[v])
            if r is not None:
                if (int(f), person) not in truth_row:
                    raise ValueError(
                        f"{scene_dir}: views.parquet has frame {f} person {person} but "
                        "people.parquet does not"
                    )
                pairs.append((r, truth_row[(int(f), person)]))

    err = {"mpjpe": np.zeros(0), "pa": np.zeros(0), "root": np.zeros(0)}
    if pairs and joints_frame == "world":
        pred = torch.from_numpy(t_joints[[p for p, _ in pairs]])
        gt = torch.from_numpy(truth.joints_world[[g for _, g in pairs]].astype(np.float64))
        err = {
            "mpjpe": mpjpe(pred, gt, root=PELVIS).numpy(),
            "pa": pa_mpjpe(pred, gt).numpy(),
            "root": (pred[:, PELVIS] - gt[:, PELVIS]).norm(dim=-1).numpy(),
        }
    pair_person = np.array([truth.person_id[g] for _, g in pairs], np.int64)
    mirrored = _mirrored_rows(table, meta, truth.joints_world, pairs, camera)

    persons = []
    for person, ids in sorted(history.items()):
        switches, fragments, _ = identity_counts(ids)
        mine = pair_person == person
        seen = tuple(dict.fromkeys(t for t in ids if t is not None))
        persons.append(
            PersonEvaluation(
                truth_person_id=person,
                frames_visible=len(ids),
                frames_matched=sum(t is not None for t in ids),
                track_ids=seen,
                id_switches=switches,
                fragments=fragments,
                mpjpe_mm=_finite_mm(err["mpjpe"][mine]) if len(err["mpjpe"]) else None,
                pa_mpjpe_mm=_finite_mm(err["pa"][mine]) if len(err["pa"]) else None,
                root_error_mm=_finite_mm(err["root"][mine]) if len(err["root"]) else None,
            )
        )

    n_truth, n_rows, n_match = int(v_in.sum()), int(in_eval.sum()), len(pairs)
    n_half = int((half & v_in).sum())
    id_tp = _identity_true_positives(overlaps)
    id_switches = sum(p.id_switches for p in persons)
    matched_persons = [p for p in persons if p.track_ids]
    return TrackEvaluation(
        video=str((meta.get("video") or {}).get("name", tracks_parquet.parent.name)),
        camera=camera_name,
        min_iou=float(min_iou),
        frames=len(frames),
        truth_instances=n_truth,
        track_rows=n_rows,
        matches=n_match,
        recall=n_match / n_truth if n_truth else float("nan"),
        idf1=2 * id_tp / (n_truth + n_rows) if n_truth + n_rows else float("nan"),
        id_true_positives=id_tp,
        half_visible=n_half,
        half_visible_matched=half_matched,
        recall_half_visible=half_matched / n_half if n_half else float("nan"),
        precision=n_match / n_rows if n_rows else float("nan"),
        mota=1.0 - ((n_truth - n_match) + (n_rows - n_match) + id_switches) / n_truth
        if n_truth
        else float("nan"),
        id_switches=id_switches,
        fragments=sum(p.fragments for p in persons),
        ids_per_person=(
            float(np.mean([len(p.track_ids) for p in matched_persons]))
            if matched_persons
            else float("nan")
        ),
        track_ids=len(np.unique(t_pid)),
        joints_frame=joints_frame,
        mpjpe_mm=_finite_mm(err["mpjpe"]),
        pa_mpjpe_mm=_finite_mm(err["pa"]),
        root_error_mm=_finite_mm(err["root"]),
        root_error_median_mm=_finite_mm(err["root"], np.median),
        persons=tuple(persons),
        mirrored_rows=int(mirrored.sum()),
        mpjpe_mm_not_mirrored=_finite_mm(err["mpjpe"][~mirrored]) if len(err["mpjpe"]) else None,
        pose_not_finite=int((~np.isfinite(np.stack(list(err.values())))).any(0).sum()),
    )


def _mirrored_rows(
    table, meta: dict, joints_world: np.ndarray, pairs: list, camera: Camera | None
) -> np.ndarray:
    """(len(pairs),) bool: the matched row's landmarks are mirrored against its truth person."""
    cal = meta.get("calibration") or {}
    if camera is None and cal.get("calibrated") and "K" in cal:
        camera = TrackingView.from_json(cal).camera
    landmarks = landmark_array(table)
    if not pairs or camera is None or landmarks is None:
        return np.zeros(len(pairs), bool)
    landmarks = landmarks[[r for r, _ in pairs]]
    world = joints_world[[g for _, g in pairs]].astype(np.float64)
    reference = camera.project(world.reshape(-1, 3)).reshape(len(pairs), -1, 2)
    return mirrored_landmarks(landmarks, reference)

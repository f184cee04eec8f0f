"""Track evaluation (gst.track.evaluate) against hand-computed values and an independent
brute-force reference: CLEAR MOT matching (a person keeps their last track while it overlaps,
the rest by the most pairs, then the largest IoU), id switches, fragments, MOTA, and IDF1 with
its one-to-one id pairing found by trying every permutation. Plus the edge cases: no rows, no
visible truth, one frame, a person never seen, strided frames, half visibility at 12 of 24
joints, and a row whose joints are not finite."""

import itertools
import json

import numpy as np
import pyarrow.parquet as pq
import pytest
from test_track_evaluate import CAM, write_tracks, write_truth_tables

from gst.track.evaluate import evaluate_tracks
from gst.track.evaluation_report import evaluation_markdown, write_evaluation_json
from gst.track.schema import SMPL_JOINT_NAMES

JOINTS = np.zeros((24, 3))
JOINTS[:, 2] = np.arange(24) * 0.05  # a non-degenerate skeleton shared by truth and tracks


def build_scene(d, truth, n_frames, n_visible=None):
    """A scene whose people.parquet has every person of `truth` ({(frame, person): corner box,
    NaN for a person the camera does not see}) in every frame; `n_visible`: {(frame, person):
    joints visible (default 24)}."""
    n_visible = n_visible or {}
    pids = sorted({p for _, p in truth})
    rows = [(f, p) for f in range(n_frames) for p in pids]
    keys = sorted(truth)
    write_truth_tables(
        d,
        [(f, p, JOINTS) for f, p in rows],
        # truth boxes in corner convention; the tables' in pixel-centre edges
        [(*k, np.asarray(truth[k], np.float32) - 0.5, n_visible.get(k, 24)) for k in keys],
    )
    return d


def _iou(a, b):
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def reference(truth, tracks, frames, min_iou=0.3):
    """CLEAR MOT and IDF1 written out plainly, with brute force where the code uses the
    Hungarian algorithm. truth: {(frame, person): box} (seen people only); tracks:
    [(frame, id, box)]; frames: the processed frames."""
    last, history, overlaps = {}, {}, {}
    n_truth = n_rows = tp = 0
    for f in frames:
        people = sorted(p for (g, p) in truth if g == f)
        hyps = [(t, b) for (g, t, b) in tracks if g == f]
        n_truth, n_rows = n_truth + len(people), n_rows + len(hyps)
        iou = [[_iou(truth[(f, p)], b) for _, b in hyps] for p in people]
        for i, p in enumerate(people):
            for j, (t, _) in enumerate(hyps):
                if iou[i][j] >= min_iou:
                    overlaps[(p, t)] = overlaps.get((p, t), 0) + 1
        match, used = {}, set()
        for i, p in enumerate(people):  # continuity: the last track, while it still overlaps
            for j, (t, _) in enumerate(hyps):
                if p in last and t == last[p] and j not in used and iou[i][j] >= min_iou:
                    match[i] = j
                    used.add(j)
                    break
        free_p = [i for i in range(len(people)) if i not in match]
        free_h = [j for j in range(len(hyps)) if j not in used]
        best, best_key = {}, (-1, -1.0)
        for perm in itertools.permutations(free_h + [None] * len(free_p), len(free_p)):
            pairs = [
                (i, j)
                for i, j in zip(free_p, perm, strict=True)
                if j is not None and iou[i][j] >= min_iou
            ]
            key = (len(pairs), sum(iou[i][j] for i, j in pairs))
            if key > best_key:
                best, best_key = dict(pairs), key
        match.update(best)
        for i, p in enumerate(people):
            j = match.get(i)
            history.setdefault(p, []).append(None if j is None else hyps[j][0])
            if j is not None:
                last[p] = hyps[j][0]
        tp += len(match)
    switches = fragments = 0
    for ids in history.values():
        matched = [t for t in ids if t is not None]
        switches += sum(a != b for a, b in itertools.pairwise(matched))
        at = [k for k, t in enumerate(ids) if t is not None]
        span = ids[at[0] : at[-1] + 1] if at else []
        # CLEAR MOT fragmentation: a tracked -> untracked transition within the tracked span
        fragments += sum(a is not None and b is None for a, b in itertools.pairwise(span))
    people = sorted({p for p, _ in overlaps})
    ids = sorted({t for _, t in overlaps})
    idtp = max(
        (
            sum(overlaps.get((p, t), 0) for p, t in zip(people, perm, strict=True) if t is not None)
            for perm in itertools.permutations(ids + [None] * len(people), len(people))
        ),
        default=0,
    )
    return {
        "truth_instances": n_truth,
        "track_rows": n_rows,
        "matches": tp,
        "id_switches": switches,
        "fragments": fragments,
        "id_true_positives": idtp,
        "mota": 1 - ((n_truth - tp) + (n_rows - tp) + switches) / n_truth,
        "idf1": 2 * idtp / (n_truth + n_rows),
    }


def _rows(tracks):
    return [(f, t, b, JOINTS) for f, t, b in tracks]


def test_clear_mot_and_idf1_match_a_brute_force_reference(tmp_path):
    """Random small sequences (1-3 people, up to 4 ids, crowded boxes, stride 1 or 2 with
    rows in the skipped frames too, which must not count)."""
    rng = np.random.default_rng(0)
    checked = 0
    for case in range(40):
        n_frames, n_people, n_ids = (int(x) for x in rng.integers(1, [7, 4, 5], endpoint=True))
        stride = int(rng.integers(1, 3))
        truth = {}
        for f, p in itertools.product(range(n_frames), range(n_people)):
            if rng.random() < 0.8:
                x, y = rng.uniform(0, 25, 2)
                truth[(f, p)] = np.array([x, y, x + 30, y + 40])
        tracks = []
        for f in range(n_frames):
            here = [k for k in truth if k[0] == f]
            for t in sorted(set(rng.integers(0, n_ids, rng.integers(0, 4)).tolist())):
                if here and rng.random() < 0.7:
                    b = truth[here[rng.integers(len(here))]] + rng.normal(0, 6, 4)
                else:
                    x, y = rng.uniform(0, 25, 2)
                    b = np.array([x, y, x + 30, y + 40])
                tracks.append((f, t, b.astype(np.float32).astype(np.float64)))
        if not truth or not tracks:
            continue
        frames = range(0, n_frames, stride)
        if not any(f in frames for f, _ in truth):
            continue
        d = tmp_path / str(case)
        scene = build_scene(d / "scene", truth, n_frames)
        path = write_tracks(d / "t.parquet", _rows(tracks), stride=stride, frames=n_frames)
        ev = evaluate_tracks(path, scene, CAM)
        want = reference(truth, tracks, frames)
        got = {k: getattr(ev, k) for k in want}
        assert got == pytest.approx(want), (case, got, want)
        checked += 1
    assert checked >= 30


BOX_A = np.array([10.0, 10, 50, 110])
BOX_B = np.array([200.0, 10, 240, 110])


def test_idf1_pairs_ids_to_people_for_the_most_overlap_not_greedily(tmp_path):
    """Person A is seen in frames 0-6, B in 4-6. Track 0 follows A in 0-3, then B; track 1
    follows A in 4-6. Overlaps (A, 0) 4, (A, 1) 3, (B, 0) 3: taking the largest first (A-0)
    leaves IDTP 4; the best one-to-one pairing (A-1, B-0) has IDTP 6, IDF1 = 12 / (10 + 10).
    A changes id once (MOTA 1 - 1/10); nothing is missed, so no fragment."""
    truth = {(f, 1): BOX_A for f in range(7)}  # A is person 1, B person 2
    truth |= {(f, 2): BOX_B if f >= 4 else np.full(4, np.nan) for f in range(7)}
    scene = build_scene(tmp_path / "scene", truth, 7)
    tracks = [(f, 0, BOX_A) for f in range(4)]
    tracks += [(f, 0, BOX_B) for f in range(4, 7)] + [(f, 1, BOX_A) for f in range(4, 7)]
    ev = evaluate_tracks(write_tracks(tmp_path / "t.parquet", _rows(tracks), frames=7), scene, CAM)
    assert ev.truth_instances == 10 and ev.track_rows == 10 and ev.matches == 10
    assert ev.id_true_positives == 6 and ev.idf1 == pytest.approx(0.6)
    assert [p.id_switches for p in ev.persons] == [1, 0] and ev.fragments == 0
    assert ev.mota == pytest.approx(0.9) and ev.recall == ev.precision == 1.0
    assert [p.track_ids for p in ev.persons] == [(0, 1), (0,)] and ev.ids_per_person == 1.5


def test_a_gap_then_another_id_is_one_switch_and_one_fragment(tmp_path):
    """A seen in frames 0-5, matched to 7, 7, -, -, 9, 9: one switch, one fragment (the resume),
    2 misses: MOTA 1 - (2 + 0 + 1) / 6; IDTP 2 (either id), IDF1 2 * 2 / (6 + 4)."""
    scene = build_scene(tmp_path / "scene", {(f, 1): BOX_A for f in range(6)}, 6)
    tracks = [(0, 7, BOX_A), (1, 7, BOX_A), (4, 9, BOX_A), (5, 9, BOX_A)]
    ev = evaluate_tracks(write_tracks(tmp_path / "t.parquet", _rows(tracks), frames=6), scene, CAM)
    assert (ev.id_switches, ev.fragments, ev.matches) == (1, 1, 4)
    assert ev.mota == pytest.approx(0.5) and ev.idf1 == pytest.approx(0.4)


def test_stride_skipped_frames_are_neither_misses_nor_fragments(tmp_path):
    """Truth in frames 0-6, tracks processed at stride 3 (frames 0, 3, 6) with a stray row in
    skipped frame 4: 3 frames, 3 matches, no misses or false rows, no fragment."""
    scene = build_scene(tmp_path / "scene", {(f, 1): BOX_A for f in range(7)}, 7)
    tracks = [(0, 0, BOX_A), (3, 0, BOX_A), (4, 5, BOX_B), (6, 0, BOX_A)]
    path = write_tracks(tmp_path / "t.parquet", _rows(tracks), stride=3, frames=7)
    ev = evaluate_tracks(path, scene, CAM)
    assert (ev.frames, ev.truth_instances, ev.track_rows, ev.matches) == (3, 3, 3, 3)
    assert ev.fragments == 0 and ev.mota == 1.0 and ev.idf1 == 1.0


def test_one_frame_and_a_person_never_seen(tmp_path):
    """One frame; person 2 is in the scene but not in the camera: not a truth instance, not a
    per-person entry."""
    truth = {(0, 1): BOX_A, (0, 2): np.full(4, np.nan)}
    scene = build_scene(tmp_path / "scene", truth, 1)
    path = write_tracks(tmp_path / "t.parquet", _rows([(0, 3, BOX_A)]), frames=1)
    ev = evaluate_tracks(path, scene, CAM)
    assert (ev.frames, ev.truth_instances, ev.matches) == (1, 1, 1)
    assert ev.mota == ev.idf1 == ev.recall == ev.precision == 1.0
    assert [p.truth_person_id for p in ev.persons] == [1] and ev.persons[0].track_ids == (3,)
    assert ev.mpjpe_mm == pytest.approx(0.0, abs=1e-6)


def test_no_tracked_rows(tmp_path):
    scene = build_scene(tmp_path / "scene", {(f, 1): BOX_A for f in range(3)}, 3)
    path = write_tracks(tmp_path / "t.parquet", _rows([(0, 0, BOX_A)]), frames=3)
    pq.write_table(pq.read_table(path).slice(0, 0), path)  # the metadata stays, no rows
    ev = evaluate_tracks(path, scene, CAM)
    assert (ev.truth_instances, ev.track_rows, ev.matches, ev.track_ids) == (3, 0, 0, 0)
    assert ev.recall == 0.0 and ev.mota == 0.0 and ev.idf1 == 0.0 and np.isnan(ev.precision)
    assert ev.mpjpe_mm is None and np.isnan(ev.ids_per_person)
    assert ev.persons[0].frames_visible == 3 and ev.persons[0].track_ids == ()
    d = json.loads(write_evaluation_json(ev, tmp_path / "ev.json").read_text())
    assert d["precision"] is None and d["mpjpe_mm"] is None
    assert "| cam0 | 3 | 0.000 | 0.000 | n/a | 0.000 | 0.000 |" in evaluation_markdown([ev])


def test_no_visible_truth_people(tmp_path):
    """Rows where the camera sees nobody are false rows; the rates over truth are undefined."""
    scene = build_scene(tmp_path / "scene", {(f, 1): np.full(4, np.nan) for f in range(3)}, 3)
    path = write_tracks(tmp_path / "t.parquet", _rows([(1, 0, BOX_A)]), frames=3)
    ev = evaluate_tracks(path, scene, CAM)
    assert (ev.frames, ev.truth_instances, ev.track_rows, ev.matches) == (3, 0, 1, 0)
    assert np.isnan(ev.recall) and np.isnan(ev.mota) and ev.precision == 0.0 and ev.idf1 == 0.0
    assert ev.persons == ()


def test_half_visible_means_at_least_12_of_24_joints(tmp_path):
    """Frames 0-3, visible joints 12, 11, 24, 0; the tracks miss frames 1 and 3 (11 and 0
    joints) and frame 2: half visible are frames 0 and 2, one of them matched."""
    truth = {(f, 1): BOX_A for f in range(4)}
    scene = build_scene(
        tmp_path / "scene", truth, 4, n_visible={(0, 1): 12, (1, 1): 11, (2, 1): 24, (3, 1): 0}
    )
    path = write_tracks(tmp_path / "t.parquet", _rows([(0, 0, BOX_A)]), frames=4)
    ev = evaluate_tracks(path, scene, CAM)
    assert (ev.half_visible, ev.half_visible_matched) == (2, 1)
    assert ev.recall_half_visible == 0.5 and ev.recall == 0.25


def test_a_row_with_non_finite_joints_is_counted_not_averaged_in(tmp_path):
    """Four matched rows, one with a NaN elbow and all 10 cm off: that row's MPJPE and
    PA-MPJPE are NaN. The pose means are over the other rows (0 mm) and the row is counted,
    where one NaN row made the video's and the person's MPJPE NaN (null in the JSON, "n/a" in
    the report, as if the video were uncalibrated). Its pelvis is finite: the root error keeps
    it (100 mm over 4 rows = 25 mm mean)."""
    scene = build_scene(tmp_path / "scene", {(f, 1): BOX_A for f in range(4)}, 4)
    bad = JOINTS + [0.1, 0.0, 0.0]
    bad[SMPL_JOINT_NAMES.index("left_elbow")] = np.nan
    rows = [(f, 0, BOX_A, bad if f == 2 else JOINTS) for f in range(4)]
    ev = evaluate_tracks(write_tracks(tmp_path / "t.parquet", rows, frames=4), scene, CAM)
    assert ev.matches == 4 and ev.pose_not_finite == 1
    assert ev.mpjpe_mm == pytest.approx(0.0, abs=1e-6)
    assert ev.pa_mpjpe_mm == pytest.approx(0.0, abs=1e-3)
    assert ev.mpjpe_mm_not_mirrored == pytest.approx(0.0, abs=1e-6)
    assert ev.root_error_mm == pytest.approx(25.0) and ev.root_error_median_mm == pytest.approx(0)
    assert ev.persons[0].mpjpe_mm == pytest.approx(0.0, abs=1e-6)
    assert ev.persons[0].root_error_mm == pytest.approx(25.0)

"""Fusion accuracy and speed beside the peers, on the same DETECTED 2D input.

    python benchmarks/bench_fuse.py --workspace workspace/demo \\
        [--peers-python /work/bench-venv/bin/python]

Input: the scene's crop store and BlazePose landmarks per crop as the fuse stage reads them
(`gst.fuse.observations.crop_landmarks`: the landmarks the keypoint extraction stored, or, for
an older store without them, BlazePose's refined reading of each crop; the stage's second look
at crowded crops, `relook_crowded`, is not run here), read afresh on every run (a cache beside
the store served stale landmarks after a re-extraction with as many crops). The fit runs at the
scene's frame rate (`synth/scene.json`), as the stage does. Every method sees the same
observations, exported to one .npz (per person-frame and camera: undistorted full-image pixels,
confidence, and the cameras' K, R, t); the peers run in their own virtual environment (benchmark
tools, never project dependencies):

- ours, triangulation: gst.fuse.triangulate with the fuse stage's defaults (pair consensus over
  the 8 most confident views with the people's silhouettes voting, a second pass voting with
  the neighbouring frames, weighted DLT, leave-one-out, Gauss-Newton); the silhouettes are
  input the peers do not get, and their computation is counted in this row's time;
- ours, triangulation, landmarks only: the same without silhouettes, pair consensus or votes
  (the like-for-like row: the peers' input exactly);
- ours, body fit: gst.fuse.fit (markers, all cameras, whole clip, Levenberg-Marquardt), with
  the stage's floor term and up direction (gst.fuse.floor.scene_floor); the stage's later
  rounds (camera corrections, crops cut again from the bodies) are not run here;
- Pose2Sim (the version in the peers' environment, printed with its rows): its own
  `Pose2Sim.triangulation.triangulation_from_best_cameras` with its Config.toml defaults
  (15 px, at least 2 cameras, every subset of cameras tried as more are left out; NaN where no
  subset reprojects within 15 px), landmarks below likelihood 0.3 unused;
- aniposelib: `CameraGroup.triangulate`, and `optim_points` (its optim=True path: temporal
  smoothness and limb-length constraints; in 0.8.0 both are unit-free, the smoothness scaled by
  the track's own mean frame-to-frame motion and the limbs in percent, so the rig in metres
  weighs them as one in millimetres would).

Every method gets one untimed call first (ours on all person-frames; the peers on a few:
imports, and aniposelib's first call compiles its code with numba/jax, about 50x its later
calls), then the median of `--repeats` calls, with `--threads` threads for torch and the
peers' OpenMP/BLAS/numba alike. Every method is scored on the same person-frames, matched to
the truth once (per frame, Hungarian, on all methods' per-joint median; pairs more than 0.5 m
apart dropped), and on the (person-frame, joint)s that all of them returned (a method that
leaves hard joints out or misses a person is not scored on fewer, easier ones); the share of
joints each returned is printed beside it. The body fit's 13 joints are the body model's, the
triangulations' their landmarks': the truth uses the same body model as the fit, so part of the
gap is one of definition (15-42 mm offsets between a landmark and its joint, fixed per person).

Two groupings of the same landmarks into people are scored: the extraction's person ids as
they are, and the people regrouped by 3D agreement (gst.fuse.regroup, part of the fuse stage),
so that what the regrouping gives and what the fit gives can be told apart, for every method.

MPJPE (mm, world frame) is over the 13 joints every method gives (hips, knees, ankles,
shoulders, elbows, wrists, pelvis = mid-hips; a landmark stands for its joint), and for the
body fit also over all 24 joints, with PA-MPJPE.
Speed: ms per person-frame after the 2D detection (`--threads` torch threads, 1 by default),
medians over `--repeats`; the body fit is then timed on subsets and copies of the scene
(frames x people x cameras) to show how its cost grows with them, and on the copies also in
`--processes` worker processes of one thread each (people split between them: the fit of one
person does not depend on another's; the body model loaded before the workers fork), the way
to use several cores. Machines shared with other work give noisy times; the ratios within one
run are what to compare.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's packages, not an installed copy

from benchmarks.cli import bench_parser  # noqa: E402
from benchmarks.timing import median_time  # noqa: E402
from gst.train.keypoints import BODY_FROM_BLAZEPOSE  # noqa: E402

# SMPL joint -> BlazePose landmarks: the 13 joints scored here are those the training's
# keypoint term uses
JOINTS13 = BODY_FROM_BLAZEPOSE

PEER_SCRIPT = r"""
import json, sys, time, numpy as np
from importlib.metadata import version
d = np.load(sys.argv[1]); out = {}; reps = int(sys.argv[3])
uv, conf, K, R, t = d["uv"], d["conf"], d["K"], d["R"], d["t"]  # uv (N, C, 33, 2), conf (N, C, 33)
N, C, M = conf.shape
ppl, frames = d["person"], d["frame"]
P = np.stack([K[c] @ np.c_[R[c], t[c]] for c in range(C)])
seen = np.isfinite(uv).all(-1) & (conf >= 0.3)  # Pose2Sim's likelihood threshold, for all

def timed(fn):
    # one untimed call on all person-frames first (imports; aniposelib compiles its
    # triangulation for each input size: a warm-up on 4 rows left the first timed call 25 x
    # slower), then the median of `reps` calls on all of them, as ours is timed
    fn(np.arange(N))
    runs = []
    for _ in range(reps):
        t0 = time.perf_counter(); X = fn(np.arange(N)); runs.append(time.perf_counter() - t0)
    return X, float(np.median(runs))

try:
    from Pose2Sim.triangulation import triangulation_from_best_cameras
    cfg = {"triangulation": {"reproj_error_threshold_triangulation": 15,
           "min_cameras_for_triangulation": 2, "handle_LR_swap": False,
           "undistort_points": False}}  # its Config.toml defaults (points are undistorted here)
    Pl = list(P)
    def pose2sim(rows):
        X = np.full((len(rows), M, 3), np.nan)
        for i, n in enumerate(rows):
            for m in range(M):
                x = np.where(seen[n, :, m], uv[n, :, m, 0], np.nan)
                y = np.where(seen[n, :, m], uv[n, :, m, 1], np.nan)
                lik = np.where(seen[n, :, m], conf[n, :, m], 0.0)
                if (lik > 0).sum() < 2:
                    continue
                Q, *_ = triangulation_from_best_cameras(cfg, [x, y, lik], [x, y, lik], Pl, None)
                X[i, m] = np.asarray(Q, float)[:3]
        return X
    X, sec = timed(pose2sim)
    out["pose2sim"] = {"points": X.tolist(), "seconds": sec, "version": version("pose2sim")}
except Exception as exc:
    import traceback; traceback.print_exc()
    out["pose2sim"] = {"error": repr(exc)}
try:
    from aniposelib.cameras import Camera, CameraGroup
    import cv2
    cams = [Camera(name=str(c), size=(1, 1), matrix=K[c], dist=np.zeros(5),
                   rvec=cv2.Rodrigues(R[c])[0].ravel(), tvec=t[c]) for c in range(C)]
    cg = CameraGroup(cams)
    pts = np.where(seen[..., None], uv, np.nan).transpose(1, 0, 2, 3)  # (C, N, M, 2)
    def anipose(rows):
        n = len(rows)
        return cg.triangulate(pts[:, rows].reshape(C, n * M, 2), undistort=True,
                              progress=False).reshape(n, M, 3)
    X, sec = timed(anipose)
    out["aniposelib"] = {"points": X.tolist(), "seconds": sec, "version": version("aniposelib")}
    # optim=True path, per person (its temporal terms need one track): smoothness + limbs
    limbs = [[11, 13], [13, 15], [12, 14], [14, 16], [23, 25], [25, 27], [24, 26], [26, 28],
             [11, 12], [23, 24], [11, 23], [12, 24]]
    def optim(rows):
        Xo = np.full((N, M, 3), np.nan)
        for p in np.unique(ppl[rows]):
            sel = rows[ppl[rows] == p]; sel = sel[np.argsort(frames[sel])]
            init = X[sel]
            # aniposelib needs finite starts: fill missing points from the track's median
            med = np.nanmedian(init, axis=0); init = np.where(np.isfinite(init), init, med)
            init = np.nan_to_num(init)
            sc = np.where(seen[sel], conf[sel], 0).transpose(1, 0, 2)
            Xo[sel] = cg.optim_points(pts[:, sel], init, constraints=limbs, scores=sc,
                                      reproj_error_threshold=15, verbose=False)
        Xo[~np.isfinite(X).all(-1)] = np.nan  # no evidence there (only a filled-in start)
        return Xo[rows]
    Xo, sec = timed(optim)
    out["aniposelib_optim"] = {"points": Xo.tolist(), "seconds": sec,
                               "version": version("aniposelib")}
except Exception as exc:
    import traceback; traceback.print_exc()
    out["aniposelib"] = out.get("aniposelib", {"error": repr(exc)})
    out["aniposelib_optim"] = {"error": repr(exc)}
json.dump(out, open(sys.argv[2], "w"))
"""


def _export(people, store, rig, path: Path) -> dict:
    """Full-image undistorted pixels per person-frame and camera (crops map back exactly)."""
    Kf = np.stack([rig[c].K for c in store.camera_names])
    rows = {k: [] for k in ("uv", "conf", "person", "frame")}
    for p in people:
        # crop px -> full px: K_full K_crop^-1 (same R, t, no distortion in both)
        A = np.einsum("cij,tcjk->tcik", Kf, np.linalg.inv(p.K))
        xh = np.concatenate([p.uv, np.ones(p.uv.shape[:-1] + (1,))], -1)
        full = np.einsum("tcij,tcmj->tcmi", A, xh)
        rows["uv"].append(full[..., :2] / full[..., 2:])
        rows["conf"].append(p.confidence)
        rows["person"].append(np.full(len(p.frames), p.person_id))
        rows["frame"].append(p.frames)
    arrays = {k: np.concatenate(v) for k, v in rows.items()}
    arrays.update(
        K=Kf,
        R=np.stack([rig[c].R for c in store.camera_names]),
        t=np.stack([rig[c].t for c in store.camera_names]),
    )
    np.savez(path, **arrays)
    return arrays


def _joints13(X: np.ndarray) -> np.ndarray:
    out = np.full(X.shape[:-2] + (24, 3), np.nan)
    for j, lms in JOINTS13.items():
        out[..., j, :] = X[..., list(lms), :].mean(-2)
    return out


def _match(reference, frame, truth, joints) -> np.ndarray:
    """(K, 2) pairs (row, truth row): per-frame Hungarian matching of `reference`'s person-frames
    to the truth over `joints`, pairs more than 0.5 m apart dropped. One matching for every
    method (`reference` is their per-joint median), so all are scored on the same pairs."""
    from scipy.optimize import linear_sum_assignment

    js = list(joints)
    pairs = []
    for f in np.unique(frame):
        mine = np.flatnonzero(frame == f)
        rows = np.flatnonzero(truth.frame == f)
        a, b = reference[mine][:, js], truth.joints_world[rows][:, js]
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # rows with no joint at all
            cost = np.nanmean(np.linalg.norm(a[:, None] - b[None], axis=-1), -1)
        cost = np.where(np.isfinite(cost), cost, 1e6)
        r, c = linear_sum_assignment(cost)
        pairs += [(mine[i], rows[k]) for i, k in zip(r, c, strict=True) if cost[i, k] < 0.5]
    return np.array(pairs, dtype=int).reshape(-1, 2)


def _score(pred, pairs, truth, joints=None) -> tuple[float, float, int]:
    """MPJPE and PA-MPJPE (mm) of `pred`'s rows against their truth rows, over `joints`
    (default all 24); a joint the method left out (NaN) is not scored."""
    from gst.metrics.pose import mpjpe, pa_mpjpe

    if not len(pairs):
        return float("nan"), float("nan"), 0
    js = list(range(24)) if joints is None else list(joints)
    P = pred[pairs[:, 0]][:, js]
    G = truth.joints_world[pairs[:, 1]][:, js]
    ok = np.isfinite(P).all(-1)
    scored = ok.any(-1)  # a person-frame none of whose joints every method gave: not scored
    P, G, ok = P[scored], G[scored], ok[scored]
    if not len(P):
        return float("nan"), float("nan"), 0
    Pt, Gt = torch.as_tensor(np.nan_to_num(P)), torch.as_tensor(G, dtype=torch.float64)
    v = torch.as_tensor(ok)
    pa = pa_mpjpe(Pt, Gt, valid=v)  # NaN under 3 joints (a similarity fits them exactly)
    return (
        float(mpjpe(Pt, Gt, valid=v).mean() * 1000),
        float(pa[torch.isfinite(pa)].mean() * 1000),
        len(P),
    )


def _peers(
    people, store, rig, python: str, keep: Path | None, repeats: int, threads: int
) -> tuple[dict, dict]:
    with tempfile.TemporaryDirectory() as tmp:
        inp, outp, script = Path(tmp) / "in.npz", Path(tmp) / "out.json", Path(tmp) / "peers.py"
        arr = _export(people, store, rig, inp)
        script.write_text(PEER_SCRIPT)
        if keep is not None:
            import shutil

            shutil.copy(inp, keep)
        if not Path(python).is_file():  # was an uncaught FileNotFoundError after our own work
            print(f"peers not run: no Python at {python} (--peers-python; or --skip-peers)")
            return {}, arr
        # the peers' numerical libraries get the threads our torch gets
        n = str(threads)
        env = {k: n for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                              "NUMBA_NUM_THREADS")}  # fmt: skip
        env["PATH"] = "/usr/bin:/bin"
        proc = subprocess.run([python, str(script), str(inp), str(outp), str(repeats)],
                              capture_output=True, text=True, env=env)  # fmt: skip
        peers = json.loads(outp.read_text()) if outp.is_file() else {}
        if proc.returncode:
            print(proc.stderr[-3000:])
    return peers, arr


_WORKER: dict = {}  # body, markers, floor, up: set before the pool forks, so no call loads them


def _fit_part(args):
    """Worker: fit some people on one core (torch threads 1)."""
    people, tris, fps = args
    torch.set_num_threads(1)
    from gst.fuse.fit import FitOptions, fit_people

    w = _WORKER
    return fit_people(
        w["body"], w["markers"], people, tris, fps, FitOptions(), floor=w["floor"], up=w["up"]
    )


def _fit_in_processes(pool, people, tris, fps: float, n: int):
    parts = [(people[k::n], tris[k::n], fps) for k in range(n) if people[k::n]]
    return [f for part in pool.map(_fit_part, parts) for f in part]


def _copy(p, person_id: int, frames_keep: int, cams_keep: int):
    from dataclasses import replace

    q = p.select(np.arange(len(p.frames)) < frames_keep)
    drop = np.arange(q.rows.shape[1]) >= cams_keep
    q.uv[:, drop] = np.nan
    q.confidence[:, drop] = 0.0
    q.rows[:, drop] = -1
    return replace(q, person_id=person_id)


def main() -> None:
    ap = bench_parser(__doc__)
    ap.add_argument("--workspace", type=Path, default=ROOT / "workspace" / "demo")
    ap.add_argument("--peers-python", default="/work/bench-venv/bin/python")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1, help="torch threads of the main process")
    ap.add_argument(
        "--processes", type=int, default=2, help="worker processes for the multi-core fit rows"
    )
    ap.add_argument(
        "--keep-input",
        type=Path,
        help="also save the exported peer input here (one file per grouping: NAME_extraction_ids, "
        "NAME_regrouped)",
    )
    ap.add_argument("--skip-peers", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from calibration.formats import read_rig
    from gst.body import load_body_model
    from gst.body.markers import MarkerModel
    from gst.data.store import CropStore
    from gst.fuse.fit import FitOptions, fit_people
    from gst.fuse.floor import scene_floor
    from gst.fuse.observations import crop_landmarks, group_by_person
    from gst.fuse.regroup import regroup_people
    from gst.fuse.scene import FuseOptions
    from gst.fuse.silhouettes import crop_silhouettes
    from gst.fuse.triangulate import triangulate_person
    from synth.truth import read_scene_truth

    ws = args.workspace
    store = CropStore(ws / "crops" / "crops.h5")
    rig = read_rig(ws / "calibration" / "rig.json", "rig")
    truth = read_scene_truth(ws / "synth")
    fps = float(json.loads((ws / "synth" / "scene.json").read_text())["fps"])
    lm = crop_landmarks(store)
    # as the fuse stage groups them: people with nothing readable left out (scene._readable_only)
    extracted = [p for p in group_by_person(store, lm) if p.readable]
    tri_options = FuseOptions().triangulation  # what the fuse stage triangulates with
    # the people's silhouettes vote in our pair consensus: their cost is part of ours
    t_sil, silhouettes = median_time(
        lambda: crop_silhouettes(store, {c.name: (c.width, c.height) for c in rig.cameras}), 1
    )
    # like for like with the peers: landmarks only (no silhouettes, no pair consensus or votes)
    plain_options = replace(tri_options, consensus_views=0, temporal_weight=0.0)

    def triangulate(p):
        return triangulate_person(p, tri_options, silhouettes)

    t_regroup, (regrouped, report) = median_time(
        lambda: regroup_people(extracted, FuseOptions().regroup, fps), 1
    )  # the stage's options at the capture's frame rate (its jump and gap limits are per frame)
    regrouped = [p for p in regrouped if p.readable]
    body = load_body_model("anny")
    markers = MarkerModel.load()
    up = np.asarray(rig.up, np.float64)

    def floor_of(tris):  # the fuse stage's floor: its default option, on these triangulations
        return scene_floor(
            [t.points if t is not None else None for t in tris], up, FuseOptions().floor
        )

    def fit(people, tris):
        return fit_people(
            body, markers, people, tris, fps, FitOptions(), floor=floor_of(tris), up=up
        )

    results = []
    fits_for_speed = None
    for grouping, people in (("extraction ids", extracted), ("regrouped", regrouped)):
        n_pf = sum(len(p.frames) for p in people)
        person = np.concatenate([np.full(len(p.frames), p.person_id) for p in people])
        frame = np.concatenate([p.frames for p in people])
        methods = {}  # name -> (joints (N, 24, 3) in the export's row order, seconds, note)

        sec, tris = median_time(
            lambda ps=people: [triangulate(p) for p in ps], args.repeats, warmup=1
        )
        methods["ours: triangulation"] = (
            _joints13(np.concatenate([t.points for t in tris])), sec + t_sil,
            "pair consensus, silhouettes (timed in), votes",
        )  # fmt: skip
        sec, plain = median_time(
            lambda ps=people: [triangulate_person(p, plain_options) for p in ps],
            args.repeats,
            warmup=1,
        )
        methods["ours: triangulation, landmarks only"] = (
            _joints13(np.concatenate([t.points for t in plain])),
            sec,
            "as the peers' input",
        )
        sec, fits = median_time(lambda ps=people, ts=tris: fit(ps, ts), args.repeats, warmup=1)
        fits_for_speed = people
        J = np.concatenate(
            [f.joints[np.isin(f.frames, p.frames)] for f, p in zip(fits, people, strict=True)]
        )
        methods["ours: body fit"] = (J, sec, "after triangulation")
        if not args.skip_peers:
            peers, arr = _peers(
                people,
                store,
                rig,
                args.peers_python,
                # one file per grouping (the second overwrote the first)
                None
                if args.keep_input is None
                else args.keep_input.with_stem(
                    f"{args.keep_input.stem}_{grouping.replace(' ', '_')}"
                ),
                args.repeats,
                args.threads,
            )
            assert (arr["person"] == person).all() and (arr["frame"] == frame).all()
            for key, name in (("pose2sim", "Pose2Sim {}: triangulation_from_best_cameras"),
                              ("aniposelib", "aniposelib {}: triangulate"),
                              ("aniposelib_optim", "aniposelib {}: optim_points")):  # fmt: skip
                r = peers.get(key, {"error": "not run"})
                name = name.format(r.get("version", "(version unknown)"))
                if "error" in r:
                    results.append((grouping, name, np.nan, np.nan, 0, np.nan, np.nan,
                                    r["error"][:80]))  # fmt: skip
                    continue
                methods[name] = (_joints13(np.array(r["points"], dtype=float)), r["seconds"], "")
        # every method scored on the (person-frame, joint)s all of them gave: a method that
        # leaves hard joints out is not scored on fewer, easier ones
        js = list(JOINTS13)
        common = np.logical_and.reduce(
            [np.isfinite(X[:, js]).all(-1) for X, _, _ in methods.values()]
        )
        # ... and on the same person-frames: one matching to the truth, by all methods' median
        # (each matched on its own, a method's worst person-frames fell out of its own score)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # joints no method gave
            reference = np.nanmedian(np.stack([X for X, _, _ in methods.values()]), axis=0)
        pairs = _match(reference, frame, truth, js)
        for name, (X, sec, note) in methods.items():
            coverage = float(np.isfinite(X[:, js]).all(-1).mean())
            masked = X.copy()
            masked[:, js] = np.where(common[..., None], X[:, js], np.nan)
            mp, pa, n = _score(masked, pairs, truth, JOINTS13)
            label = name + (" (13 joints)" if name == "ours: body fit" else "")
            results.append((grouping, label, mp, pa, n, 1000 * sec / n_pf, coverage, note))
            if name == "ours: body fit":
                mp, pa, n = _score(X, pairs, truth)
                results.append((grouping, "ours: body fit (24 joints)", mp, pa, n,
                                1000 * sec / n_pf, 1.0, "all 24, not masked"))  # fmt: skip

    n_pf = sum(len(p.frames) for p in extracted)
    print(f"\n{n_pf} person-frames, {len(store.camera_names)} cameras, detected 2D (BlazePose), "
          f"torch threads {args.threads}; regrouping: {report.tracks} people from "
          f"{len(extracted)} extraction ids, "
          f"{1000 * t_regroup / n_pf:.2f} ms / person-frame\n")  # fmt: skip
    print("MPJPE over the (person-frame, joint)s every method gave; joints given: the share of "
          "the 13 scored joints a method returned (before that common mask)\n")  # fmt: skip
    print(
        "| grouping | method | MPJPE mm | PA-MPJPE mm | person-frames | ms / person-frame | "
        "joints given | note |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for grouping, name, mp, pa, n, ms, cov, note in results:
        print(f"| {grouping} | {name} | {mp:.1f} | {pa:.1f} | {n} | {ms:.2f} | {cov:.3f} | "
              f"{note} |")  # fmt: skip

    # linearity of the fit: subsets of frames and cameras, and copies of the people
    print("\n| fit subset | person-frames | cameras | seconds | person-frames / s | "
          "us / (person-frame x camera) |")  # fmt: skip
    print("| --- | --- | --- | --- | --- | --- |")
    import multiprocessing as mp

    floor = floor_of([triangulate(p) for p in fits_for_speed])
    _WORKER.update(body=body, markers=markers, floor=floor, up=up)
    pool = mp.get_context("fork").Pool(args.processes) if args.processes > 1 else None
    C = len(store.camera_names)
    T = max(len(p.frames) for p in fits_for_speed)
    for frames_keep, cams_keep, copies in ((T // 4, C, 1), (T // 2, C, 1), (T, C, 1),
                                           (T, C // 2, 1), (T, C, 2), (T, C, 4)):  # fmt: skip
        sub = [_copy(p, 1000 * k + p.person_id, frames_keep, cams_keep)
               for k in range(copies) for p in fits_for_speed]  # fmt: skip
        sub_tris = [triangulate(q) for q in sub]
        sec, _ = median_time(lambda s=sub, st=sub_tris: fit(s, st), args.repeats)
        pf = sum(len(q.frames) for q in sub)
        print(f"| {frames_keep} frames x {len(sub)} people | {pf} | {cams_keep} | {sec:.2f} | "
              f"{pf / sec:.1f} | {1e6 * sec / (pf * cams_keep):.0f} |")  # fmt: skip
        if pool is not None and copies > 1:
            sec, _ = median_time(
                lambda s=sub, st=sub_tris: _fit_in_processes(pool, s, st, fps, args.processes),
                args.repeats,
            )
            print(f"| same, {args.processes} processes x 1 thread | {pf} | {cams_keep} | "
                  f"{sec:.2f} | {pf / sec:.1f} | {1e6 * sec / (pf * cams_keep):.0f} |")  # fmt: skip
    if pool is not None:
        pool.close()
        pool.join()  # workers left to the interpreter's exit are killed mid-teardown


if __name__ == "__main__":
    main()

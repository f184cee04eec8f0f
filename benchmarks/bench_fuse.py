"""Fusion accuracy and speed beside the peers, on the same DETECTED 2D input.

    python benchmarks/bench_fuse.py --workspace workspace/demo [--peers-python /work/bench-venv/bin/python]

Input: the scene's crop store and BlazePose landmarks per crop (computed once, cached beside
the store as `fuse_bench_landmarks.npy`). Every method sees the same observations, exported to
one .npz (per person-frame and camera: undistorted full-image pixels, confidence, and the
cameras' K, R, t); the peers run in their own virtual environment (they are benchmark tools,
never project dependencies) on that file:

- ours, triangulation: gst.fuse.triangulate (weighted DLT + leave-one-out + Gauss-Newton);
- ours, body fit: gst.fuse.fit (markers, all cameras, whole clip);
- Pose2Sim 0.10.49: its weighted DLT (`Pose2Sim.common.weighted_triangulation`) inside its
  camera-exclusion loop (drop views while the mean reprojection error exceeds 15 px);
- aniposelib 0.8.0: `CameraGroup.triangulate`, and `optim_points` (its optim=True path:
  temporal smoothness and limb-length constraints).

MPJPE (mm, world frame, per-frame Hungarian matching to the truth) is over the 13 joints every
method gives (hips, knees, ankles, shoulders, elbows, wrists, pelvis = mid-hips; a landmark
stands for its joint), and for the body fit also over all 24 joints, with PA-MPJPE.
Speed: ms per person-frame after the 2D detection, single thread; the body fit is timed over
subsets (frames x people x cameras) to show that its cost is linear in them.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
# SMPL joint -> BlazePose landmarks (gst.train.keypoints.BODY_FROM_BLAZEPOSE)
JOINTS13 = {0: (23, 24), 1: (23,), 2: (24,), 4: (25,), 5: (26,), 7: (27,), 8: (28,),
            16: (11,), 17: (12,), 18: (13,), 19: (14,), 20: (15,), 21: (16,)}  # fmt: skip

PEER_SCRIPT = r"""
import json, sys, time, numpy as np
d = np.load(sys.argv[1]); out = {}
uv, conf, K, R, t = d["uv"], d["conf"], d["K"], d["R"], d["t"]  # uv (N, C, 33, 2), conf (N, C, 33)
N, C, M = conf.shape
ppl, frames = d["person"], d["frame"]
P = np.stack([K[c] @ np.c_[R[c], t[c]] for c in range(C)])
seen = np.isfinite(uv).all(-1) & (conf >= 0.3)
try:
    from Pose2Sim.common import weighted_triangulation
    t0 = time.perf_counter(); X = np.full((N, M, 3), np.nan)
    for n in range(N):
        for m in range(M):
            cams = list(np.flatnonzero(seen[n, :, m]))
            while len(cams) >= 2:
                Q = weighted_triangulation([P[c] for c in cams], list(uv[n, cams, m, 0]),
                                           list(uv[n, cams, m, 1]), list(conf[n, cams, m]))
                q = np.r_[np.asarray(Q)[:3], 1.0]
                pr = np.stack([P[c] @ q for c in cams]); pr = pr[:, :2] / pr[:, 2:]
                err = np.linalg.norm(pr - uv[n, cams, m], axis=1)
                if err.mean() <= 15 or len(cams) == 2:
                    X[n, m] = q[:3]; break
                # Pose2Sim drops the camera whose removal helps most; one at a time
                best = None
                for c in cams:
                    rest = [k for k in cams if k != c]
                    Q2 = weighted_triangulation([P[k] for k in rest], list(uv[n, rest, m, 0]),
                                                list(uv[n, rest, m, 1]), list(conf[n, rest, m]))
                    q2 = np.r_[np.asarray(Q2)[:3], 1.0]
                    pr2 = np.stack([P[k] @ q2 for k in rest]); pr2 = pr2[:, :2] / pr2[:, 2:]
                    e2 = np.linalg.norm(pr2 - uv[n, rest, m], axis=1).mean()
                    if best is None or e2 < best[0]: best = (e2, c)
                cams.remove(best[1])
    out["pose2sim"] = {"points": X.tolist(), "seconds": time.perf_counter() - t0}
except Exception as exc:
    out["pose2sim"] = {"error": repr(exc)}
try:
    from aniposelib.cameras import Camera, CameraGroup
    import cv2
    cams = [Camera(name=str(c), size=(1, 1), matrix=K[c], dist=np.zeros(5),
                   rvec=cv2.Rodrigues(R[c])[0].ravel(), tvec=t[c]) for c in range(C)]
    cg = CameraGroup(cams)
    pts = np.where(seen[..., None], uv, np.nan).transpose(1, 0, 2, 3)  # (C, N, M, 2)
    t0 = time.perf_counter()
    X = cg.triangulate(pts.reshape(C, N * M, 2), undistort=True, progress=False).reshape(N, M, 3)
    out["aniposelib"] = {"points": X.tolist(), "seconds": time.perf_counter() - t0}
    # optim=True path, per person (its temporal terms need one track): smoothness + limbs
    limbs = [[11, 13], [13, 15], [12, 14], [14, 16], [23, 25], [25, 27], [24, 26], [26, 28],
             [11, 12], [23, 24], [11, 23], [12, 24]]
    t0 = time.perf_counter(); Xo = np.full((N, M, 3), np.nan)
    for p in np.unique(ppl):
        sel = np.flatnonzero(ppl == p); sel = sel[np.argsort(frames[sel])]
        init = X[sel]
        # aniposelib needs finite starts: fill missing points from the track's median
        med = np.nanmedian(init, axis=0); init = np.where(np.isfinite(init), init, med)
        init = np.nan_to_num(init)
        sc = np.where(seen[sel], conf[sel], 0).transpose(1, 0, 2)
        Xo[sel] = cg.optim_points(pts[:, sel], init, constraints=limbs, scores=sc,
                                  reproj_error_threshold=15, verbose=False)
    out["aniposelib_optim"] = {"points": Xo.tolist(), "seconds": time.perf_counter() - t0}
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


def _score(pred, person, frame, truth, joints=None) -> tuple[float, float, int]:
    """Per-frame Hungarian matching; MPJPE and PA-MPJPE (mm) over `joints` (default all)."""
    from scipy.optimize import linear_sum_assignment

    from gst.metrics.pose import mpjpe, pa_mpjpe

    js = list(range(24)) if joints is None else list(joints)
    P, G = [], []
    for f in np.unique(frame):
        mine = np.flatnonzero(frame == f)
        rows = np.flatnonzero(truth.frame == f)
        a = pred[mine][:, js]
        b = truth.joints_world[rows][:, js]
        cost = np.nanmean(np.linalg.norm(a[:, None] - b[None], axis=-1), -1)
        cost = np.where(np.isfinite(cost), cost, 1e6)
        r, c = linear_sum_assignment(cost)
        for i, k in zip(r, c, strict=True):
            if cost[i, k] < 0.5:
                P.append(a[i])
                G.append(b[k])
    if not P:
        return float("nan"), float("nan"), 0
    P, G = np.array(P), np.array(G)
    ok = np.isfinite(P).all(-1)
    Pt, Gt = torch.as_tensor(np.nan_to_num(P)), torch.as_tensor(G, dtype=torch.float64)
    v = torch.as_tensor(ok)
    return (
        float(mpjpe(Pt, Gt, valid=v).mean() * 1000),
        float(pa_mpjpe(Pt, Gt, valid=v).mean() * 1000),
        len(P),
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workspace", type=Path, default=ROOT / "workspace" / "demo")
    ap.add_argument("--peers-python", default="/work/bench-venv/bin/python")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--keep-input", type=Path, help="also save the exported peer input here")
    args = ap.parse_args()
    torch.set_num_threads(1)

    from calibration.formats import read_rig
    from gst.body import load_body_model
    from gst.body.markers import MarkerModel
    from gst.data.store import CropStore
    from gst.fuse.fit import FitOptions, fit_people
    from gst.fuse.observations import crop_landmarks, group_by_person
    from gst.fuse.triangulate import triangulate_person
    from synth.truth import read_scene_truth

    ws = args.workspace
    store = CropStore(ws / "crops" / "crops.h5")
    rig = read_rig(ws / "calibration" / "rig.json", "rig")
    truth = read_scene_truth(ws / "synth")
    cache = ws / "crops" / "fuse_bench_landmarks.npy"
    if cache.is_file():
        lm = np.load(cache)
    else:
        lm = crop_landmarks(store)
        np.save(cache, lm)
    people = group_by_person(store, lm)
    n_pf = sum(len(p.frames) for p in people)
    results = []

    def row(name, mp, pa, n, sec, note=""):
        results.append((name, mp, pa, n, 1000 * sec / n_pf, note))

    # ours: triangulation
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        tris = [triangulate_person(p) for p in people]
        times.append(time.perf_counter() - t0)
    X = np.concatenate([t.points for t in tris])
    person = np.concatenate([np.full(len(p.frames), p.person_id) for p in people])
    frame = np.concatenate([p.frames for p in people])
    mp, pa, n = _score(_joints13(X), person, frame, truth, JOINTS13)
    row("ours: triangulation", mp, pa, n, float(np.median(times)))

    body = load_body_model("anny")
    markers = MarkerModel.load()
    times = []
    for _ in range(max(1, args.repeats - 1)):
        t0 = time.perf_counter()
        fits = fit_people(body, markers, people, tris, 30.0, FitOptions())
        times.append(time.perf_counter() - t0)
    J = np.concatenate(
        [f.joints[np.isin(f.frames, p.frames)] for f, p in zip(fits, people, strict=True)]
    )
    mp, pa, n = _score(J, person, frame, truth, JOINTS13)
    row(
        "ours: body fit (13 joints)",
        mp,
        pa,
        n,
        float(np.median(times)),
        "fit only, after triangulation",
    )
    mp, pa, n = _score(J, person, frame, truth)
    row("ours: body fit (24 joints)", mp, pa, n, float(np.median(times)))

    # peers, same input, in their own venv
    with tempfile.TemporaryDirectory() as tmp:
        inp, outp, script = Path(tmp) / "in.npz", Path(tmp) / "out.json", Path(tmp) / "peers.py"
        arr = _export(people, store, rig, inp)
        script.write_text(PEER_SCRIPT)
        if args.keep_input:
            import shutil

            shutil.copy(inp, args.keep_input)
        proc = subprocess.run([args.peers_python, str(script), str(inp), str(outp)],
                              capture_output=True, text=True, env={"OMP_NUM_THREADS": "1",
                              "NUMBA_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})  # fmt: skip
        peers = json.loads(outp.read_text()) if outp.is_file() else {}
        if proc.returncode:
            print(proc.stderr[-3000:])
    for key, name in (("pose2sim", "Pose2Sim 0.10.49: triangulation"),
                      ("aniposelib", "aniposelib 0.8.0: triangulate"),
                      ("aniposelib_optim", "aniposelib 0.8.0: optim_points")):  # fmt: skip
        r = peers.get(key, {"error": "not run"})
        if "error" in r:
            results.append((name, float("nan"), float("nan"), 0, float("nan"), r["error"][:80]))
            continue
        Xp = np.array(r["points"], dtype=float)
        mp, pa, n = _score(_joints13(Xp), arr["person"], arr["frame"], truth, JOINTS13)
        row(name, mp, pa, n, r["seconds"])

    print(f"\n{n_pf} person-frames, {len(store.camera_names)} cameras, detected 2D (BlazePose)\n")
    print("| method | MPJPE mm | PA-MPJPE mm | person-frames | ms / person-frame | note |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name, mp, pa, n, ms, note in results:
        print(f"| {name} | {mp:.1f} | {pa:.1f} | {n} | {ms:.2f} | {note} |")

    # linearity of the fit: subsets of frames and cameras, and the people replicated
    print("\n| fit subset | person-frames | cameras | seconds | person-frames / s |")
    print("| --- | --- | --- | --- | --- |")
    C = len(store.camera_names)
    for frames_keep, cams_keep, copies in ((12, C, 1), (24, C, 1), (48, C, 1), (48, C // 2, 1),
                                           (48, C, 4)):  # fmt: skip
        sub, sub_tris = [], []
        for _ in range(copies):
            for p in people:
                keep = np.arange(len(p.frames)) < frames_keep
                q = p.select(keep)
                drop = np.arange(C) >= cams_keep
                q.uv[:, drop] = np.nan
                q.confidence[:, drop] = 0.0
                q.rows[:, drop] = -1
                sub.append(q)
                sub_tris.append(triangulate_person(q))
        t0 = time.perf_counter()
        fit_people(body, markers, sub, sub_tris, 30.0, FitOptions())
        sec = time.perf_counter() - t0
        pf = sum(len(q.frames) for q in sub)
        print(
            f"| {frames_keep} frames x {len(sub)} people | {pf} | {cams_keep} | {sec:.2f} | {pf / sec:.1f} |"
        )


if __name__ == "__main__":
    main()

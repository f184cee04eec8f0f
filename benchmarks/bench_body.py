"""Body model benchmark: forward time next to accuracy, variants compared in one run.

    python benchmarks/bench_body.py                # CPU, batch 32, 1 thread
    python benchmarks/bench_body.py --threads 2 --device cuda --skip-accuracy

Timing: median of --repeats runs after a warm-up, torch.no_grad() unless marked "fwd+bwd".
Rows:
- smplx lbs vs ours on an SMPL-sized synthetic model (6890 vertices, 207 pose blend shapes),
  with the maximum difference between the two;
- ours on the Anny default: the 6890-vertex preset (as GST uses it), with skinning transforms,
  forward+backward, and the full mesh; Anny itself (13718 vertices, 104 bones) for scale.
Accuracy: the Anny default against Anny's own posed bone heads and mesh, over random shapes
from Anny's distribution and random poses within the joint limits (gst.body.joint_limits).
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.cli import bench_parser  # noqa: E402
from gst.body import BodyModel  # noqa: E402
from gst.body.anny_default import AnnyReference, build_anny_default  # noqa: E402
from gst.body.joint_limits import sample_body_pose  # noqa: E402
from gst.body.random_model import random_body_data  # noqa: E402
from gst.body.rotations import axis_angle_to_matrix  # noqa: E402
from gst.body.skeleton import SMPL_JOINT_NAMES  # noqa: E402
from gst.body.subsets import vertex_subset  # noqa: E402


def timed(fn, repeats: int, device: torch.device) -> float:
    """Median wall time in ms."""

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize()

    for _ in range(2):
        fn()
    sync()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def inputs(batch: int, nb: int, device, dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    betas = torch.randn(batch, nb, generator=g)
    pose = sample_body_pose(batch, generator=g)
    orient = axis_angle_to_matrix(0.5 * torch.randn(batch, 3, generator=g))
    transl = torch.randn(batch, 3, generator=g)
    return [x.to(device=device, dtype=dtype) for x in (betas, pose, orient, transl)]


def bench_speed(args, device) -> None:
    from smplx.lbs import lbs as smplx_lbs

    B = args.batch
    print(
        f"\n== forward time, batch {B}, {device}, float32, torch threads {torch.get_num_threads()} "
        "=="
    )
    print(f"{'variant':58s} {'vertices':>8s} {'ms':>8s} {'ratio':>7s}  error")
    smpl_like = random_body_data(num_vertices=6890, seed=0)
    body = BodyModel(smpl_like, device=device)
    betas, pose, orient, transl = inputs(B, 10, device)
    parents = torch.as_tensor(smpl_like.parents, device=device)
    full_rot = torch.cat([orient[:, None], pose], dim=1)

    def ref():
        return smplx_lbs(
            betas,
            full_rot,
            body.v_template,
            body.shapedirs,
            body.posedirs,
            body.J_regressor,
            parents,
            body.weights,
            pose2rot=False,
        )

    with torch.no_grad():
        t_ref = timed(ref, args.repeats, device)
        t_ours = timed(lambda: body(betas, pose, orient), args.repeats, device)
        ref_v, ref_j = ref()
        out = body(betas, pose, orient)
        err = max(
            float((out.vertices - ref_v).abs().max()), float((out.joints - ref_j).abs().max())
        )
    print(
        f"{'smplx.lbs (rotation matrices), SMPL-sized synthetic model':58s} {6890:8d} {t_ref:8.1f} "
        f"{1.0:7.2f}"
    )
    print(
        f"{'ours, same arrays':58s} {6890:8d} {t_ours:8.1f} {t_ours / t_ref:7.2f}  "
        f"max |ours - smplx| = {err:.1e} m"
    )

    if args.skip_anny:
        return
    data = build_anny_default()
    body = BodyModel(data, device=device)
    ids = torch.as_tensor(vertex_subset(data, "6890"), device=device)
    betas, pose, orient, transl = inputs(B, 10, device)
    rows = []
    with torch.no_grad():
        rows.append(
            (
                "ours, Anny default, 6890 preset",
                len(ids),
                timed(
                    lambda: body(betas, pose, orient, transl, vertex_ids=ids), args.repeats, device
                ),
            )
        )
        rows.append(
            (
                "ours, Anny default, 6890 preset, + skinning transforms",
                len(ids),
                timed(
                    lambda: body(
                        betas, pose, orient, transl, vertex_ids=ids, return_transforms=True
                    ),
                    args.repeats,
                    device,
                ),
            )
        )
        rows.append(
            (
                "ours, Anny default, full mesh",
                data.num_vertices,
                timed(lambda: body(betas, pose, orient, transl), args.repeats, device),
            )
        )

    params = [x.clone().requires_grad_(True) for x in (betas, pose, orient, transl)]

    def train_step():
        out = body(*params, vertex_ids=ids, return_transforms=True)
        (out.vertices.sum() + out.vertex_transforms.sum() + out.joints.sum()).backward()

    rows.append(
        (
            "ours, Anny default, 6890 preset, transforms, fwd+bwd",
            len(ids),
            timed(train_step, args.repeats, device),
        )
    )
    if device.type == "cpu":
        ref_anny = AnnyReference()
        ref_anny.model.to(torch.float32)
        phen = torch.rand(B, 6)
        deltas = torch.eye(4).repeat(B, len(ref_anny.bone_labels), 1, 1)
        with torch.no_grad():
            rows.append(
                (
                    "Anny itself (float32, 104 bones)",
                    ref_anny.model.template_vertices.shape[0],
                    timed(
                        lambda: ref_anny.model(pose_parameters=deltas, phenotype_kwargs=phen),
                        args.repeats,
                        device,
                    ),
                )
            )
    base = rows[0][2]
    for name, nv, ms in rows:
        print(f"{name:58s} {nv:8d} {ms:8.1f} {ms / base:7.2f}")


def bench_accuracy(args) -> None:
    n = args.samples
    data = build_anny_default()
    body = BodyModel(data, dtype=torch.float64)
    ref = AnnyReference()
    ids = torch.as_tensor(data.source_vertex_ids)
    phen = ref.sample_phenotypes(n, (12.0, 80.0), seed=2024)
    rest_v, rest_heads = ref.rest(phen)
    dirs = body.shapedirs.reshape(-1, body.num_betas)
    betas_all = torch.linalg.lstsq(
        dirs, (rest_v[:, ids] - body.v_template).reshape(n, -1).T
    ).solution.T
    print(
        f"\n== Anny default vs Anny: {n} shapes (ages 12-80), random poses within joint limits, "
        "float64 =="
    )
    print(
        f"shape space: {data.num_betas} betas; explained variance, first 10: "
        f"{100 * data.shape_variance_ratio[:10].sum():.3f}%, all {data.num_betas}: "
        f"{100 * data.shape_variance_ratio.sum():.4f}%"
    )
    print(
        f"{'betas':>5s} {'hands/feet':>10s} | {'joint mm: mean':>14s} {'median':>7s} {'p95':>7s} "
        f"{'max':>7s} | {'vertex mm: median':>17s} {'p95':>7s} {'max':>7s} | "
        f"{'rest joints mean/max':>20s}"
    )
    fixed = [
        SMPL_JOINT_NAMES.index(n) - 1
        for n in ("left_hand", "right_hand", "left_foot", "right_foot")
    ]
    for nb in (10, data.num_betas):
        betas = betas_all[:, :nb]
        rest_err = 1e3 * (body.rest_joints(betas) - rest_heads).norm(dim=-1)
        for posed_ends in (True, False):
            g = torch.Generator().manual_seed(7)
            pose = sample_body_pose(n, generator=g, dtype=torch.float64)
            if not posed_ends:
                pose[:, fixed] = torch.eye(3, dtype=torch.float64)
            orient = axis_angle_to_matrix(0.7 * torch.randn(n, 3, generator=g, dtype=torch.float64))
            anny_v, anny_heads = ref.posed(phen, torch.cat([orient[:, None], pose], dim=1))
            out = body(betas, pose, orient, transl=-body.rest_joints(betas)[:, 0])
            je = 1e3 * (out.joints - anny_heads).norm(dim=-1)
            ve = 1e3 * (out.vertices - anny_v[:, ids]).norm(dim=-1)
            print(
                f"{nb:5d} {'posed' if posed_ends else 'at rest':>10s} | {je.mean():14.2f} "
                f"{je.median():7.2f} {je.quantile(0.95):7.2f} {je.max():7.2f} | "
                f"{ve.median():17.2f} {ve.flatten().quantile(0.95):7.2f} {ve.max():7.2f} | "
                f"{rest_err.mean():9.2f} / {rest_err.max():.2f}"
            )
    # float32 against float64 on the same inputs
    b32 = BodyModel(data, dtype=torch.float32)
    betas, pose, orient, transl = inputs(32, data.num_betas, "cpu", dtype=torch.float64)
    d = (
        (
            b32(betas, pose, orient, transl).vertices.double()
            - body(betas, pose, orient, transl).vertices
        )
        .abs()
        .max()
    )
    print(f"float32 vs float64 forward: max vertex difference {1e3 * float(d):.4f} mm")


def main() -> None:
    parser = bench_parser(__doc__)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument(
        "--threads", type=int, default=1, help="torch CPU threads (0: leave torch's default)"
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--samples", type=int, default=100, help="shapes and poses for the accuracy check"
    )
    parser.add_argument(
        "--skip-anny", action="store_true", help="only the synthetic SMPL-sized timing"
    )
    parser.add_argument("--skip-accuracy", action="store_true")
    args = parser.parse_args()
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    np.set_printoptions(precision=3)
    device = torch.device(args.device)
    bench_speed(args, device)
    if not args.skip_accuracy and not args.skip_anny:
        bench_accuracy(args)


if __name__ == "__main__":
    main()

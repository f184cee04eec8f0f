"""Rendering speed of the synthetic capture, per camera, at 512x512 and 1920x1080.

    python benchmarks/bench_synth_render.py [--frames 8] [--people 2]

One dome camera (60 degree lens, mild distortion) looks at people running and jumping. For each
image size it compares, in one run, on the same frames:

  ours        Embree via embreex, rays only inside the people's box, 2x2 samples on silhouettes
  no-aa       as ours, one sample per pixel
  trimesh     as no-aa, through trimesh's ray interface (trimesh.ray.ray_pyembree, Embree too)
  full-frame  as no-aa, a primary ray for every pixel (the brute-force reference)

and prints median CPU milliseconds per frame (process time, all threads; steadier than wall
time on a shared machine, whose wall median for `frame` is printed too): `shared` (building the
Embree scene and the floor
shadow maps, done once per frame for all cameras), `render` (one camera's view) and `frame`
(render + camera response + mp4 encode + mask write), then frames/s per camera in a many-camera
scene (1 / frame) and for a lone camera (1 / (shared + frame)), the ratio to `ours`, and errors:
mask pixels differing from the brute-force reference, the share of in-image ground-truth joints
on their own mask, and the mean 8-bit image difference to `ours`.
The body model is gst.body's open default when it is installed, else the capsule stand-in of
tests/synth_fixtures.py (printed in the header).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.cli import add_scene_size, bench_parser  # noqa: E402
from synth.animate import pose_person  # noqa: E402
from synth.appearance import BodyAtlas  # noqa: E402
from synth.imaging import CameraResponse, develop  # noqa: E402
from synth.io import MaskStore, VideoOut  # noqa: E402
from synth.people import sample_people  # noqa: E402
from synth.projection import field_radius, project_in_view  # noqa: E402
from synth.render import (  # noqa: E402
    PosedPerson,
    RayCaster,
    RenderOptions,
    ViewRenderer,
    floor_shadow_maps,
    vertex_normals,
)
from synth.rigs import make_rig  # noqa: E402
from synth.stage import stage_for_rig  # noqa: E402

VARIANTS = {
    "ours": RenderOptions(antialias=2),
    "no-aa": RenderOptions(antialias=1),
    "trimesh": RenderOptions(antialias=1, backend="trimesh"),
    "full-frame": RenderOptions(antialias=1, roi=False),
}


def load_body():
    try:
        from gst.body import load_body_model

        return load_body_model("anny"), "gst.body anny"
    except ImportError:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
        from synth_fixtures import CapsuleBody

        return CapsuleBody(), "capsule stand-in (gst.body not installed)"


def main() -> None:
    ap = bench_parser(__doc__)
    add_scene_size(ap, frames=8, people=2)
    args = ap.parse_args()
    model, body_name = load_body()
    faces = np.asarray(model.faces, np.int32)
    fps, n = 30.0, args.frames
    rig0 = make_rig("dome", n_cameras=1, seed=0)
    people = sample_people(
        args.people,
        np.random.default_rng(0),
        int(model.num_betas),
        rig0.meta["volume_center"],
        rig0.meta["volume_radius"],
        n,
        fps,
        programmes=[["run"], ["jump"]][: args.people] if args.people <= 2 else None,
    )
    tracks = [pose_person(model, p.betas, p.motion_clip(n, fps, 0), p.person_id) for p in people]
    atlases = [
        BodyAtlas.build(
            t.rest_vertices,
            t.rest_joints,
            getattr(model, "part_labels", None),
            getattr(model, "part_names", None),
        )
        for t in tracks
    ]
    normals = [vertex_normals(t.vertices, faces) for t in tracks]
    stage = stage_for_rig("dome", 0)
    print(
        f"body: {body_name}, {tracks[0].vertices.shape[1]} vertices, {len(faces)} triangles; "
        f"{args.people} people, {n} frames per variant; medians"
    )
    for width, height in ((512, 512), (1920, 1080)):
        cam = make_rig(
            "dome", n_cameras=1, width=width, height=height, fov_deg=60.0, distortion="mild", seed=4
        ).cameras[0]
        radius = field_radius(cam)
        print(f"\n{width}x{height}  camera '{cam.name}'")
        print(
            f"{'variant':<11} {'setup s':>8} {'shared ms':>10} {'render ms':>10} {'frame ms':>9} "
            f"{'wall ms':>8} {'fps/cam':>8} {'fps lone':>9} {'ratio':>6} {'mask px vs ref':>15} "
            f"{'joints on mask':>15} {'img diff':>9}"
        )
        # Variants run interleaved frame by frame, so machine load hits them alike.
        results, renderers, sinks = {}, {}, {}
        tmp = tempfile.TemporaryDirectory()
        for name, opts in VARIANTS.items():
            t0 = time.perf_counter()
            renderers[name] = ViewRenderer(cam, stage, opts)
            results[name] = dict(
                setup=time.perf_counter() - t0,
                shared=[],
                render=[],
                frame=[],
                wall=[],
                masks=[],
                images=[],
                on=0,
                total=0,
            )
            sinks[name] = (
                VideoOut(Path(tmp.name) / f"{name}.mp4", fps, width, height),
                MaskStore(Path(tmp.name) / f"{name}.h5", n, width, height, cam.name, True),
            )
        for f in range(n):
            posed = [
                PosedPerson(
                    t.person_id, t.vertices[f], normals[k][f], faces, atlases[k], people[k].outfit
                )
                for k, t in enumerate(tracks)
            ]
            for name, opts in VARIANTS.items():
                r, (video, store) = results[name], sinks[name]
                cs = time.process_time()
                caster = RayCaster([(p.vertices, p.faces) for p in posed], opts.backend)
                caster.occluded(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))  # build the BVH now
                shadows = floor_shadow_maps(posed, caster, stage, opts.shadow_samples)
                t0, c0 = time.perf_counter(), time.process_time()
                layers = renderers[name].render_people(posed, caster, shadows)
                c1 = time.process_time()
                image = develop(
                    layers.radiance,
                    CameraResponse(blur_sigma=0.5, noise_sigma=1.5),
                    np.random.default_rng(f),
                )
                video.write(image)
                store.write(f, layers.mask, layers.depth)
                t2, c2 = time.perf_counter(), time.process_time()
                r["shared"].append(c0 - cs)
                r["render"].append(c1 - c0)
                r["frame"].append(c2 - c0)
                r["wall"].append(t2 - t0)
                r["masks"].append(layers.mask)
                r["images"].append(image)
                for t in tracks:
                    uv, inside = project_in_view(cam, t.joints[f], radius)
                    px = np.rint(uv[inside]).astype(int)
                    r["total"] += int(inside.sum())
                    r["on"] += int((layers.mask[px[:, 1], px[:, 0]] == t.person_id).sum())
        for name, r in results.items():
            for sink in sinks[name]:
                sink.close()
            for key in ("shared", "render", "frame", "wall"):
                r[key] = float(np.median(r[key]))
            r["joints"] = r["on"] / max(r["total"], 1)
        tmp.cleanup()
        ref, base = results["full-frame"], results["ours"]
        for name, r in results.items():
            diff_px = int(
                np.mean([(a != b).sum() for a, b in zip(r["masks"], ref["masks"], strict=True)])
            )
            img_diff = np.mean(
                [
                    np.abs(a.astype(int) - b.astype(int)).mean()
                    for a, b in zip(r["images"], base["images"], strict=True)
                ]
            )
            print(
                f"{name:<11} {r['setup']:>8.2f} {1000 * r['shared']:>10.1f} "
                f"{1000 * r['render']:>10.1f} {1000 * r['frame']:>9.1f} {1000 * r['wall']:>8.1f} "
                f"{1 / r['frame']:>8.2f} {1 / (r['shared'] + r['frame']):>9.2f} "
                f"{r['frame'] / base['frame']:>6.2f} {diff_px:>15d} {100 * r['joints']:>14.1f}% "
                f"{img_diff:>9.3f}"
            )


if __name__ == "__main__":
    main()

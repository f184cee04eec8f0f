"""Crops cut again from the fitted bodies (gst.fuse.body_labels, gst.fuse.body_crops).

The end-to-end test renders two known bodies with a brute-force painter's rasteriser written
here (every triangle filled with OpenCV, far to near), writes those frames as videos, and checks
the new crops against the rendered silhouettes: every visible person has a crop in every view,
with the right id and a mask that matches them."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch
import trimesh
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from calibration.camera import Camera, Rig
from gst.body import load_body_model
from gst.data.extract.crops import crop_person, landmarks_to_crop
from gst.data.store import CropBatch, CropStore, CropStoreWriter
from gst.fuse.body_crops import BodyCropReport, lenders, move_landmarks, recut_crops
from gst.fuse.body_labels import CameraRays, body_labels
from gst.fuse.fit import PersonFit
from gst.fuse.rounds import fuse_rounds
from gst.fuse.scene import FuseOptions
from gst.fuse.tables import joint_evidence, write_bodies
from gst.video import read_frames
from synth.render import RayCaster
from tests.fuse_fixtures import make_capture, write_store

BACKGROUND = (120, 120, 120)
COLOURS = [(40, 40, 210), (210, 80, 40)]


def _camera(dist=(), size=(320, 240)) -> Camera:
    K = np.array([[300.0, 0, size[0] / 2], [0, 300.0, size[1] / 2], [0, 0, 1]])
    return Camera.create("c", K, list(dist), np.eye(3), np.zeros(3), *size)


@settings(max_examples=25, deadline=None)
@given(
    k1=st.floats(-0.3, 0.3),
    k2=st.floats(-0.1, 0.1),
    u=st.floats(5, 315),
    v=st.floats(5, 235),
    depth=st.floats(0.5, 10.0),
)
def test_rays_project_back_onto_their_pixel_through_the_lens(k1, k2, u, v, depth):
    cam = _camera((k1, k2, 0, 0, 0))
    i, j = int(round(v)), int(round(u))
    # a strong barrel lens images no ray beyond the largest distorted radius it reaches (its
    # fold-over): such a pixel has no ray to come back from (k1 -0.28, k2 -0.094 reach 0.640,
    # the corner pixel lies at 0.643), so the draw must be a pixel the lens can image
    r = np.linspace(0.0, 3.0, 30001)
    rd = r * (1 + k1 * r**2 + k2 * r**4)
    reach = rd[: np.argmax(np.diff(rd) <= 0) or None].max()
    assume(np.hypot(j - cam.cx, i - cam.cy) / cam.fx < 0.99 * reach)
    rays = CameraRays(cam, (cam.width, cam.height))
    # the ray of the pixel nearest (u, v), walked to `depth` along the optical axis
    d = rays.dirs[i, j].astype(np.float64)
    point = rays.origin + d * depth / d[2]
    assert np.allclose(cam.project(point[None])[0], (j, i), atol=1e-3)


def test_rays_at_half_size_meet_the_full_size_pixel_centres():
    cam = _camera((0.1, -0.05, 0, 0, 0))
    rays = CameraRays(cam, (160, 120))
    d = rays.dirs[10, 20].astype(np.float64)
    # working pixel (20, 10) covers full pixels 40..41 x 20..21: its centre is (40.5, 20.5)
    assert np.allclose(cam.project((d / d[2])[None])[0], (40.5, 20.5), atol=1e-3)


def _box(centre, size) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.box(extents=size)
    return np.asarray(m.vertices + centre, np.float32), np.asarray(m.faces, np.int32)


def test_labels_follow_the_front_body_and_the_foreground():
    cam = _camera()
    (near, faces), (far, _) = _box([0.0, 0, 3], [0.4, 1, 0.2]), _box([0.2, 0, 5], [0.6, 1, 0.2])
    meshes = [far, near]  # index 0 is the far box
    caster = RayCaster([(m, faces) for m in meshes])
    rays = CameraRays(cam, (cam.width, cam.height))
    fg = np.ones((cam.height, cam.width), bool)
    lab = body_labels(rays, meshes, caster, fg, max_distance_px=3)
    cy = 120
    # near box: x in [-0.2, 0.2] at z 2.9 -> u 160 +- 20.7; far box x in [-0.1, 0.5] at z 4.9
    assert lab[cy, 160] == 1  # both cover it: the near one is in front
    assert lab[cy, 190] == 0  # only the far box (u up to 160 + 300 * 0.5 / 4.9 = 190.6)
    assert lab[cy, 192] == 0  # 1.4 px beyond it: foreground within 3 px
    assert lab[cy, 196] == -1  # 5 px beyond: nobody's
    assert lab[5, 5] == -1
    fg[cy, 160] = False
    assert body_labels(rays, meshes, caster, fg, 3)[cy, 160] == -1  # not foreground: nobody's
    with pytest.raises(ValueError, match="meshes"):
        body_labels(rays, meshes[:1], caster, fg)


def _labels_casting_every_pixel(rays, caster, fg, max_distance_px) -> np.ndarray:
    """The definition, brute force: every pixel cast, nearest owned pixel by scanning."""
    owner = caster.cast(rays.origin[None], rays.dirs.reshape(-1, 3)).geom.reshape(fg.shape)
    oy, ox = np.nonzero(owner >= 0)
    out = np.full(fg.shape, -1, np.int16)
    for y, x in zip(*np.nonzero(fg), strict=True):
        d2 = (oy - y) ** 2 + (ox - x) ** 2
        if len(d2) and d2.min() <= max_distance_px**2:
            out[y, x] = owner[oy[d2.argmin()], ox[d2.argmin()]]
    return out


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    max_distance=st.floats(0.5, 6.0),
    x=st.floats(-0.6, 0.6),
)
def test_labels_equal_casting_every_pixel(seed, max_distance, x):
    # only pixels near the foreground are cast (body_labels); a random foreground of blobs and
    # noise, two bodies side by side: the labels must be those of casting them all. Where two
    # bodies' owned pixels lie at exactly the nearest distance either answer is right, and the
    # two nearest-pixel searches break such ties differently: there the label must be one of the
    # tied bodies (how many ties a draw holds depends on its geometry, so they are not counted)
    cam = _camera(size=(96, 72))
    cam = Camera.create("c", cam.K / np.array([[3.3], [3.3], [1]]), [], np.eye(3), np.zeros(3),
                        96, 72)  # fmt: skip
    (a, faces), (b, _) = _box([x, 0, 3], [0.5, 1, 0.2]), _box([x + 0.35, 0.1, 4], [0.5, 1, 0.2])
    caster = RayCaster([(a, faces), (b, faces)])
    rays = CameraRays(cam, (96, 72))
    rng = np.random.default_rng(seed)
    fg = rng.random((72, 96)) < 0.05
    for _ in range(3):
        cv2.circle(fg.view(np.uint8), (int(rng.integers(0, 96)), int(rng.integers(0, 72))),
                   int(rng.integers(2, 15)), 1, -1)  # fmt: skip
    got = body_labels(rays, [a, b], caster, fg, max_distance)
    want = _labels_casting_every_pixel(rays, caster, fg, max_distance)
    owner = caster.cast(rays.origin[None], rays.dirs.reshape(-1, 3)).geom.reshape(fg.shape)
    oy, ox = np.nonzero(owner >= 0)
    for y, x_ in zip(*np.nonzero(got != want), strict=True):
        d2 = (oy - y) ** 2 + (ox - x_) ** 2
        nearest = set(owner[oy, ox][d2 == d2.min()].tolist())
        assert len(nearest) > 1 and got[y, x_] in nearest, (y, x_, got[y, x_], want[y, x_])


def test_landmarks_move_between_crops_of_one_view():
    K_from = np.array([[2.0, 0.1, 30], [0, 2.1, 40], [0, 0, 1]])
    K_to = np.array([[0.5, 0.0, -3], [0, 0.5, 7], [0, 0, 1]])
    xy = np.random.default_rng(0).uniform(-1, 1, (33, 2))
    lm = np.c_[(np.c_[xy, np.ones(33)] @ K_from.T)[:, :2], np.full(33, 0.8)]
    lm[5, 2] = 0  # no reading: stays without one
    out = move_landmarks(lm, K_from, K_to)
    want = (np.c_[xy, np.ones(33)] @ K_to.T)[:, :2]
    ok = np.arange(33) != 5
    assert np.allclose(out[ok, :2], want[ok]) and np.allclose(out[ok, 2], 0.8)
    assert out[5, 2] == 0


def test_lenders_pair_masks_one_to_one_above_the_overlap():
    a = np.zeros((10, 10), bool)
    b = np.zeros((10, 10), bool)
    a[:5] = True
    b[5:] = True
    small = np.zeros((10, 10), bool)
    small[0, 0] = True
    assert {i: j for i, (j, _) in lenders([a, b], [b, a], 0.3).items()} == {0: 1, 1: 0}
    assert all(iou == 1.0 for _, iou in lenders([a, b], [b, a], 0.3).values())
    assert lenders([a], [small], 0.3) == {}  # overlap 0.02
    assert lenders([], [a], 0.3) == {} and lenders([a], [], 0.3) == {}


def _render(cam: Camera, meshes: list[np.ndarray], faces: np.ndarray) -> np.ndarray:
    """(H, W) labels 0 (nobody), k + 1 for meshes[k]: every triangle filled far to near."""
    tris, depth, who = [], [], []
    for k, v in enumerate(meshes):
        z = cam.to_camera(v)[:, 2]
        uv = cam.project(v)
        tris.append(uv[faces])
        depth.append(z[faces].mean(1))
        who.append(np.full(len(faces), k + 1))
    tris, depth, who = np.concatenate(tris), np.concatenate(depth), np.concatenate(who)
    out = np.zeros((cam.height, cam.width), np.uint8)
    for i in np.argsort(-depth):
        pts = np.round(tris[i] * 16).astype(np.int32)  # 4 fractional bits
        cv2.fillPoly(out, [pts], int(who[i]), lineType=cv2.LINE_8, shift=4)
    return out


def _write_video(path, frames) -> None:
    h, w = frames[0].shape[:2]
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (w, h))
    for f in frames:
        out.write(f)
    out.release()


def _truth_fit(cap, k: int) -> PersonFit:
    """Person k's true body as the fuse stage's fit of it."""
    T = cap.transl.shape[1]
    return PersonFit(
        person_id=k + 1, frames=np.arange(T), betas=cap.betas[k],
        global_orient=cap.global_orient[k], body_pose=cap.body_pose[k], transl=cap.transl[k],
        joints=cap.joints[k], markers=cap.markers[k],
        reprojection=np.full((T, len(cap.rig), 33), np.nan), observed=np.ones(T, bool),
        static=np.zeros(T, bool), single_view=False, sigma_px=1.0,
    )  # fmt: skip


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bodycrops")
    body = load_body_model("anny")
    faces = np.asarray(body.faces, np.int32)
    cap = make_capture(body, n_people=2, n_frames=2, n_cams=3, seed=1)
    T = cap.transl.shape[1]
    with_verts = []
    for k in range(2):
        out = body(
            torch.as_tensor(np.repeat(cap.betas[k : k + 1], T, 0), dtype=body.dtype),
            torch.as_tensor(cap.body_pose[k], dtype=body.dtype),
            torch.as_tensor(cap.global_orient[k], dtype=body.dtype),
            torch.as_tensor(cap.transl[k], dtype=body.dtype),
        )
        with_verts.append(out.vertices.detach().numpy())
    truth, videos, plates = {}, {}, {}
    for cam in cap.rig:
        frames = []
        for f in range(T):
            lab = _render(cam, [with_verts[0][f], with_verts[1][f]], faces)
            truth[cam.name, f] = lab
            img = np.zeros((cam.height, cam.width, 3), np.uint8)
            img[:] = BACKGROUND
            for k, colour in enumerate(COLOURS):
                img[lab == k + 1] = colour
            frames.append(img)
        videos[cam.name] = tmp / f"{cam.name}.avi"
        plates[cam.name] = tmp / f"{cam.name}_empty.avi"
        _write_video(videos[cam.name], frames)
        _write_video(plates[cam.name], [np.full_like(frames[0], BACKGROUND)] * 5)
    write_store(tmp / "crops.h5", cap)
    fits = [_truth_fit(cap, k) for k in range(2)]
    write_bodies(
        tmp / "bodies.parquet", fits, [joint_evidence(f, None) for f in fits], fps=30.0,
        camera_names=cap.rig.names, model={"body_model": "anny"}, settings={},
        settings_sha256="0" * 64, stats={},
    )  # fmt: skip
    return tmp, cap, truth, videos, plates


def _check_crops(store: CropStore, cap, truth) -> None:
    """Every crop's mask matches its person's rendered silhouette; every visible person has one."""
    batch = store.read(np.arange(len(store)))
    seen = set()
    for i in range(len(store)):
        cam = cap.rig[store.camera_names[batch.camera[i]]]
        f, pid = int(batch.frame[i]), int(batch.person_id[i])
        seen.add((cam.name, f, pid))
        # the rendered silhouette, sampled into the crop through its K_crop (no lens here)
        S = store.crop_size
        jj, ii = np.meshgrid(np.arange(S), np.arange(S))
        xy = np.linalg.solve(batch.K_crop[i], np.stack([jj, ii, np.ones_like(jj)]).reshape(3, -1))
        uv = (cam.K @ (xy / xy[2])).T[:, :2].reshape(S, S, 2).astype(np.float32)
        lab = cv2.remap(truth[cam.name, f], uv[..., 0], uv[..., 1], cv2.INTER_NEAREST)
        want, got = lab == pid, batch.masks[i] >= 128
        iou = np.count_nonzero(want & got) / np.count_nonzero(want | got)
        assert iou > 0.85, (cam.name, f, pid, iou)
    for (name, f), lab in truth.items():
        for pid in (1, 2):
            if np.count_nonzero(lab == pid) >= 200:
                assert (name, f, pid) in seen, (name, f, pid)


def test_every_visible_person_gets_their_own_crop_with_their_silhouette(scene):
    tmp, cap, truth, videos, plates = scene
    report = recut_crops(
        tmp / "crops.h5", cap.rig, videos, tmp / "bodies.parquet", tmp / "out" / "crops.h5",
        plates=plates,
    )  # fmt: skip
    store = CropStore(tmp / "out" / "crops.h5")
    assert report.crops == len(store) > 0
    assert store.attrs["setting.association"] == "bodies"
    _check_crops(store, cap, truth)


def test_clean_plates_that_announce_a_frame_more_than_they_hold_cut_the_same_crops(scene):
    """The extraction reads such files to the frames they hold; the recut sampled the announced
    count and failed on the missing last frame as "truncated or corrupt"."""
    from tests.test_track_bad_video import _announcing_one_more

    tmp, cap, truth, videos, plates = scene
    over = {}
    for name, path in plates.items():
        over[name] = tmp / "over" / f"{name}.avi"
        over[name].parent.mkdir(exist_ok=True)
        _announcing_one_more(path, over[name])
    plain, out = tmp / "plain_plates" / "crops.h5", tmp / "over_plates" / "crops.h5"
    recut_crops(tmp / "crops.h5", cap.rig, videos, tmp / "bodies.parquet", plain, plates=plates)
    recut_crops(tmp / "crops.h5", cap.rig, videos, tmp / "bodies.parquet", out, plates=over)
    a, b = CropStore(plain), CropStore(out)
    assert len(a) == len(b) > 0
    rows = np.arange(len(a))
    assert np.array_equal(a.read_masks(rows), b.read_masks(rows))


def test_a_calibration_with_encoder_padding_cuts_the_same_crops(scene):
    """The calibration says 16 rows more than the videos decode to (as 1088 for 1080): the
    cameras are fitted to the frames as the extraction fits them, so the crops are the ones the
    true frame size gives."""
    tmp, cap, truth, videos, plates = scene
    padded = Rig([c.replace(height=c.height + 16) for c in cap.rig])
    plain, out = tmp / "plain" / "crops.h5", tmp / "padded" / "crops.h5"
    recut_crops(tmp / "crops.h5", cap.rig, videos, tmp / "bodies.parquet", plain, plates=plates)
    recut_crops(tmp / "crops.h5", padded, videos, tmp / "bodies.parquet", out, plates=plates)
    a, b = CropStore(plain), CropStore(out)
    assert len(a) == len(b) > 0
    rows = np.arange(len(a))
    assert np.array_equal(a.read_masks(rows), b.read_masks(rows))
    assert np.allclose(a.read_column("K_crop", rows), b.read_column("K_crop", rows))


def test_nobody_fitted_gives_an_empty_complete_store(scene):
    tmp, cap, _, videos, plates = scene
    write_bodies(
        tmp / "nobody.parquet", [], [], fps=30.0, camera_names=cap.rig.names,
        model={"body_model": "anny"}, settings={}, settings_sha256="0" * 64, stats={},
    )  # fmt: skip
    out = tmp / "empty" / "crops.h5"
    report = recut_crops(tmp / "crops.h5", cap.rig, videos, tmp / "nobody.parquet", out)
    assert report.crops == 0 and len(CropStore(out)) == 0


def test_a_camera_without_video_is_named(scene):
    tmp, cap, _, videos, plates = scene
    some = dict(list(videos.items())[1:])
    with pytest.raises(ValueError, match=list(videos)[0]):
        recut_crops(tmp / "crops.h5", cap.rig, some, tmp / "bodies.parquet", tmp / "x.h5")


def test_bodies_are_projected_with_the_fitted_cameras_and_crops_keep_the_calibration(scene):
    """A calibration 1 degree off (what the fit corrects, `FuseResult.rig`): the bodies are
    projected with the fitted cameras, so the masks match, and the crops keep the calibration's
    R, t as the extraction's do (every fusion corrects the rig from the calibration)."""
    tmp, cap, truth, videos, plates = scene
    turn = cv2.Rodrigues(np.array([0.0, np.deg2rad(1.0), 0.0]))[0]
    calibrated = Rig([c.replace(R=turn @ c.R, t=turn @ c.t) for c in cap.rig])
    out = tmp / "fitted" / "crops.h5"
    recut_crops(tmp / "crops.h5", calibrated, videos, tmp / "bodies.parquet", out,
                plates=plates, fitted_rig=cap.rig)  # fmt: skip
    store = CropStore(out)
    _check_crops(store, cap, truth)
    batch = store.read(np.arange(len(store)))
    for i in range(len(store)):
        cam = calibrated[store.camera_names[batch.camera[i]]]
        assert np.allclose(batch.R[i], cam.R) and np.allclose(batch.t[i], cam.t)


@pytest.fixture(scope="module")
def extracted(scene):
    """The scene's crops as the extraction would cut them: each person's rendered silhouette
    (crop_person, the extraction's conventions) with their projected landmarks."""
    tmp, cap, truth, videos, plates = scene
    parts = []
    for c, cam in enumerate(cap.rig):
        for f, image in read_frames(videos[cam.name], range(cap.transl.shape[1])):
            for k in range(2):
                got = crop_person(image, truth[cam.name, f] == k + 1, cam, 64, 1.2)
                if got is None:
                    continue
                img, msk, Kc, box, cbox = got
                uv = cam.project(cap.markers[k, f])
                lm = landmarks_to_crop(cam, np.c_[uv, np.full(len(uv), 0.9)], Kc)
                parts.append(CropBatch(
                    img[None], msk[None], Kc[None], cam.R[None], cam.t[None], box[None],
                    cbox[None], np.array([c], np.int32), np.array([f], np.int64),
                    np.array([k + 1], np.int64), np.array([np.nan], np.float32),
                    landmarks=lm[None],
                ))  # fmt: skip
    path = tmp / "extracted.h5"
    with CropStoreWriter(path, cap.rig.names, 64, {"scale": 1.2}, landmarks=True) as w:
        T = cap.transl.shape[1]
        w.commit(CropBatch.concat(parts), [(f, c) for f in range(T) for c in range(len(cap.rig))])
        w.finalize({"n_frames": T})
    return path


@pytest.mark.parametrize("skip_agreement, fusions", [(0.0, 1), (None, 2), (1.01, 2)])
def test_rounds_stop_where_the_cut_agrees_with_the_extraction(
    scene, extracted, tmp_path, skip_agreement, fusions
):
    """A cut that agrees with the extraction at least `skip_agreement` ends the rounds: its
    fusion's outputs (with the overlays an intermediate fusion does not draw) and its crops are
    the stage's; otherwise the second fusion runs. Either way nothing is left in the work
    folder, and the crops are those of the final bodies."""
    tmp, cap, truth, videos, plates = scene
    out, rep = tmp_path / "fused", tmp_path / "reports" / "fuse"
    crops, crops_rep = tmp_path / "bodycrops" / "crops.h5", tmp_path / "reports" / "bodycrops"
    result = fuse_rounds(
        extracted, cap.rig, out, rep, crops, crops_rep, rounds=1,
        skip_agreement=skip_agreement, fps=30.0,
        options=dataclasses.replace(FuseOptions(), relook=None), videos=videos, plates=plates,
    )  # fmt: skip
    assert result.fusions == fusions
    assert result.fused.bodies == out / "bodies.parquet" and result.fused.bodies.is_file()
    assert all(p.is_file() and p.parent.parent == out for p in result.fused.trc)
    assert sorted(p.name for p in result.fused.overlays) == [f"{n}.mp4" for n in cap.rig.names]
    assert all(p.is_file() and p.parent == rep / "overlay" for p in result.fused.overlays)
    assert (rep / "report.md").is_file() and (crops_rep / "summary.json").is_file()
    assert not (tmp_path / ".fused.rounds").exists()
    assert result.crops.agreement() > 0.9  # every crop paired with the extraction's
    _check_crops(CropStore(crops), cap, truth)


def test_a_body_whose_fit_failed_in_a_frame_gets_no_crop_there(scene, tmp_path):
    """A fit that diverged leaves NaN parameters in a row of the bodies file: the body model
    refused the whole frame's batch ("transl contains NaN or Inf (batch items [0])", naming no
    person, frame or file) and the cut stopped. The row is a person not fitted in that frame:
    no crop there, the other person's crops and the person's other frames as before."""
    tmp, cap, truth, videos, plates = scene
    fits = [_truth_fit(cap, k) for k in range(2)]
    fits[0].transl[0] = np.nan  # person 1, frame 0
    write_bodies(
        tmp_path / "bodies.parquet", fits, [joint_evidence(f, None) for f in fits], fps=30.0,
        camera_names=cap.rig.names, model={"body_model": "anny"}, settings={},
        settings_sha256="0" * 64, stats={},
    )  # fmt: skip
    out = tmp_path / "crops.h5"
    report = recut_crops(tmp / "crops.h5", cap.rig, videos, tmp_path / "bodies.parquet", out,
                         plates=plates)  # fmt: skip
    store = CropStore(out)
    frame, person = store.read_column("frame"), store.read_column("person_id")
    got = {(int(f), int(p)) for f, p in zip(frame, person, strict=True)}
    assert (0, 1) not in got and {(1, 1), (0, 2), (1, 2)} <= got
    assert report.unposed == 1 and "1 fitted body with non-finite parameters" in (
        report.summary_line()
    )


def test_a_view_whose_cut_fails_is_named_by_camera_and_frame(scene, tmp_path, monkeypatch):
    """The views are cut on a pool of threads: an error inside one (here the labels) came back
    naming neither the camera nor the frame."""
    import gst.fuse.body_crops as body_crops

    tmp, cap, truth, videos, plates = scene

    def broken(rays, *args, **kwargs):
        raise ValueError("labels failed")

    monkeypatch.setattr(body_crops, "body_labels", broken)
    with pytest.raises(ValueError, match="labels failed") as err:
        recut_crops(tmp / "crops.h5", cap.rig, videos, tmp / "bodies.parquet",
                    tmp_path / "crops.h5", plates=plates)  # fmt: skip
    notes = "\n".join(getattr(err.value, "__notes__", []))
    assert f"camera {cap.rig.names[0]}, frame 0" in notes


def test_two_empty_sides_agree():
    """A scene without people (no crop cut, none extracted) scored agreement 0, so the fuse
    stage ran a second fusion on an empty store and reported "agreement 0.000"."""
    empty = BodyCropReport(0, 0, 10, {}, 0, 0.0)
    assert empty.agreement() == 1.0
    assert dataclasses.replace(empty, extraction_crops=4).agreement() == 0.0
    assert dataclasses.replace(empty, crops=4, extraction_crops=5, paired=4).agreement() == 0.8

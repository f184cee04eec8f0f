"""fuse_scene end to end on a small crop store, and resume after kill -9: a run killed after
its first batch of people, rerun into the same folder, writes byte-identical outputs."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from gst.fuse import FitOptions, FuseOptions, fuse_scene
from tests.fuse_fixtures import capture_in_store

ROOT = Path(__file__).resolve().parents[1]
OPTS = FuseOptions(fit=FitOptions(iterations=60), people_per_batch=1, overlay=False)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    torch.set_num_threads(1)
    tmp = tmp_path_factory.mktemp("fuse")
    cap, landmarks = capture_in_store(tmp, n_people=3, n_frames=4, n_cams=3, seed=7)
    np.save(tmp / "landmarks.npy", landmarks)
    return tmp, cap, landmarks


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def test_fuse_scene_writes_every_output(scene):
    tmp, cap, landmarks = scene
    res = fuse_scene(
        tmp / "crops.h5", cap.rig, tmp / "a" / "fused", tmp / "a" / "report", fps=30.0,
        options=OPTS, landmarks=landmarks,
    )  # fmt: skip
    names = set(_files(tmp / "a" / "fused"))
    assert {"bodies.parquet", "landmarks.parquet"} <= names
    assert {f"trc/person_{k}.trc" for k in (1, 2, 3)} <= names
    assert {f"c3d/person_{k}.c3d" for k in (1, 2, 3)} <= names
    assert not (tmp / "a" / "fused" / ".work").exists()
    assert {"report.md", "summary.json", "bone_lengths.png"} <= set(_files(tmp / "a" / "report"))
    t = pq.read_table(tmp / "a" / "fused" / "bodies.parquet")
    assert t.num_rows == 12 and t.column("person_id").to_pylist()[:3] == [1, 2, 3]
    err = [np.linalg.norm(f.joints - cap.joints[k], axis=-1).mean() for k, f in enumerate(res.fits)]
    assert max(err) < 0.05  # few iterations, few frames; the accuracy test is test_fuse_fit
    assert res.summary.gap_filled_share == 0.0
    assert res.summary.exchanged_view_groups == 0  # clean landmarks: no view read mirrored


def test_resume_after_kill_gives_identical_outputs(scene, tmp_path):
    tmp, cap, landmarks = scene
    ref_dir, run_dir = tmp_path / "ref", tmp_path / "run"
    fuse_scene(tmp / "crops.h5", cap.rig, ref_dir / "fused", ref_dir / "report", fps=30.0,
               options=OPTS, landmarks=landmarks)  # fmt: skip
    # The child fits person 1, saves that batch, and is killed (SIGKILL) as it starts person 2.
    child = textwrap.dedent(f"""
        import os, signal, sys, numpy as np, torch
        sys.path.insert(0, {str(ROOT)!r})
        import gst.fuse.scene as scene
        from tests.fuse_fixtures import make_rig
        from tests.test_fuse_resume import OPTS
        calls = []
        real = scene.fit_people
        def fit_then_die(*a, **k):
            calls.append(1)
            if len(calls) == 2:
                os.kill(os.getpid(), signal.SIGKILL)
            return real(*a, **k)
        scene.fit_people = fit_then_die
        scene.fuse_scene({str(tmp / "crops.h5")!r}, make_rig(3), {str(run_dir / "fused")!r},
                         {str(run_dir / "report")!r}, fps=30.0, options=OPTS,
                         landmarks=np.load({str(tmp / "landmarks.npy")!r}))
    """)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", child], cwd=ROOT, env=env, capture_output=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()[-2000:]
    work = run_dir / "fused" / ".work"
    assert (work / "fit_0_000000.npz").is_file() and not (work / "fit_0_000001.npz").exists()
    assert not (run_dir / "fused" / "bodies.parquet").exists()
    fuse_scene(tmp / "crops.h5", cap.rig, run_dir / "fused", run_dir / "report", fps=30.0,
               options=OPTS, landmarks=landmarks)  # fmt: skip
    ref, got = _files(ref_dir / "fused"), _files(run_dir / "fused")
    assert sorted(ref) == sorted(got)
    for name in ref:
        assert ref[name] == got[name], name
    assert _files(ref_dir / "report")["summary.json"] == _files(run_dir / "report")["summary.json"]


def test_the_fitted_body_gives_views_read_again_their_first_reading_back(scene, monkeypatch):
    """A second reading of person 1's crops in camera 0 (gst.fuse.relook, stubbed here) that is
    80 px off: without the body's judgement the robust fit still follows it a little (1.3 mm
    here); with it, those views get their first reading back and the body is where a run
    without any second reading puts it, whichever reading the first fit starts from."""
    from dataclasses import replace

    import gst.fuse.scene as fuse_module
    from gst.data.store import CropStore
    from gst.fuse.relook import RelookOptions, RelookResult

    tmp, cap, landmarks = scene
    index = CropStore(tmp / "crops.h5").index
    person, camera = (index.column(k).to_numpy() for k in ("person_id", "camera_index"))
    rows = np.flatnonzero((person == 1) & (camera == 0))

    def read_again(store, lm, options=None, model=None, progress=None, cache=None):
        off = np.array(lm, np.float32)
        off[rows, :, 0] += 80.0
        return RelookResult(off, rows, np.zeros(len(lm)))

    monkeypatch.setattr(fuse_module, "relook_crowded", read_again)
    err = {}
    variants = {
        "none": None,
        "blind": RelookOptions(judge=False),
        "judged": RelookOptions(),
        "judged, fitted from the first readings": RelookOptions(first="stored"),
    }
    for name, relook in variants.items():
        out = tmp / f"relook_{len(err)}"
        options = replace(OPTS, relook=relook)
        res = fuse_scene(
            tmp / "crops.h5", cap.rig, out / "fused", out / "report", fps=30.0,
            options=options, landmarks=landmarks,
        )  # fmt: skip
        err[name] = np.linalg.norm(res.fits[0].joints - cap.joints[0], axis=-1).mean()
    assert err["judged"] < err["none"] + 2e-4 and err["blind"] > err["judged"] + 1e-3, err
    assert err["judged, fitted from the first readings"] < err["none"] + 2e-4, err


def test_a_person_with_nothing_readable_is_left_out_and_named(scene, tmp_path, caplog):
    """Person 3's every landmark has confidence 0 (projected from a skeleton, not read): the
    others are fused, person 3 is not, and the log says so (it used to stop the stage). The
    extraction's people as they are (no regrouping, which would drop person 3 on its own)."""
    import logging
    from dataclasses import replace

    from gst.data.store import CropStore

    tmp, cap, landmarks = scene
    person = CropStore(tmp / "crops.h5").index.column("person_id").to_numpy()
    blind = np.array(landmarks, np.float32)
    blind[person == 3, :, 2] = 0.0
    log = logging.getLogger("test_fuse_unreadable")
    with caplog.at_level(logging.WARNING, logger=log.name):
        res = fuse_scene(
            tmp / "crops.h5", cap.rig, tmp_path / "fused", tmp_path / "report", fps=30.0,
            options=replace(OPTS, regroup=None), landmarks=blind, log=log,
        )  # fmt: skip
    assert [f.person_id for f in res.fits] == [1, 2]
    assert "people [3] left out" in caplog.text
    t = pq.read_table(tmp_path / "fused" / "bodies.parquet")
    assert sorted(set(t.column("person_id").to_pylist())) == [1, 2]


def test_reprojection_is_reported_over_every_reading_and_over_the_views_used(scene, tmp_path):
    """Camera 0's landmarks of person 1 moved 40 px: the triangulation leaves them out, so the
    reprojection over the views it used stays that of clean data, while the one over every
    reading takes them in."""
    from dataclasses import replace

    from gst.data.store import CropStore

    tmp, cap, landmarks = scene
    index = CropStore(tmp / "crops.h5").index
    person, camera = (index.column(k).to_numpy() for k in ("person_id", "camera_index"))
    moved = np.array(landmarks, np.float32)
    moved[(person == 1) & (camera == 0), :, 0] += 40.0
    res = fuse_scene(
        tmp / "crops.h5", cap.rig, tmp_path / "fused", tmp_path / "report", fps=30.0,
        options=replace(OPTS, regroup=None, relook=None), landmarks=moved,
    )  # fmt: skip
    one = res.summary.people[0]
    assert np.nanmedian(res.fits[0].reprojection[:, 0]) > 30.0  # the moved readings, unexplained
    assert one["median_reprojection_used_px"] < 2.0  # ... and not among the views used
    assert one["median_reprojection_px"] > one["median_reprojection_used_px"] + 0.2
    s = res.summary
    assert s.median_reprojection_used_px <= s.median_reprojection_px
    assert "over the readings the triangulation used" in (tmp_path / "report/report.md").read_text()


def test_nobody_readable_writes_empty_outputs(scene, tmp_path):
    """Every landmark without confidence: no person is fused, and the stage still writes its
    (empty) Parquet files and report instead of stopping."""
    from dataclasses import replace

    tmp, cap, landmarks = scene
    blind = np.array(landmarks, np.float32)
    blind[..., 2] = 0.0
    res = fuse_scene(
        tmp / "crops.h5", cap.rig, tmp_path / "fused", tmp_path / "report", fps=30.0,
        options=replace(OPTS, regroup=None), landmarks=blind,
    )  # fmt: skip
    assert res.fits == [] and pq.read_table(tmp_path / "fused" / "bodies.parquet").num_rows == 0
    assert (tmp_path / "report" / "report.md").is_file()


def test_a_rerun_with_other_landmarks_or_another_rig_starts_over(scene, tmp_path, monkeypatch):
    """The resume key held the options, the store's stat and the frame rate only: a call
    interrupted, then made again into the same folder with other landmarks (or another rig),
    fitted the first call's landmarks cached in the work folder."""
    import gst.fuse.scene as fscene

    tmp, cap, landmarks = scene
    seen = []

    class Stop(Exception):
        pass

    def group_by_person(store, lm):  # stands in for the rest of the run: record, then stop
        seen.append(np.array(lm))
        raise Stop

    monkeypatch.setattr(fscene, "group_by_person", group_by_person)
    other = landmarks.copy()
    other[..., :2] += 40.0
    moved = cap.rig.cameras[0]
    rig2 = type(cap.rig)([replace_camera(moved)] + list(cap.rig.cameras[1:]))
    calls = [(landmarks, cap.rig), (other, cap.rig), (landmarks, cap.rig), (landmarks, rig2)]
    keys = []
    for lm, rig in calls:
        with pytest.raises(Stop):
            fuse_scene(tmp / "crops.h5", rig, tmp_path / "fused", tmp_path / "report", fps=30.0,
                       options=OPTS, landmarks=lm)  # fmt: skip
        keys.append((tmp_path / "fused" / ".work" / "settings.json").read_text())
    assert np.allclose(seen[1], other) and np.allclose(seen[2], landmarks)
    assert keys[0] != keys[1] and keys[0] == keys[2] and keys[3] != keys[2]


def replace_camera(cam):
    """Another calibration of the camera's lens (the crops carry its pose, checked apart)."""
    from dataclasses import replace

    K = cam.K.copy()
    K[0, 0] += 1.0
    return replace(cam, K=K)


def test_a_rig_other_than_the_extractions_is_refused_naming_the_camera(scene, tmp_path):
    """The bodies are fitted in the crops' own cameras, the overlays and the re-cut in the rig
    given: a rig recalibrated after the extraction gave bodies in the old calibration and
    overlays in the new one, without a word. The refusal leaves no work folder."""
    from dataclasses import replace

    tmp, cap, landmarks = scene
    cams = list(cap.rig.cameras)
    cams[1] = replace(cams[1], t=cams[1].t + np.array([0.01, 0.0, 0.0]))
    moved = type(cap.rig)(cams)
    with pytest.raises(ValueError, match=f"camera {cams[1].name}'s crops were cut with another"):
        fuse_scene(tmp / "crops.h5", moved, tmp_path / "fused", tmp_path / "report", fps=30.0,
                   options=OPTS, landmarks=landmarks)  # fmt: skip
    assert not (tmp_path / "fused").exists()


def test_more_cameras_than_the_views_masks_hold_are_refused(scene, tmp_path, monkeypatch):
    """The views masks are int64 bit masks: a 64th camera's bit was the sign, a 65th's none."""
    import gst.fuse.scene as fscene

    tmp, cap, landmarks = scene
    monkeypatch.setattr(fscene, "MAX_CAMERAS", 2)  # the store has 3
    with pytest.raises(ValueError, match="3 cameras; fusion takes at most 2"):
        fuse_scene(tmp / "crops.h5", cap.rig, tmp_path / "fused", tmp_path / "report", fps=30.0,
                   options=OPTS, landmarks=landmarks)  # fmt: skip


def test_marker_files_of_people_from_an_earlier_fusion_are_removed(scene, tmp_path):
    """A library caller fusing again into one folder kept the earlier fusion's person files
    beside the new ones (the stage writes into a fresh folder), and a write killed before its
    rename left its hidden temporary file, which the stage then moved along with the outputs."""
    tmp, cap, landmarks = scene
    for sub in ("trc", "c3d"):
        (tmp_path / "fused" / sub).mkdir(parents=True)
        (tmp_path / "fused" / sub / f"person_99.{sub}").write_text("an earlier fusion's")
        (tmp_path / "fused" / sub / f".person_1.k2x9.tmp.{sub}").write_text("killed mid-write")
    (tmp_path / "fused" / ".bodies.a1b2.tmp.parquet").write_text("killed mid-write")
    res = fuse_scene(tmp / "crops.h5", cap.rig, tmp_path / "fused", tmp_path / "report",
                     fps=30.0, options=OPTS, landmarks=landmarks)  # fmt: skip
    for sub, written in (("trc", res.trc), ("c3d", res.c3d)):
        assert sorted((tmp_path / "fused" / sub).iterdir()) == sorted(written)
    assert not list((tmp_path / "fused").glob(".*"))


def test_a_store_extracted_at_a_stride_is_refused(scene, tmp_path):
    """fuse took frames 1 apart for neighbours: at extract.frame_stride 2 half the fused rows
    were 'gap-filled' and the temporal votes were off; at 5 the smoothness term was off too,
    all without a word."""
    import shutil

    import h5py

    tmp, cap, landmarks = scene
    shutil.copy(tmp / "crops.h5", tmp_path / "crops.h5")
    with h5py.File(tmp_path / "crops.h5", "r+") as f:
        f.attrs["setting.frame_stride"] = 2
    with pytest.raises(ValueError, match="extract with frame_stride 1"):
        fuse_scene(tmp_path / "crops.h5", cap.rig, tmp_path / "fused", tmp_path / "report",
                   fps=30.0, options=OPTS, landmarks=landmarks)  # fmt: skip

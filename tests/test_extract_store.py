"""The HDF5 crop store: append, commit, resume, selection, multi-view groups, refusal of bad
stores."""

import os
import pickle
import subprocess
import sys

import h5py
import numpy as np
import pyarrow.parquet as pq
import pytest

from gst.data.store import (
    CropBatch,
    CropStore,
    CropStoreWriter,
    StoreError,
    index_path_for,
    merge_part,
    write_subset,
)
from tests.real_capture import NEEDS_MODELS

S = 16
CAMS = ["a", "b", "c"]


def _batch(frames, cams, persons, seed=0) -> CropBatch:
    n = len(frames)
    rng = np.random.default_rng(seed)
    return CropBatch(
        images=rng.integers(0, 255, (n, S, S, 3), dtype=np.uint8),
        masks=rng.integers(0, 255, (n, S, S), dtype=np.uint8),
        K_crop=np.tile(np.eye(3), (n, 1, 1)) * rng.uniform(1, 2, (n, 1, 1)),
        R=np.tile(np.eye(3), (n, 1, 1)),
        t=rng.normal(size=(n, 3)),
        box=rng.uniform(0, 100, (n, 4)),
        crop_box=rng.uniform(0, 100, (n, 3)),
        camera=np.asarray(cams, np.int32),
        frame=np.asarray(frames, np.int64),
        person_id=np.asarray(persons, np.int64),
        mask_support=rng.uniform(0, 1, n).astype(np.float32),
    )


def test_write_read_select_and_groups(tmp_path):
    path = tmp_path / "crops.h5"
    b1 = _batch([0, 0, 0, 1, 1], [0, 1, 2, 0, 2], [7, 7, 7, 7, 7], seed=1)
    b2 = _batch([1, 2, 2], [1, 0, 1], [8, 7, 7], seed=2)
    with CropStoreWriter(path, CAMS, S, {"scale": 1.2}) as w:
        w.commit(b1, [(0, 0), (0, 1), (0, 2), (1, 0), (1, 2)])
        w.commit(b2, [(1, 1), (2, 0), (2, 1), (2, 2)])
        w.finalize()
    store = CropStore(path)
    assert len(store) == 8
    assert store.camera_names == CAMS
    got = store.read([6, 0, 3])
    assert np.array_equal(got.images[0], b2.images[1])
    assert np.array_equal(got.images[1], b1.images[0])
    assert np.array_equal(got.K_crop[2], b1.K_crop[3])
    assert np.array_equal(store.select(frames=[1], cameras=["c"]), [4])
    assert np.array_equal(store.select(persons=[8]), [5])
    assert np.array_equal(store.select(frames=[0], cameras=[1]), [1])
    groups = {(g.frame, g.person_id): g for g in store.multiview_groups(min_views=2)}
    assert set(groups) == {(0, 7), (1, 7), (2, 7)}
    assert sorted(groups[(0, 7)].cameras.tolist()) == [0, 1, 2]
    assert len(store.multiview_groups(min_views=3)) == 1
    index = pq.read_table(index_path_for(path))
    assert index.num_rows == 8 and index.column("camera").to_pylist()[5] == "b"
    # Picklable for data-loader workers: the file handle is reopened lazily.
    clone = pickle.loads(pickle.dumps(store))
    assert np.array_equal(clone.read([2]).masks, store.read([2]).masks)
    with pytest.raises(KeyError, match="camera 'z'"):
        store.select(cameras=["z"])
    with pytest.raises(IndexError):
        store.read([8])


def test_half_written_batch_is_invisible_and_cut_on_resume(tmp_path):
    path = tmp_path / "crops.h5"
    with CropStoreWriter(path, CAMS, S) as w:
        w.commit(_batch([0, 0], [0, 1], [1, 1]), [(0, 0), (0, 1)])
    # Simulate a writer killed mid-batch: rows appended, counters not yet updated.
    with h5py.File(path, "a") as f:
        for name in ("images", "masks", "frame", "camera"):  # as `commit` resizes them
            f[name].resize(5, axis=0)
        f["frame"][2:5] = 99
        f["done"].resize(3, axis=0)
        del f.attrs["complete"]  # the stale index is rebuilt from the committed rows only
    (tmp_path / "crops.index.parquet").unlink(missing_ok=True)
    with pytest.raises(StoreError, match="incomplete"):
        CropStore(path)
    partial = CropStore(path, allow_incomplete=True)
    assert len(partial) == 2 and 99 not in partial.index.column("frame").to_pylist()
    with CropStoreWriter(path, CAMS, S) as w:
        assert w.n_committed == 2
        assert w.done_pairs() == {(0, 0), (0, 1)}
        w.commit(_batch([0], [2], [1]), [(0, 2)])
        w.finalize()
    store = CropStore(path)
    assert len(store) == 3
    assert store.index.column("frame").to_pylist() == [0, 0, 0]
    with h5py.File(path, "r") as f:
        assert all(f[k].shape[0] == 3 for k in ("images", "masks", "frame", "camera", "person_id"))


def test_every_row_reader_refuses_uncommitted_and_negative_rows(tmp_path):
    """The rows of a half-written batch lie past `n_committed` in the file, and a negative row
    counts from the file's end: `read` refused both, the per-column readers returned them."""
    path = tmp_path / "crops.h5"
    with CropStoreWriter(path, CAMS, S) as w:
        w.commit(_batch([0, 0], [0, 1], [1, 1]), [(0, 0), (0, 1)])
    with h5py.File(path, "a") as f:  # a writer killed mid-batch, as above
        for name in ("images", "masks", "frame", "camera"):
            f[name].resize(5, axis=0)
        f["frame"][2:5] = 99
    partial = CropStore(path, allow_incomplete=True)
    for read in (
        lambda rows: partial.read_column("frame", rows),
        partial.read_images,
        partial.read_masks,
        partial.read,
    ):
        for rows in ([3], [-1], [0, 2]):
            with pytest.raises(IndexError, match=r"\[0, 2\)"):
                read(rows)
    assert partial.read_column("frame", [1, 0]).tolist() == [0, 0]


def test_a_batch_whose_fields_do_not_match_its_rows_is_refused(tmp_path):
    """h5py broadcasts a field of one row over the batch, and a camera index past the store's
    cameras failed only at `finalize`, after all the work."""
    path = tmp_path / "crops.h5"
    with CropStoreWriter(path, CAMS, S) as w:
        short = _batch([0, 0, 0], [0, 1, 2], [5, 5, 5])
        short.person_id = short.person_id[:1]
        with pytest.raises(StoreError, match="'person_id' has shape \\(1,\\), expected \\(3,\\)"):
            w.commit(short, [(0, 0), (0, 1), (0, 2)])
        with pytest.raises(StoreError, match="camera indices 0..3 outside the store's 3"):
            w.commit(_batch([0, 0], [0, 3], [5, 5]), [(0, 0), (0, 3)])
        w.commit(_batch([0], [0], [5]), [(0, 0)])
        assert w.n_committed == 1
        w.finalize()
    assert CropStore(path).read_column("person_id").tolist() == [5]


def test_an_empty_store_indexes_cameras_as_strings(tmp_path):
    """A store without rows typed its index's camera column as null, so the indices of two
    stores could not be joined."""
    import pyarrow as pa

    empty, full = tmp_path / "empty.h5", tmp_path / "full.h5"
    with CropStoreWriter(empty, CAMS, S) as w:
        w.finalize()
    with CropStoreWriter(full, CAMS, S) as w:
        w.commit(_batch([0], [1], [1]), [(0, 1)])
        w.finalize()
    tables = [pq.read_table(index_path_for(p)) for p in (empty, full)]
    assert tables[0].schema.field("camera").type == pa.string()
    joined = pa.concat_tables([t.replace_schema_metadata(None) for t in tables])
    assert joined.column("camera").to_pylist() == ["b"]
    assert CropStore(empty).index.schema.field("camera").type == pa.string()


def test_a_truncated_store_file_is_named(tmp_path):
    path = tmp_path / "crops.h5"
    with CropStoreWriter(path, CAMS, S) as w:
        w.commit(_batch([0], [0], [1]), [(0, 0)])
        w.finalize()
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(StoreError, match="crops.h5: cannot open the crop store"):
        CropStore(path)


def test_reopening_marks_incomplete_until_finalized(tmp_path):
    path = tmp_path / "crops.h5"
    with CropStoreWriter(path, CAMS, S) as w:
        w.commit(_batch([0], [0], [1]), [(0, 0)])
        w.finalize()
    CropStore(path)
    with CropStoreWriter(path, CAMS, S) as w:
        w.commit(_batch([1], [0], [1]), [(1, 0)])
    with pytest.raises(StoreError, match="incomplete"):
        CropStore(path)


def test_incompatible_store_is_refused(tmp_path):
    path = tmp_path / "crops.h5"
    with CropStoreWriter(path, CAMS, S, {"scale": 1.2}) as w:
        w.finalize()
    with pytest.raises(StoreError, match="crop_size=16"):
        CropStoreWriter(path, CAMS, 32).open()
    with pytest.raises(StoreError, match="cameras"):
        CropStoreWriter(path, ["a", "b"], S).open()
    with pytest.raises(StoreError, match="scale"):
        CropStoreWriter(path, CAMS, S, {"scale": 1.5}).open()
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = np.arange(3)
    with pytest.raises(StoreError, match="not a crop store"):
        CropStoreWriter(other, CAMS, S).open()
    with h5py.File(other, "r") as f:  # untouched
        assert f["x"].shape == (3,)
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not hdf5 at all")
    with pytest.raises(StoreError, match="cannot open"):
        CropStoreWriter(junk, CAMS, S).open()
    with pytest.raises(StoreError, match="does not exist"):
        CropStore(tmp_path / "missing.h5")


def test_versions_and_landmarks_that_do_not_match_are_refused(tmp_path):
    """A store of another format version is neither read nor appended to, and a writer with
    landmarks never appends to a store without them or the other way round (the rows of the
    two kinds of dataset would no longer line up)."""
    path = tmp_path / "crops.h5"
    with CropStoreWriter(path, CAMS, S) as w:
        w.commit(_batch([0], [0], [1]), [(0, 0)])
        w.finalize()
    with pytest.raises(StoreError, match="has no landmarks"):
        CropStoreWriter(path, CAMS, S, landmarks=True).open()
    with_lm = tmp_path / "with_landmarks.h5"
    b = _batch([0], [0], [1])
    b.landmarks = np.zeros((1, 33, 3), np.float32)
    with CropStoreWriter(with_lm, CAMS, S, landmarks=True) as w:
        w.commit(b, [(0, 0)])
        w.finalize()
    with pytest.raises(StoreError, match="holds landmarks"):  # accepted before: rows misaligned
        CropStoreWriter(with_lm, CAMS, S).open()
    # the association changed (hull -> keypoints, the person model installed since): that is the
    # cause to name, not the landmarks that come with it
    hull = tmp_path / "hull.h5"
    with CropStoreWriter(hull, CAMS, S, {"association": "hull"}) as w:
        w.finalize()
    with pytest.raises(StoreError, match="association='hull'.*association='keypoints'"):
        CropStoreWriter(hull, CAMS, S, {"association": "keypoints"}, landmarks=True).open()
    for version in (0, 99):
        with h5py.File(path, "a") as f:
            f.attrs["version"] = version
        with pytest.raises(StoreError, match=f"version {version}"):
            CropStore(path)
        with pytest.raises(StoreError, match=f"version {version}"):
            CropStoreWriter(path, CAMS, S).open()


def test_a_creation_killed_half_way_is_created_again(tmp_path, monkeypatch):
    """A writer killed while creating the store (some datasets made, the counters not): the
    next writer recognises its own half-made file and starts it again (before: the format
    attribute came last, and the file was refused as 'not a crop store')."""
    path = tmp_path / "crops.h5"
    made = h5py.Group.create_dataset
    calls = []

    def dies_on_the_third(self, *args, **kwargs):
        calls.append(args[0] if args else kwargs.get("name"))
        if len(calls) == 3:
            raise KeyboardInterrupt("killed")
        return made(self, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", dies_on_the_third)
    with pytest.raises(KeyboardInterrupt):
        CropStoreWriter(path, CAMS, S).open()
    monkeypatch.setattr(h5py.Group, "create_dataset", made)
    with CropStoreWriter(path, CAMS, S) as w:
        w.commit(_batch([0], [0], [1]), [(0, 0)])
        w.finalize()
    assert len(CropStore(path)) == 1


def test_stale_index_is_rebuilt(tmp_path):
    path = tmp_path / "crops.h5"
    with CropStoreWriter(path, CAMS, S) as w:
        w.commit(_batch([0, 1], [0, 1], [3, 3]), [(0, 0), (1, 1)])
        w.finalize()
    index_path_for(path).unlink()
    store = CropStore(path)
    assert store.index.column("person_id").to_pylist() == [3, 3]


def test_read_landmarks_matches_read_without_images(tmp_path):
    """`read_landmarks` gives what `read(rows).landmarks` gives (any order, repeats), and None
    for a store without landmarks."""
    path = tmp_path / "crops.h5"
    b = _batch([0, 0, 1, 1], [0, 1, 0, 1], [7, 7, 7, 7], seed=3)
    b.landmarks = np.random.default_rng(4).uniform(0, S, (4, 33, 3)).astype(np.float32)
    with CropStoreWriter(path, CAMS, S, landmarks=True) as w:
        w.commit(b, [(0, 0), (0, 1), (1, 0), (1, 1)])
        w.finalize()
    store = CropStore(path)
    rows = [3, 0, 3, 1]
    np.testing.assert_array_equal(store.read_landmarks(rows), store.read(rows).landmarks)
    np.testing.assert_array_equal(store.read_landmarks(), store.read([0, 1, 2, 3]).landmarks)
    plain = tmp_path / "plain.h5"
    with CropStoreWriter(plain, CAMS, S) as w:
        w.commit(_batch([0], [0], [7]), [(0, 0)])
        w.finalize()
    assert CropStore(plain).read_landmarks() is None


@pytest.mark.parametrize("main_compression", ["gzip", "lzf"])
def test_merging_a_part_copies_its_rows_exactly(tmp_path, main_compression):
    """`merge_part` appends a camera's part store: the same rows as the part holds, whether the
    crops go over as compressed chunks (same settings) or are recompressed (lzf main store)."""
    part = tmp_path / "part.h5"
    b = _batch([0, 0, 1, 2], [1, 1, 1, 1], [7, 8, 7, 7], seed=3)
    with CropStoreWriter(part, CAMS, S) as w:
        w.commit(_rows(b, 0, 2), [(0, 1)])
        w.commit(_rows(b, 2, 4), [(1, 1), (2, 1), (3, 1)])  # frame 3: nobody
    main = tmp_path / "crops.h5"
    with CropStoreWriter(main, CAMS, S, compression=main_compression) as w:
        w.commit(_batch([0], [0], [7], seed=4), [(0, 0)])
        assert merge_part(w, part, 1, commit_frames=2) == 4
        assert merge_part(w, part, 1, commit_frames=2) == 0  # already there
        w.finalize()
    store = CropStore(main)
    got = store.read(np.arange(1, 5))
    for name in ("images", "masks", "K_crop", "t", "frame", "person_id", "mask_support"):
        assert np.array_equal(getattr(got, name), getattr(b, name)), name
    with h5py.File(main, "r") as f:
        assert f["images"].compression == main_compression
        assert sorted(map(tuple, f["done"][:].tolist())) == [(0, 0), (0, 1), (1, 1), (2, 1), (3, 1)]


def _rows(b: CropBatch, a: int, e: int) -> CropBatch:
    return CropBatch(
        **{k: (v[a:e] if isinstance(v, np.ndarray) else v) for k, v in vars(b).items()}
    )


def test_projected_landmarks_are_flagged_and_older_stores_say_nothing(tmp_path):
    """A store with landmarks says per crop whether they were projected from the rig's skeleton
    (`landmarks_projected`, version 3); batches that leave it out mean "all read"; a store
    written without the dataset (version 2) reads None, and so does one without landmarks."""
    path = tmp_path / "crops.h5"
    b = _batch([0, 0, 1, 1], [0, 1, 0, 1], [7, 7, 7, 7], seed=3)
    b.landmarks = np.random.default_rng(4).uniform(0, S, (4, 33, 3)).astype(np.float32)
    b.landmarks_projected = np.array([False, True, False, True])
    c = _batch([2], [0], [7], seed=5)
    c.landmarks = np.zeros((1, 33, 3), np.float32)  # no flag given: read
    with CropStoreWriter(path, CAMS, S, landmarks=True) as w:
        w.commit(b, [(0, 0), (0, 1), (1, 0), (1, 1)])
        w.commit(c, [(2, 0)])
        w.finalize()
    store = CropStore(path)
    assert store.attrs["version"] == 3
    assert store.read_landmarks_projected().tolist() == [False, True, False, True, False]
    assert store.read_landmarks_projected([3, 0]).tolist() == [True, False]
    assert store.read([1, 2]).landmarks_projected.tolist() == [True, False]
    store.close()
    with h5py.File(path, "a") as f:  # as a version 2 store was written
        del f["landmarks_projected"]
        f.attrs["version"] = 2
    old = CropStore(path)
    assert old.read_landmarks_projected() is None
    assert old.read([1]).landmarks_projected.tolist() == [False]  # read as "all read"
    plain = tmp_path / "plain.h5"
    with CropStoreWriter(plain, CAMS, S) as w:
        w.commit(_batch([0], [0], [7]), [(0, 0)])
        w.finalize()
    assert CropStore(plain).read_landmarks_projected() is None


def test_a_subset_store_holds_those_rows_and_the_store_settings(tmp_path):
    path = tmp_path / "crops.h5"
    b = _batch([0, 0, 0, 1, 1, 2], [0, 1, 2, 0, 2, 1], [7, 7, 7, 7, 8, 7], seed=3)
    b.landmarks = np.random.default_rng(4).random((6, 33, 3)).astype(np.float32)
    done = [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2), (2, 0), (2, 1), (2, 2)]
    with CropStoreWriter(path, CAMS, S, {"scale": 1.2, "method": "x"}, landmarks=True) as w:
        w.commit(b, done)
        w.finalize({"n_frames": 3, "source_videos": '{"a": "a.mp4"}'})
    keep = np.array([4, 0, 1])  # camera 2 of frame 0 and frames 1-2 but for one crop left out
    sub = write_subset(CropStore(path), keep, tmp_path / "sub.h5", chunk=2)
    assert len(sub) == 3 and sub.camera_names == CAMS and sub.crop_size == S
    got, want = sub.read(np.arange(3)), CropStore(path).read(keep)
    for name in ("images", "masks", "K_crop", "frame", "camera", "person_id", "landmarks"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    for key in ("setting.scale", "setting.method", "n_frames", "source_videos"):
        assert sub.attrs[key] == CropStore(path).attrs[key], key
    assert bool(sub.attrs["complete"]) and index_path_for(sub.path).is_file()
    # the pairs whose crops were all kept, and the empty ones, stay processed; (0, 2), (1, 0)
    # and (2, 1) lost crops
    with h5py.File(sub.path, "r") as f:
        pairs = {tuple(p) for p in f["done"][: int(f.attrs["n_done"])].tolist()}
    assert pairs == set(done) - {(0, 2), (1, 0), (2, 1)}


@NEEDS_MODELS
def test_scored_rows_get_the_models_own_reading_where_the_landmarks_were_projected(tmp_path):
    """Landmarks projected from the rig's skeleton hold what every camera saw: rows scored as
    single images (`reread`) get the landmark model's reading of the crop instead; every other
    row keeps the stored landmarks (training may use the rig)."""
    import torch

    from gst.detect.crops import detect_crop_landmarks
    from gst.train.keypoints import store_landmarks

    path = tmp_path / "crops.h5"
    b = _batch([0, 0, 1, 1], [0, 1, 0, 1], [7, 7, 7, 7], seed=3)
    b.landmarks = np.random.default_rng(4).uniform(0, S, (4, 33, 3)).astype(np.float32)
    b.landmarks_projected = np.array([True, False, True, False])
    with CropStoreWriter(path, CAMS, S, landmarks=True) as w:
        w.commit(b, [(0, 0), (0, 1), (1, 0), (1, 1)])
        w.finalize()
    images = torch.from_numpy(b.images)
    plain, source = store_landmarks(path, images)
    np.testing.assert_array_equal(plain.numpy(), b.landmarks)
    scored = np.array([False, True, True, True])  # row 0 projected but trained on
    got, source = store_landmarks(path, images, reread=scored)
    assert "1 projected read again" in source
    # the store's scale (visibility, as extraction and tracking give it), not times the whole
    # crop's presence
    found = detect_crop_landmarks(b.images[[2]], rgb=True)
    assert found.presence[0] < 0.99  # a noise crop: the two scales differ here
    np.testing.assert_array_equal(got.numpy()[2], found.landmarks[0])
    np.testing.assert_array_equal(got.numpy()[[0, 1, 3]], b.landmarks[[0, 1, 3]])


def test_a_store_moved_into_place_keeps_an_index_that_names_it(tmp_path):
    """The fuse stage's cut is written as crops_1.h5 and moved to bodycrops/crops.h5 when it
    agrees with the extraction: its index must name the store it sits beside (it said
    crops_1.h5)."""
    import pyarrow.parquet as pq

    from gst.data.store import index_path_for
    from gst.fuse.rounds import _replace

    first = tmp_path / "work" / "crops_1.h5"
    first.parent.mkdir()
    with CropStoreWriter(first, CAMS, S) as w:
        w.commit(_batch([0, 1], [0, 0], [7, 7], seed=1), [(0, 0), (1, 0)])
        w.finalize()
    final = tmp_path / "bodycrops" / "crops.h5"
    _replace(first, final)
    meta = pq.read_schema(index_path_for(final)).metadata
    assert meta[b"store"] == b"crops.h5"
    assert not index_path_for(first).exists() and pq.read_table(index_path_for(final)).num_rows == 2


_KILLED_WRITER = r"""
import os, signal, sys
import h5py
import numpy as np
from tests.test_extract_store import CAMS, S, _batch
from gst.data.store import CropStoreWriter

path, kill_at = sys.argv[1], int(sys.argv[2])
writes = {"n": 0}
real = h5py.Dataset.__setitem__


def setitem(self, key, value):  # SIGKILL at the kill_at-th dataset write
    writes["n"] += 1
    if writes["n"] == kill_at:
        os.kill(os.getpid(), signal.SIGKILL)
    return real(self, key, value)


h5py.Dataset.__setitem__ = setitem
with CropStoreWriter(path, CAMS, S, {"x": 1}, compression="gzip") as w:
    done = w.done_pairs()
    for f in range(40):
        if (f, 0) not in done:
            w.commit(_batch([f, f], [0, 0], [1, 2], seed=f), [(f, 0)])
    w.finalize()
"""


def test_a_kill_inside_a_commit_leaves_the_committed_rows_readable(tmp_path):
    """The small per-row arrays were gzip-compressed in 1024-row chunks that every commit
    rewrites; a rewritten compressed chunk moved, and HDF5 could reuse its old space within the
    same commit: a kill there left committed rows unreadable ("filter returned failure during
    read") and the store beyond resuming (4 of 25 random kills in a review's fuzz)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root)}
    failures = []
    for kill_at in range(30, 62, 4):  # dataset writes of the third commit and around it
        path = tmp_path / f"k{kill_at}.h5"
        run = [sys.executable, "-c", _KILLED_WRITER, str(path)]
        killed = subprocess.run([*run, str(kill_at)], cwd=root, env=env, capture_output=True)
        assert killed.returncode == -9
        resumed = subprocess.run([*run, "0"], cwd=root, env=env, capture_output=True, text=True)
        if resumed.returncode != 0:
            failures.append((kill_at, resumed.stderr.strip().splitlines()[-1][:120]))
            continue
        assert len(CropStore(path)) == 80
    assert failures == []


def _store(path, frames, cams, persons, seed=0, settings=None):
    with CropStoreWriter(path, CAMS, S, settings or {}) as w:
        w.commit(_batch(frames, cams, persons, seed), [])
        w.finalize()
    return path


def test_an_index_of_other_rows_is_not_trusted(tmp_path, caplog):
    """A crops.h5 copied over another's, its index left beside it: the index had as many rows
    and was used, so select() named the old frames and people while read() returned the new
    file's pixels. The index is checked against the file's frames, cameras and people, and
    the rebuild is said whatever the old index's length (it was said only at the same length)."""
    a = _store(tmp_path / "a" / "crops.h5", [0, 0, 1, 1], [0, 1, 0, 1], [1, 2, 1, 2])
    b = _store(tmp_path / "b" / "crops.h5", [5, 6, 6], [0, 0, 1], [4, 4, 4], seed=1)
    a.write_bytes(b.read_bytes())  # a's index stays
    with caplog.at_level("WARNING", logger="gst.data"):
        store = CropStore(a)
    assert "index does not describe crops.h5's rows; rebuilt" in caplog.text
    assert store.index.column("frame").to_pylist() == [5, 6, 6]
    assert np.array_equal(store.select(frames=[6]), [1, 2])
    assert store.read(store.select(frames=[6])).frame.tolist() == [6, 6]
    # an index that is not Parquet at all is rebuilt too (was a raw ArrowInvalid)
    index_path_for(a).write_bytes(b"garbage")
    assert CropStore(a).index.column("person_id").to_pylist() == [4, 4, 4]
    # the same rows cut at another scale (other crop boxes): the index is rebuilt too
    c = _store(tmp_path / "c" / "crops.h5", [5, 6, 6], [0, 0, 1], [4, 4, 4], seed=2)
    c.write_bytes(b.read_bytes())  # b's rows, c's index: same ids, other crop boxes
    got = CropStore(c).index.column("crop_side").to_numpy()
    with h5py.File(b, "r") as f:
        np.testing.assert_array_equal(got, f["crop_box"][:, 2])
    # an index without a column of today's layout (version 1 had no single_view)
    table = pq.read_table(index_path_for(b)).drop_columns(["single_view"])
    pq.write_table(table, index_path_for(b))
    assert "single_view" in CropStore(b).index.column_names


def test_a_boolean_row_mask_selects_its_true_rows(tmp_path):
    """A mask built from the index's columns was read as rows 0 and 1 (True/False as ints)."""
    path = _store(tmp_path / "crops.h5", [0, 0, 1, 1], [0, 1, 0, 1], [1, 1, 2, 2])
    store = CropStore(path)
    mask = store.index.column("frame").to_numpy() == 1
    assert store.read(mask).frame.tolist() == [1, 1]
    assert store.read_column("person_id", mask).tolist() == [2, 2]
    with pytest.raises(IndexError, match="one value per row"):
        store.read(np.array([True, False]))
    out = write_subset(store, mask, tmp_path / "sub.h5")
    assert out.read(np.arange(len(out))).frame.tolist() == [1, 1]
    with pytest.raises(IndexError, match=r"rows must be in \[0, 4\)"):
        write_subset(store, [-1], tmp_path / "bad.h5")
    assert not (tmp_path / "bad.h5").exists()  # refused before anything was written
    with pytest.raises(StoreError, match="over the store it is taken from"):
        write_subset(store, mask, path)  # deleted the store before reading it
    assert CropStore(path).read(np.arange(4)).frame.tolist() == [0, 0, 1, 1]


def test_store_writer_refuses_what_it_cannot_keep(tmp_path):
    """Settings on one side only (accepted unchecked, never recorded), float values for integer
    fields (1.7 stored as 1), and a store that another process holds open (told to delete a
    healthy store)."""
    path = _store(tmp_path / "crops.h5", [0], [0], [1], settings={"scale": 1.2})
    with pytest.raises(StoreError, match=r"settings \['scale'\].*\['scale', 'step'\]"):
        CropStoreWriter(path, CAMS, S, {"scale": 1.2, "step": 2}).open()
    with pytest.raises(StoreError, match=r"settings \['scale'\], asked to append with \[\]"):
        CropStoreWriter(path, CAMS, S).open()
    b = _batch([1], [0], [1])
    b.person_id = np.array([1.7])
    with (
        CropStoreWriter(tmp_path / "f.h5", CAMS, S) as w,
        pytest.raises(StoreError, match="person_id"),
    ):
        w.commit(b, [])
    held = h5py.File(path, "r")  # another reader, here in this process
    try:
        with pytest.raises(StoreError, match="open elsewhere") as err:
            CropStoreWriter(path, CAMS, S, {"scale": 1.2}).open()
        assert "delete it" not in str(err.value)
    finally:
        held.close()
    # ... and in another process (HDF5's file lock; none where locking is turned off)
    if os.environ.get("HDF5_USE_FILE_LOCKING", "").upper() == "FALSE":
        return
    code = (
        f"import h5py, time; f = h5py.File({str(path)!r}, 'r'); print('ok', flush=True); "
        "time.sleep(30)"
    )
    other = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert other.stdout.readline().strip() == "ok"
        with pytest.raises(StoreError, match="open elsewhere"):
            CropStoreWriter(path, CAMS, S, {"scale": 1.2}).open()
    finally:
        other.kill()
        other.wait()


def test_a_store_without_a_required_dataset_is_named(tmp_path):
    """The first version-1 stores had no mask_support: read() failed deep in h5py with a
    KeyError naming neither file nor cause; so did a store without camera_names."""
    path = _store(tmp_path / "crops.h5", [0], [0], [1])
    with h5py.File(path, "a") as f:
        del f["mask_support"]
    with pytest.raises(StoreError, match=r"crops\.h5: crop store without its mask_support"):
        CropStore(path)


@pytest.mark.parametrize("dataset", ["masks", "images", "person_id", "landmarks"])
def test_a_store_whose_datasets_hold_fewer_rows_than_committed_is_named(tmp_path, dataset):
    """A complete store whose `masks` held fewer rows than `n_committed` was opened: its index
    had unset mask coverages, and `read` failed in h5py ("Fancy indexing out of range")
    naming no file; a short `person_id` failed building the index, also naming no file."""
    path = tmp_path / "crops.h5"
    with CropStoreWriter(path, CAMS, S, landmarks=True) as w:
        b = _batch([0, 1, 2, 3], [0, 1, 0, 1], [1, 1, 2, 2])
        b.landmarks = np.zeros((4, 33, 3), np.float32)
        w.commit(b, [(0, 0), (1, 1), (2, 0), (3, 1)])
        w.finalize()
    with h5py.File(path, "a") as f:
        f[dataset].resize(2, axis=0)
    with pytest.raises(StoreError, match=rf"crops\.h5: damaged crop store: 4 committed.*{dataset}"):
        CropStore(path)

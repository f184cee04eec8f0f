"""A second look at crowded crops (gst.fuse.relook): which pixels belong to the other people of
a crop's camera and frame, and that only crowded crops are read again, with those people painted
over and the person's own pixels untouched."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from gst.data.store import CropStore
from gst.fuse.relook import RelookOptions, others_masks, relook_crowded
from tests.fuse_fixtures import windows_store
from tests.real_capture import NEEDS_MODELS

S = 64  # crop pixels
RED, GREEN = (0, 0, 255), (0, 255, 0)  # BGR


def _scene(tmp_path) -> CropStore:
    """Two people side by side in camera a, frame 0: person 1 (green, image x 8-24) and person 2
    (red, image x 28-44), each window reaching into the other's; a third crop alone in camera
    b."""
    windows = [(0, 0, 64), (16, 0, 64), (0, 0, 64)]
    masks = np.zeros((3, S, S), np.uint8)
    images = np.full((3, S, S, 3), 90, np.uint8)
    masks[0, 8:56, 8:24] = 255
    images[0, 8:56, 8:24] = GREEN
    images[0, 8:56, 28:44] = RED  # person 2, as crop 0 sees them
    masks[1, 8:56, 12:28] = 255  # person 2 in their own window (x0 = 16)
    images[1, 8:56, 12:28] = RED
    images[1, 8:56, 0:8] = GREEN  # the edge of person 1
    masks[2, 8:56, 8:24] = 255
    return windows_store(
        tmp_path / "c.h5", windows, masks, camera=[0, 0, 1], frame=[0, 0, 0], images=images
    )


def test_the_other_people_are_the_pixels_of_their_masks_outside_ones_own(tmp_path):
    store = _scene(tmp_path)
    others, share = others_masks(store, np.array([0, 1]))
    want = np.zeros((S, S), bool)
    want[8:56, 28:44] = True  # person 2's mask, moved into crop 0's window
    np.testing.assert_array_equal(others[0], want)
    want_1 = np.zeros((S, S), bool)
    want_1[8:56, 0:8] = True  # person 1's right edge (image x 16-24) in person 2's window
    np.testing.assert_array_equal(others[1], want_1)
    np.testing.assert_allclose(share, [want.mean(), want_1.mean()])


class _Recorder:
    """A stand-in for the landmark model that remembers the crops it was given."""

    def __init__(self):
        self.images = []

    def segment(self, image, roi):
        self.images.append(image.copy())
        lm = np.full((33, 3), 7.0, np.float32)
        return SimpleNamespace(landmarks=lm, world_landmarks=np.zeros((33, 3)), presence=1.0)


def test_only_crowded_crops_are_read_again_with_the_others_painted_over(tmp_path):
    """Person 2 covers 19 % of crop 0's window and person 1 9 % of crop 1's: with a threshold of
    12 % only crop 0 is read again, with person 2 painted over and person 1's pixels untouched."""
    store = _scene(tmp_path)
    before = np.zeros((3, 33, 3), np.float32)
    model = _Recorder()
    options = RelookOptions(min_share=0.12, refine=False)
    out = relook_crowded(store, before, options, model=model)
    np.testing.assert_array_equal(out.rows, [0])  # crop 1 is not crowded, crop 2 is alone
    np.testing.assert_allclose(out.shares, [48 * 16 / S**2, 48 * 8 / S**2, 0.0])
    np.testing.assert_array_equal(out.landmarks[0], np.full((33, 3), 7.0))
    np.testing.assert_array_equal(out.landmarks[1:], before[1:])
    (seen,) = model.images
    red = np.all(seen == RED, axis=-1)
    assert not red.any()  # person 2 painted over from the surroundings
    np.testing.assert_array_equal(seen[8:56, 8:24], np.broadcast_to(GREEN, (48, 16, 3)))
    # the ablation reads the same crop again as it is
    model = _Recorder()
    relook_crowded(store, before, replace(options, paint=False), model=model)
    assert np.all(model.images[0][8:56, 28:44] == RED)
    # nobody crowded enough: nothing is read again, and no model is even made
    quiet = relook_crowded(store, before, replace(options, min_share=0.5))
    assert len(quiet.rows) == 0


def test_wrong_landmark_shapes_are_refused(tmp_path):
    with pytest.raises(ValueError, match=r"expected \(3, 33, 3\)"):
        relook_crowded(_scene(tmp_path), np.zeros((2, 33, 3)))


@NEEDS_MODELS
def test_threads_read_the_same_landmarks_as_one(tmp_path):
    """The crowded crops are read on a pool of threads (a camera and frame per task), one
    landmark model each: the same numbers as one thread."""
    one_frame = _scene(tmp_path).read(np.arange(2))
    frames = 4
    rng = np.random.default_rng(0)
    images = np.concatenate([one_frame.images] * frames)
    images = np.clip(images + rng.integers(-20, 20, images.shape), 0, 255)  # frames differ
    store = windows_store(
        tmp_path / "frames.h5", np.concatenate([one_frame.crop_box] * frames),
        np.concatenate([one_frame.masks] * frames), camera=[0] * 2 * frames,
        frame=np.repeat(np.arange(frames), 2), images=images,
    )  # fmt: skip
    before = np.zeros((2 * frames, 33, 3), np.float32)
    one = relook_crowded(store, before, RelookOptions(min_share=0.05), threads=1)
    two = relook_crowded(store, before, RelookOptions(min_share=0.05), threads=2)
    np.testing.assert_array_equal(one.rows, np.arange(2 * frames))
    np.testing.assert_array_equal(one.landmarks, two.landmarks)
    assert np.isfinite(one.landmarks).all() and len(np.unique(one.landmarks[:, 0, 0])) > 1


def test_projected_landmarks_are_no_reading(tmp_path):
    """The extraction's landmarks of a view where the landmark model did not confirm the person
    are its skeleton projected (`landmarks_projected`): the fuse stage takes them with no
    confidence, so they cannot outvote real readings; read landmarks pass unchanged."""
    from gst.data.store import CropBatch, CropStoreWriter
    from gst.fuse.observations import crop_landmarks

    n = 3
    lm = np.random.default_rng(0).uniform(0, S, (n, 33, 3)).astype(np.float32)
    lm[..., 2] = 0.8
    lm[1, :, 2] = 0.5  # the projected one (the extraction's PROJECTED_CONFIDENCE)
    batch = CropBatch(
        images=np.zeros((n, S, S, 3), np.uint8), masks=np.zeros((n, S, S), np.uint8),
        K_crop=np.tile(np.eye(3), (n, 1, 1)), R=np.tile(np.eye(3), (n, 1, 1)),
        t=np.zeros((n, 3)), box=np.zeros((n, 4)), crop_box=np.tile([0.0, 0.0, S], (n, 1)),
        camera=np.array([0, 1, 0], np.int32), frame=np.array([0, 0, 1]),
        person_id=np.ones(n, np.int64), mask_support=np.ones(n, np.float32),
        landmarks=lm, landmarks_projected=np.array([False, True, False]),
    )  # fmt: skip
    with CropStoreWriter(tmp_path / "crops.h5", ["a", "b"], S, landmarks=True) as w:
        w.commit(batch, [(0, 0), (0, 1), (1, 0)])
        w.finalize()
    got = crop_landmarks(CropStore(tmp_path / "crops.h5"))
    np.testing.assert_array_equal(got[[0, 2]], lm[[0, 2]])
    np.testing.assert_array_equal(got[1, :, :2], lm[1, :, :2])
    assert (got[1, :, 2] == 0).all()


@NEEDS_MODELS  # the cache's file is named by the model files' SHA-256
def test_readings_kept_by_content_are_not_read_again(tmp_path, caplog, monkeypatch):
    """With a reading cache the second run over the same crops runs the model on none of them
    and gives the same landmarks; a crop whose pixels changed is read; the second pass (refine)
    has a file of its own; a caller's own model never meets the cache; a damaged cache file is
    logged, removed and written again."""
    import gst.detect.blazepose as blazepose
    from gst.detect.reading_cache import ReadingCache

    made = []

    def recorder(threads=1):
        made.append(_Recorder())
        return made[-1]

    monkeypatch.setattr(blazepose, "BlazePose", recorder)  # relook makes its model from here
    seen = lambda: sum(len(m.images) for m in made)  # noqa: E731
    store = _scene(tmp_path)
    before = np.zeros((3, 33, 3), np.float32)
    options = RelookOptions(min_share=0.05, refine=False)
    cache_dir = tmp_path / "readings"
    first = ReadingCache(cache_dir, refine=False)
    a = relook_crowded(store, before, options, threads=1, cache=first)
    first.save()
    assert seen() == 2 and first.hits == 0
    again = ReadingCache(cache_dir, refine=False)
    b = relook_crowded(store, before, options, threads=1, cache=again)
    assert seen() == 2 and again.hits == 2  # nothing read again
    np.testing.assert_array_equal(a.landmarks, b.landmarks)
    np.testing.assert_array_equal(a.rows, b.rows)
    # other pixels: read
    changed = windows_store(
        tmp_path / "changed.h5", store.read(np.arange(3)).crop_box, store.read_masks(),
        camera=[0, 0, 1], frame=[0, 0, 0], images=store.read_images() // 2,
    )  # fmt: skip
    relook_crowded(changed, before, options, threads=1, cache=ReadingCache(cache_dir, False))
    assert seen() == 4
    # a caller's model: read, whatever the cache holds
    own = _Recorder()
    relook_crowded(store, before, options, model=own, cache=ReadingCache(cache_dir, False))
    assert len(own.images) == 2
    assert ReadingCache(cache_dir, refine=True).path != again.path
    again.path.write_bytes(b"not a zip")
    damaged = ReadingCache(cache_dir, refine=False)
    assert "not read" in caplog.text and not again.path.exists()
    key = ReadingCache.key(np.zeros((2, 2), np.uint8))
    assert damaged.get(key) is None
    damaged.put(key, np.ones((33, 3)))
    damaged.save()
    assert len(np.load(again.path)["keys"]) == 1


def _reading_cache(tmp_path):
    from gst.detect.reading_cache import ReadingCache

    return ReadingCache, tmp_path / "cache"


def test_a_cache_file_damaged_in_its_zip_directory_is_made_again(tmp_path):
    """One flipped bit of a zip directory entry (the compression method) made np.load raise
    NotImplementedError, which was not among the errors caught: fuse and the teacher failed
    until the user found and deleted the file."""
    ReadingCache, folder = _reading_cache(tmp_path)
    cache = ReadingCache(folder, refine=False)
    cache.put(ReadingCache.key(np.zeros((4, 4, 3), np.uint8)), np.ones((33, 3)))
    cache.save()
    data = bytearray(cache.path.read_bytes())
    data[data.rfind(b"PK\x01\x02") + 10] ^= 0x01
    cache.path.write_bytes(bytes(data))
    again = ReadingCache(folder, refine=False)
    assert again.get(ReadingCache.key(np.zeros((4, 4, 3), np.uint8))) is None
    assert not again.path.exists()


def test_two_caches_saving_into_one_folder_keep_each_others_readings(tmp_path):
    """Each saved what it had loaded plus its own: the last writer's readings alone stayed."""
    ReadingCache, folder = _reading_cache(tmp_path)
    a, b = ReadingCache(folder, False), ReadingCache(folder, False)
    ka = ReadingCache.key(np.zeros((2, 2), np.uint8))
    kb = ReadingCache.key(np.ones((2, 2), np.uint8))
    a.put(ka, np.full((33, 3), 1.0))
    b.put(kb, np.full((33, 3), 2.0))
    a.save()
    b.save()
    both = ReadingCache(folder, False)
    assert both.get(ka)[0, 0] == 1.0 and both.get(kb)[0, 0] == 2.0
    assert b.get(ka) is not None  # the merge is b's too


def test_a_view_that_fails_is_named_by_camera_and_frame(tmp_path):
    """The crowded crops are read on a pool of threads: an error there (the landmark model, the
    inpainting, a damaged crop) came back with nothing saying which camera and frame."""

    class Broken(_Recorder):
        def segment(self, image, roi):
            raise RuntimeError("the landmark model failed")

    store = _scene(tmp_path)
    with pytest.raises(RuntimeError, match="landmark model failed") as err:
        relook_crowded(store, np.zeros((3, 33, 3), np.float32),
                       RelookOptions(min_share=0.12, refine=False), model=Broken())  # fmt: skip
    notes = "\n".join(getattr(err.value, "__notes__", []))
    assert f"camera {store.camera_names[0]}, frame 0" in notes

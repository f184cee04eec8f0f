"""Simulated whole-body flips of the input landmarks in multi-view batches (train.landmark_flips):
the input's left/right labels are exchanged, nothing the batch is judged against changes."""

from dataclasses import replace

import torch

from gst.body.markers import BLAZEPOSE_MIRROR
from gst.train.views import sample_multiview


def _with_landmarks(crops):
    g = torch.Generator().manual_seed(3)
    return replace(crops, landmarks=torch.rand(len(crops.images), 33, 3, generator=g) * 100)


def _batch(crops, flips: float):
    return sample_multiview(
        crops, crops.groups(), torch.Generator().manual_seed(0), 16, 2, 32, landmark_flips=flips
    )


def test_flips_exchange_left_and_right_of_the_inputs_only(one_sample):
    crops = _with_landmarks(one_sample[0])
    plain, never, always = _batch(crops, 0.0), _batch(crops, 0.0), _batch(crops, 1.0)
    stored = crops.landmarks[plain.input_index]
    assert torch.equal(plain.input_landmarks, stored) and torch.equal(never.input_landmarks, stored)
    assert torch.equal(always.input_landmarks, stored[:, BLAZEPOSE_MIRROR])
    assert not torch.equal(always.input_landmarks, stored)
    for name in ("input_index", "target_index", "input_images", "target_images", "target_masks", "backgrounds"):
        assert torch.equal(getattr(always, name), getattr(plain, name)), name


def test_a_share_of_flips_mirrors_whole_rows(one_sample):
    crops = _with_landmarks(one_sample[0])
    b = _batch(crops, 0.5)
    stored = crops.landmarks[b.input_index]
    same = (b.input_landmarks == stored).flatten(1).all(1)
    mirrored = (b.input_landmarks == stored[:, BLAZEPOSE_MIRROR]).flatten(1).all(1)
    assert bool((same ^ mirrored).all())  # each row is one or the other, whole
    assert 0 < int(mirrored.sum()) < len(b.input_landmarks)

"""A run resumed into a folder whose last.pt was trained with other held-out cameras or frames,
or on another Gaussian layout, is refused naming what differs (it resumed silently: the held-out
camera of the new run had been trained on, and its scores were novel-view scores no more)."""

from __future__ import annotations

import pytest

from gst.body import BodyModel
from gst.body.random_model import random_body_data
from gst.model.presets import get_preset
from gst.train.losses import LossWeights
from gst.train.recipe import FitOptions, build_network, fit_gst, make_task
from gst.train.trainer import TrainConfig
from tests.test_train_recipe import crop_set


def _fit(tmp_path, net, task, crops, ids, groups, **options):
    return fit_gst(
        net, task, crops,
        TrainConfig(steps=2, batch_size=2, warmup_steps=1, val_every=2, log_every=1),
        tmp_path,
        FitOptions(mode="multiview", num_targets=2, render_size=16, **options),
        body_spec="random", vertex_ids=ids, group_index=groups,
    )  # fmt: skip


def test_resuming_a_run_with_other_heldout_data_is_refused_naming_it(tmp_path):
    body = BodyModel(random_body_data(num_vertices=400, with_posedirs=False))
    cfg = get_preset("tiny", vertex_preset="full")
    net, ids, groups = build_network(cfg, body)
    crops = crop_set(n_frames=6, n_cams=3)
    task = make_task(body, ids, cfg, crops.crop_size, LossWeights(lpips=0.0))
    _fit(tmp_path, net, task, crops, ids, groups, heldout_cameras=("c2",))
    with pytest.raises(ValueError, match=r"last.pt.*held-out cameras \['c2'\].*\['c1'\]"):
        _fit(tmp_path, net, task, crops, ids, groups, heldout_cameras=("c1",))
    with pytest.raises(ValueError, match=r"last.pt.*first held-out frame -1.*4"):
        _fit(tmp_path, net, task, crops, ids, groups, heldout_cameras=("c2",),
             first_heldout_frame=4)  # fmt: skip
    # the same held-out data resumes (the run is finished: nothing to do)
    _fit(tmp_path, net, task, crops, ids, groups, heldout_cameras=("c2",))

"""Shared helpers for the body-model tests: files in the official SMPL layout, written with a
stand-in for chumpy (no SMPL download, no chumpy install)."""

from __future__ import annotations

import pickle
import sys
import types
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import scipy.sparse

from gst.body.model import BodyModelData


@contextmanager
def fake_chumpy():
    """Install a stand-in ``chumpy.ch.Ch`` class that pickles like the real one (an object whose
    state holds its value in ``x``), for writing files in the official SMPL layout."""
    chumpy = types.ModuleType("chumpy")
    ch = types.ModuleType("chumpy.ch")

    class Ch:
        def __init__(self, x):
            self.x = np.asarray(x)
            self._dirty_vars = set()  # real chumpy carries bookkeeping like this in its state

    Ch.__module__ = "chumpy.ch"
    Ch.__qualname__ = "Ch"
    ch.Ch = Ch
    chumpy.ch = ch
    saved = {k: sys.modules.get(k) for k in ("chumpy", "chumpy.ch")}
    sys.modules["chumpy"], sys.modules["chumpy.ch"] = chumpy, ch
    try:
        yield Ch
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v


def official_smpl_dict(data: BodyModelData, ch_class=None) -> dict:
    """The dict an official SMPL .pkl holds, built from ``data`` (chumpy-wrapped where the
    official files use chumpy when ``ch_class`` is given)."""
    wrap = ch_class if ch_class is not None else (lambda x: x)
    V = data.num_vertices
    kintree = np.stack([np.asarray(data.parents), np.arange(data.num_joints)]).astype(np.int64)
    kintree[0, 0] = 4294967295  # as in the official files
    raw = {
        "v_template": wrap(data.v_template),
        "shapedirs": wrap(data.shapedirs),
        "J_regressor": scipy.sparse.csc_matrix(data.dense_J_regressor()),
        "weights": wrap(data.weights),
        "kintree_table": kintree,
        "f": np.asarray(data.faces, dtype=np.uint32),
        "J": data.dense_J_regressor() @ data.v_template,
        "bs_style": "lbs",
        "bs_type": "lrotmin",
        "vert_sym_idxs": np.arange(V),
        "pose_training_info": {"a": 1},
    }
    if data.posedirs is not None:
        # smplx layout (P, V*3) back to the official (V, 3, P)
        raw["posedirs"] = wrap(np.asarray(data.posedirs).T.reshape(V, 3, -1))
    return raw


def write_official_pkl(data: BodyModelData, path: Path, protocol: int = 2) -> Path:
    with fake_chumpy() as Ch:
        raw = official_smpl_dict(data, Ch)
        path.write_bytes(pickle.dumps(raw, protocol=protocol))
    return path


def write_official_npz(data: BodyModelData, path: Path) -> Path:
    raw = official_smpl_dict(data)
    raw["J_regressor"] = raw["J_regressor"].toarray()
    raw = {k: v for k, v in raw.items() if isinstance(v, np.ndarray)}
    np.savez(path, **raw)
    return path

"""The SMPL file loader: where it looks, what it refuses, and that it never runs pickle code."""

from __future__ import annotations

import io
import os
import pickle

import numpy as np
import pytest

from gst.body.random_model import random_body_data
from gst.body.smpl_file import UnsafePickleError, load_smpl_file, safe_load_pickle
from tests.body_fixtures import write_official_pkl


@pytest.fixture(scope="module")
def data():
    return random_body_data(num_vertices=500, seed=1)


def test_missing_file_says_where_and_licence(tmp_path, monkeypatch):
    monkeypatch.setenv("GST_BODY_DIR", str(tmp_path / "nowhere"))
    with pytest.raises(FileNotFoundError) as err:
        load_smpl_file()
    text = str(err.value)
    assert str(tmp_path / "nowhere") in text and "SMPL_NEUTRAL.pkl" in text
    assert "GST_BODY_DIR" in text and "smpl.is.tue.mpg.de" in text and "anny" in text
    with pytest.raises(FileNotFoundError, match="SMPL_FEMALE"):
        load_smpl_file(tmp_path, gender="female")


def test_env_dir_and_gender(tmp_path, monkeypatch, data):
    write_official_pkl(data, tmp_path / "SMPL_MALE.pkl")
    monkeypatch.setenv("GST_BODY_DIR", str(tmp_path))
    loaded = load_smpl_file(gender="male")
    assert loaded.num_vertices == 500 and "male" in loaded.name
    assert "smpl.is.tue.mpg.de" in loaded.licence
    with pytest.raises(ValueError, match="gender must be one of"):
        load_smpl_file(gender="other")


def test_a_file_given_by_path_is_named_by_its_own_gender(tmp_path, data):
    """SMPL_MALE.pkl given as a path was called "SMPL (neutral)", and with gender='female'
    "SMPL (female)"."""
    male = tmp_path / "SMPL_MALE.pkl"
    write_official_pkl(data, male)
    assert load_smpl_file(male).name == "SMPL (male)"
    assert load_smpl_file(male, gender="male").name == "SMPL (male)"
    with pytest.raises(ValueError, match="gender='female' was asked, but the file is the male"):
        load_smpl_file(male, gender="female")
    old_name = tmp_path / "basicModel_f_lbs_10_207_0_v1.0.0.pkl"
    write_official_pkl(data, old_name)
    assert "female" in load_smpl_file(old_name).name


class _Boom:
    """Pickles to a call of os.system: a loader that executes it would create the file."""

    def __init__(self, target):
        self.target = target

    def __reduce__(self):
        return (os.system, (f"touch {self.target}",))


def test_malicious_pickle_is_refused_without_running(tmp_path):
    target = tmp_path / "pwned"
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    path.write_bytes(pickle.dumps({"v_template": _Boom(target)}, protocol=2))
    with pytest.raises(UnsafePickleError, match=r"refusing to load (posix|os|nt)\.system"):
        load_smpl_file(path)
    assert not target.exists()
    # A global smuggled through copyreg's reconstructor is refused too.
    evil = io.BytesIO()
    evil.write(b"\x80\x02cbuiltins\neval\nX\x04\x00\x00\x001+1\x85R.")
    path.write_bytes(evil.getvalue())
    with pytest.raises(UnsafePickleError, match="builtins.eval"):
        safe_load_pickle(path)


def test_wrong_content_names_file_and_key(tmp_path, data):
    path = write_official_pkl(data, tmp_path / "x.pkl")
    raw = safe_load_pickle(path)
    del raw["weights"]
    bad = tmp_path / "bad.npz"
    np.savez(bad, **{k: v for k, v in raw.items() if isinstance(v, np.ndarray)})
    with pytest.raises(ValueError, match=r"bad\.npz: missing key 'weights'"):
        load_smpl_file(bad)
    with pytest.raises(ValueError, match="unknown SMPL file type"):
        (tmp_path / "m.txt").write_text("x")
        load_smpl_file(tmp_path / "m.txt")
    with pytest.raises(ValueError, match="not a readable pickle"):
        (tmp_path / "junk.pkl").write_bytes(b"not a pickle")
        load_smpl_file(tmp_path / "junk.pkl")


def test_npz_with_pickled_objects_is_refused(tmp_path):
    path = tmp_path / "obj.npz"
    np.savez(path, v_template=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="pickled objects"):
        load_smpl_file(path)


def test_an_smplx_like_npz_is_told_by_its_arrays_not_its_objects(tmp_path, data):
    """SMPL-X's npz holds some pickled entries beside its arrays: it was refused for those
    ("save plain arrays"), and re-saving led to the next error. Its 55-joint tree is what
    matters."""
    path = tmp_path / "SMPLX_NEUTRAL.npz"
    write_official_pkl(data, tmp_path / "SMPL_NEUTRAL.pkl")
    raw = safe_load_pickle(tmp_path / "SMPL_NEUTRAL.pkl")
    arrays = {k: np.asarray(v.toarray() if hasattr(v, "toarray") else v) for k, v in raw.items()}
    arrays["kintree_table"] = np.zeros((2, 55), np.int64)
    np.savez(path, joint2num=np.array([{"pelvis": 0}], dtype=object), **arrays)
    with pytest.raises(ValueError, match=r"kintree_table has shape \(2, 55\)"):
        load_smpl_file(path)


def test_chumpy_values_become_numpy(tmp_path, data):
    raw = safe_load_pickle(write_official_pkl(data, tmp_path / "m.pkl"))
    assert type(raw["v_template"]) is np.ndarray
    assert raw["shapedirs"].shape == (500, 3, 10)
    assert raw["J_regressor"].format == "csc" and raw["J_regressor"].shape == (24, 500)


def test_a_coo_regressor_pickled_by_this_scipy_is_read(tmp_path):
    """scipy now keeps a COO matrix's indices as `coords`; only `row` / `col` were read, so a
    regressor re-saved as COO was refused as unreadable."""
    import scipy.sparse

    dense = np.arange(12.0).reshape(3, 4) * (np.arange(12).reshape(3, 4) % 3 == 0)
    path = tmp_path / "coo.pkl"
    path.write_bytes(pickle.dumps({"J_regressor": scipy.sparse.coo_matrix(dense)}, protocol=2))
    np.testing.assert_array_equal(safe_load_pickle(path)["J_regressor"].toarray(), dense)


def test_load_body_model_specs(tmp_path, monkeypatch, data):
    from gst.body import load_body_model

    monkeypatch.setenv("GST_BODY_DIR", str(tmp_path))
    with pytest.raises(FileNotFoundError, match="SMPL_FEMALE"):
        load_body_model("smpl:female")
    write_official_pkl(data, tmp_path / "SMPL_NEUTRAL.pkl")
    assert load_body_model("smpl").num_vertices == 500
    assert load_body_model(str(tmp_path)).num_vertices == 500  # a folder


@pytest.mark.parametrize(
    "key, change, culprit",
    [
        ("shapedirs", lambda a: a.reshape(-1, a.shape[-1]).T.copy(), "shapedirs"),  # (B, V*3)
        ("weights", lambda a: a.T.copy(), "weights"),
        ("v_template", lambda a: a.reshape(-1), "v_template"),
    ],
)
def test_arrays_of_the_wrong_shape_name_their_key(tmp_path, data, key, change, culprit):
    """A transposed flattened shapedirs was reshaped into a scrambled shape space without a word;
    transposed weights raised a bare IndexError; a flat v_template blamed posedirs."""
    raw = safe_load_pickle(write_official_pkl(data, tmp_path / "x.pkl"))
    arrays = {k: v for k, v in raw.items() if isinstance(v, np.ndarray)}
    arrays["J_regressor"] = np.asarray(raw["J_regressor"].todense())  # sparse in the .pkl
    arrays[key] = change(np.asarray(arrays[key]))
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match=rf"bad\.npz: {culprit} has shape"):
        load_smpl_file(tmp_path / "bad.npz")


def _official_arrays(data, tmp_path) -> dict:
    raw = safe_load_pickle(write_official_pkl(data, tmp_path / "x.pkl"))
    arrays = {k: v for k, v in raw.items() if isinstance(v, np.ndarray)}
    arrays["J_regressor"] = np.asarray(raw["J_regressor"].todense())  # sparse in the .pkl
    return arrays


@pytest.mark.parametrize(
    "key, change, shown",
    [
        ("f", lambda a: a + 0.4, r"f must hold whole numbers"),  # cut to ints without a word
        ("kintree_table", lambda a: np.stack([a[0], a[1][::-1]]), r"second row \(the joint ids"),
        ("v_template", lambda a: np.full(a.shape, "a"), r"v_template is not numeric"),
        ("shapedirs", lambda a: a[..., :0], r"shapedirs has no shape components"),
        ("J_regressor", lambda a: np.where(np.arange(a.size).reshape(a.shape) == 7, np.nan, a),
         r"J_regressor contains NaN"),
        ("posedirs", lambda a: np.where(np.arange(a.size).reshape(a.shape) == 7, np.nan, a),
         r"posedirs contains NaN"),
    ],
)  # fmt: skip
def test_malformed_arrays_name_the_file_and_key(tmp_path, data, key, change, shown):
    """Fractional face indices were truncated and a permuted joint-id row loaded a scrambled
    body without a word; a NaN in J_regressor or posedirs loaded and posed NaN vertices; a text
    v_template and zero shape components failed later with messages naming neither."""
    arrays = _official_arrays(data, tmp_path)
    arrays[key] = change(np.asarray(arrays[key]))
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match=rf"bad\.npz: .*{shown}"):
        load_smpl_file(tmp_path / "bad.npz")


def test_an_upper_case_suffix_is_read(tmp_path, data):
    path = write_official_pkl(data, tmp_path / "SMPL_NEUTRAL.PKL")
    assert load_smpl_file(path).num_vertices == 500


def test_a_tree_that_is_not_smpls_is_refused(tmp_path, data):
    """A 24-joint file whose parents differ from SMPL's loaded under SMPL's joint names (the
    overlays and reports draw SMPL's tree whatever the body's)."""
    arrays = _official_arrays(data, tmp_path)
    kt = np.asarray(arrays["kintree_table"]).copy()
    kt[0, 12], kt[0, 16] = 3, 9  # neck under spine1, left_shoulder under spine3
    np.savez(tmp_path / "tree.npz", **{**arrays, "kintree_table": kt})
    with pytest.raises(ValueError, match=r"tree\.npz: .*not SMPL's tree: neck under 3 \(SMPL: 9\)"):
        load_smpl_file(tmp_path / "tree.npz")


@pytest.mark.parametrize("damage", ["empty", "cut", "crc", "npy"])
def test_a_damaged_npz_is_named(tmp_path, data, damage):
    """An empty, cut or corrupted .npz, or an .npy under an .npz name, raised zipfile's or
    NumPy's bare errors, naming no file."""
    from gst.body import load_body_model

    path = tmp_path / "SMPL_NEUTRAL.npz"
    np.savez(path, **_official_arrays(data, tmp_path))
    blob = path.read_bytes()
    if damage == "empty":
        path.write_bytes(b"")
    elif damage == "cut":
        path.write_bytes(blob[: len(blob) // 2])
    elif damage == "crc":  # a byte inside the first member's stored data
        middle = blob.index(b"NUMPY") + 200
        path.write_bytes(blob[:middle] + bytes([blob[middle] ^ 0xFF]) + blob[middle + 1 :])
    else:
        with open(path, "wb") as fh:
            np.save(fh, np.zeros(3))
    for load in (load_smpl_file, lambda p: load_body_model(str(p))):
        with pytest.raises(ValueError, match=r"SMPL_NEUTRAL\.npz: (not a readable|a single \.npy)"):
            load(path)


def test_weights_drifting_within_the_check_are_renormalised(tmp_path, data):
    """Rows summing to 1 + 5e-5 pass the check, and the translation goes through the skinning
    blend: a body 50 m out moved by 2 mm against smplx's (translation added after)."""
    import torch

    from gst.body import BodyModel

    arrays = _official_arrays(data, tmp_path)
    arrays["weights"] = np.asarray(arrays["weights"]) * (1 + 5e-5)
    np.savez(tmp_path / "drift.npz", **arrays)
    body = BodyModel(load_smpl_file(tmp_path / "drift.npz"), dtype=torch.float64)
    np.testing.assert_allclose(body.weights.sum(1).numpy(), 1.0, atol=1e-12)
    g = torch.Generator().manual_seed(0)
    pose = torch.randn(1, 23, 3, generator=g, dtype=torch.float64) * 0.3
    betas = torch.zeros(1, body.num_betas, dtype=torch.float64)
    far = torch.tensor([[40.0, 0.0, 30.0]], dtype=torch.float64)
    from gst.body import axis_angle_to_matrix as aa

    R = aa(pose)
    at_origin = body(betas, R, aa(torch.zeros(1, 3, dtype=torch.float64)), None).vertices
    moved = body(betas, R, aa(torch.zeros(1, 3, dtype=torch.float64)), far).vertices
    assert (moved - at_origin - far[:, None]).abs().max() < 1e-9

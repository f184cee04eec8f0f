"""Read official SMPL model files (.pkl or .npz) into :class:`BodyModelData`, safely.

SMPL is licensed (https://smpl.is.tue.mpg.de): we can neither ship nor download it. Users who have
it point at their copy (a file or a folder holding ``SMPL_NEUTRAL.pkl`` and friends), or drop it
into ``$GST_BODY_DIR`` or ``~/.cache/gst-capture/body/``.

The official .pkl files are Python 2 pickles holding chumpy arrays and scipy sparse matrices.
We never import chumpy and never let the pickle call arbitrary code: a restricted unpickler
resolves only numpy's array-reconstruction helpers and maps every chumpy and scipy.sparse class
to inert placeholders, which are turned into numpy / scipy arrays after loading. Anything else
in the file (a class or function from another module) is refused with an error naming it.
"""

from __future__ import annotations

import copyreg
import io
import os
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse

from gst.body.model import NPZ_MEMBER_ERRORS, WEIGHT_SUM_TOLERANCE, BodyModelData, open_npz
from gst.body.skeleton import (
    NUM_JOINTS,
    PART_NAMES,
    SMPL_JOINT_NAMES,
    SMPL_PARENTS,
    parts_from_weights,
)

__all__ = ["load_smpl_file", "default_body_dir", "SMPL_LICENCE_NOTE", "UnsafePickleError"]

SMPL_LICENCE_NOTE = (
    "SMPL is licensed by the Max Planck Institute for Intelligent Systems and cannot be shipped "
    "or downloaded by this project: register at https://smpl.is.tue.mpg.de, download the model "
    "yourself, and accept its licence (non-commercial research unless licensed otherwise)."
)
_GENDERS = ("neutral", "male", "female")
# File names used by the official releases, most specific first.
_OFFICIAL_NAMES = {
    "neutral": [
        "SMPL_NEUTRAL",
        "basicModel_neutral_lbs_10_207_0_v1.0.0",
        "basicmodel_neutral_lbs_10_207_0_v1.1.0",
    ],
    "male": ["SMPL_MALE", "basicmodel_m_lbs_10_207_0_v1.0.0", "basicmodel_m_lbs_10_207_0_v1.1.0"],
    "female": [
        "SMPL_FEMALE",
        "basicModel_f_lbs_10_207_0_v1.0.0",
        "basicmodel_f_lbs_10_207_0_v1.1.0",
    ],
}


class UnsafePickleError(pickle.UnpicklingError):
    """The pickle asked for a class or function outside the allowed set."""


def default_body_dir() -> Path:
    """``$GST_BODY_DIR`` if set, else ``~/.cache/gst-capture/body``."""
    env = os.environ.get("GST_BODY_DIR")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "gst-capture" / "body"


# --------------------------------------------------------------------------- restricted unpickler
class _Placeholder:
    """An inert stand-in for a pickled object: records its class name and pickled state."""

    kind = "object"
    qualname = "?"
    args: tuple = ()
    state: Any = None  # NEWOBJ creates instances without calling __init__

    def __init__(self, *args: Any) -> None:
        self.args = args

    def __setstate__(self, state: Any) -> None:
        self.state = state


def _placeholder_class(kind: str, module: str, name: str) -> type:
    return type(
        f"{kind}:{module}.{name}", (_Placeholder,), {"kind": kind, "qualname": f"{module}.{name}"}
    )


def _numpy_global(module: str, name: str):
    # numpy >= 2 keeps the array reconstruction helpers in numpy._core; old pickles say numpy.core.
    if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name in (
        "_reconstruct",
        "scalar",
    ):
        import numpy._core.multiarray as multiarray

        return getattr(multiarray, name)
    if module in ("numpy.core.numeric", "numpy._core.numeric") and name == "_frombuffer":
        import numpy._core.numeric as numeric

        return numeric._frombuffer
    if module == "numpy" and name in ("ndarray", "dtype"):
        return getattr(np, name)
    if module == "numpy.dtypes" and name.endswith("DType"):
        return getattr(np.dtypes, name, None)
    return None


def _latin1_encode(text: str, encoding: str = "utf-8") -> bytes:
    """Python 3 pickles of bytes (protocol < 3) call ``_codecs.encode(text, 'latin1')``; allow
    exactly that and nothing else of the codec registry."""
    if encoding not in ("latin1", "latin-1") or not isinstance(text, str):
        raise UnsafePickleError(f"refusing _codecs.encode with encoding {encoding!r}")
    return text.encode("latin1")


_BUILTINS = {
    "object": object,
    "set": set,
    "frozenset": frozenset,
    "list": list,
    "dict": dict,
    "tuple": tuple,
    "complex": complex,
}


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        if module in ("copy_reg", "copyreg") and name == "_reconstructor":
            return copyreg._reconstructor
        if module == "_codecs" and name == "encode":
            return _latin1_encode
        if module in ("__builtin__", "builtins") and name in _BUILTINS:
            return _BUILTINS[name]
        found = _numpy_global(module, name)
        if found is not None:
            return found
        if module == "chumpy" or module.startswith("chumpy."):
            return _placeholder_class("chumpy", module, name)
        if module.startswith("scipy.sparse") and name.endswith(("_matrix", "_array")):
            return _placeholder_class("sparse", module, name)
        raise UnsafePickleError(
            f"refusing to load {module}.{name} from a pickle (only numpy arrays, "
            "chumpy arrays and scipy sparse matrices are allowed)"
        )


def _convert(obj: Any, where: str) -> Any:
    """Turn placeholders into numpy / scipy objects, recursively through containers."""
    if isinstance(obj, _Placeholder):
        if obj.kind == "chumpy":
            state = obj.state if isinstance(obj.state, dict) else {}
            if "x" not in state:
                raise ValueError(
                    f"{where}: chumpy object {obj.qualname} is not a plain array (it is a "
                    "derived expression); convert the file to .npz with numpy arrays first"
                )
            return np.asarray(_convert(state["x"], where))
        return _sparse_from_state(obj, where)
    if isinstance(obj, dict):
        return {k: _convert(v, f"{where}[{k!r}]") for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_convert(v, where) for v in obj)
    return obj


def _sparse_from_state(obj: _Placeholder, where: str):
    state = obj.state if isinstance(obj.state, dict) else {}
    shape = state.get("_shape", state.get("shape"))
    fmt = obj.qualname.rsplit(".", 1)[-1].split("_")[0]
    try:
        if fmt in ("csc", "csr"):
            cls = scipy.sparse.csc_matrix if fmt == "csc" else scipy.sparse.csr_matrix
            return cls(
                (
                    np.asarray(state["data"]),
                    np.asarray(state["indices"]),
                    np.asarray(state["indptr"]),
                ),
                shape=tuple(shape),
            )
        if fmt == "coo":
            # newer scipy keeps the indices as `coords`, older versions as `row` and `col`
            row, col = state["coords"] if "coords" in state else (state["row"], state["col"])
            return scipy.sparse.coo_matrix(
                (np.asarray(state["data"]), (np.asarray(row), np.asarray(col))),
                shape=tuple(shape),
            ).tocsr()
    except (KeyError, TypeError) as err:
        raise ValueError(f"{where}: unreadable sparse matrix {obj.qualname} ({err})") from err
    raise ValueError(f"{where}: unsupported sparse matrix type {obj.qualname}")


def safe_load_pickle(path: str | Path) -> Any:
    """Unpickle ``path`` allowing only numpy arrays, chumpy arrays (as numpy) and scipy sparse
    matrices. Python 2 pickles are read with latin1 strings, as numpy requires."""
    path = Path(path)
    raw = path.read_bytes()
    try:
        obj = _RestrictedUnpickler(io.BytesIO(raw), encoding="latin1").load()
    except UnsafePickleError as err:
        raise UnsafePickleError(f"{path}: {err}") from None
    except Exception as err:  # noqa: BLE001 - any parse failure is reported with the file name
        raise ValueError(f"{path}: not a readable pickle ({type(err).__name__}: {err})") from err
    return _convert(obj, str(path))


# --------------------------------------------------------------------------- SMPL layout
def _find_file(path: str | Path | None, gender: str | None) -> Path:
    gender = (gender or "neutral").lower()
    if gender not in _GENDERS:
        raise ValueError(f"gender must be one of {_GENDERS}, got {gender!r}")
    if path is not None and Path(path).expanduser().is_file():
        return Path(path).expanduser()
    folder = Path(path).expanduser() if path is not None else default_body_dir()
    tried = []
    if path is None or folder.is_dir():
        for stem in _OFFICIAL_NAMES[gender]:
            for ext in (".pkl", ".npz"):
                for candidate in (folder / (stem + ext), folder / "smpl" / (stem + ext)):
                    tried.append(candidate)
                    if candidate.is_file():
                        return candidate
    else:
        tried.append(folder)
    raise FileNotFoundError(
        f"No SMPL model file found (looked for {', '.join(str(p) for p in tried[:4])}"
        f"{' ...' if len(tried) > 4 else ''}). Put SMPL_{gender.upper()}.pkl (or .npz) into "
        f"{default_body_dir()} (or set $GST_BODY_DIR), or pass its path. {SMPL_LICENCE_NOTE} "
        "Without SMPL, use the open default body: load_body_model('anny')."
    )


def find_smpl_file(path: str | Path | None, gender: str | None) -> Path:
    """The SMPL file that `path` (a file, a folder, or None for the default folder) and
    `gender` name; FileNotFoundError, naming where it looked, when there is none."""
    return _find_file(path, gender)


def _gender_of(file: Path, asked: str | None) -> str | None:
    """The gender a model file is, from its name as SMPL ships it (SMPL_MALE, basicModel_m_...,
    basicmodel_neutral_...); `asked` where the name says none. A path given to SMPL_MALE.pkl was
    called "SMPL (neutral)", and gender='female' with it "SMPL (female)"."""
    stem = file.stem.lower()
    found = next(
        (
            g
            for g, marks in (
                ("neutral", ("_neutral", "neutral_")),
                ("female", ("_female", "_f_", "female_")),
                ("male", ("_male", "_m_")),
            )
            if any(m in f"_{stem}_" for m in marks)
        ),
        None,
    )
    if found is not None and asked is not None and asked.lower() != found:
        raise ValueError(
            f"{file}: gender={asked!r} was asked, but the file is the {found} model by its name; "
            "give a folder (the gender picks the file in it) or the file alone"
        )
    return found or (asked.lower() if asked else None)


# the arrays an SMPL file must hold (`load_smpl_file`; posedirs is optional)
SMPL_KEYS = ("v_template", "shapedirs", "weights", "f", "kintree_table", "J_regressor")


def _read_raw(path: Path) -> dict[str, Any]:
    suffix = path.suffix.lower()  # SMPL_NEUTRAL.PKL was "unknown file type"
    if suffix == ".pkl":
        raw = safe_load_pickle(path)
        if not isinstance(raw, dict):
            raise ValueError(f"{path}: expected a dict of SMPL arrays, got {type(raw).__name__}")
        return raw
    if suffix == ".npz":
        # Entries that hold pickled objects (SMPL-X's npz has some beside its arrays) are left
        # out: the arrays then say what the file is ("only the 24-joint SMPL body" for SMPL-X,
        # where refusing the file for its objects sent the user to re-save it for nothing).
        raw, pickled = {}, []
        try:
            with open_npz(path, ".npz SMPL file") as z:
                for k in z.files:
                    try:
                        raw[k] = z[k]
                    except ValueError:
                        pickled.append(k)
        except NPZ_MEMBER_ERRORS as exc:  # a damaged member (bad CRC, cut stream)
            raise ValueError(f"{path}: not a readable .npz SMPL file ({exc})") from exc
        needed = [k for k in SMPL_KEYS if k in pickled]
        if needed:
            raise ValueError(
                f"{path}: its {needed} hold pickled objects, which we do not load from .npz; "
                "use the official .pkl or save plain arrays"
            )
        return raw
    raise ValueError(f"{path}: unknown SMPL file type {path.suffix!r}, expected .pkl or .npz")


def _required(raw: dict[str, Any], key: str, path: Path) -> Any:
    if key not in raw:
        raise ValueError(f"{path}: missing key {key!r} of the SMPL layout (has {sorted(raw)})")
    return raw[key]


def _numbers(value: Any, key: str, path: Path, whole: bool = False) -> np.ndarray:
    """`value` as a float64 array (`whole`: an int64 one, every value a whole number: face and
    joint indices), or a ValueError naming the file and key (a bare "could not convert string to
    float" before; fractional face indices were cut without a word)."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: {key} is not numeric ({exc})") from exc
    if not whole:
        return arr
    if not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr)):
        raise ValueError(f"{path}: {key} must hold whole numbers (indices)")
    return arr.astype(np.int64)


def load_smpl_file(path: str | Path | None = None, gender: str | None = None) -> BodyModelData:
    """Load an official SMPL model (.pkl with chumpy inside, or .npz) as :class:`BodyModelData`.

    Args:
        path: the model file, or a folder holding ``SMPL_{NEUTRAL,MALE,FEMALE}.pkl|npz`` (or the
            original ``basicModel_*`` names); None searches :func:`default_body_dir`.
        gender: "neutral" (default), "male" or "female": which file of a folder; with a file, its
            name says its gender (``SMPL_MALE``), and a gender that contradicts it is an error.
    Raises:
        FileNotFoundError saying where to put the file (and that SMPL is licensed);
        ValueError / UnsafePickleError naming the file and key when its content is not SMPL.
    """
    file = _find_file(path, gender)
    raw = _read_raw(file)
    v_template = _numbers(_required(raw, "v_template", file), "v_template", file)
    shapedirs = _numbers(_required(raw, "shapedirs", file), "shapedirs", file)
    weights = _numbers(_required(raw, "weights", file), "weights", file)
    faces = _numbers(_required(raw, "f", file), "f", file, whole=True)
    kintree = _numbers(_required(raw, "kintree_table", file), "kintree_table", file, whole=True)
    reg = _required(raw, "J_regressor", file)
    reg = (
        reg.astype(np.float64).tocsr()
        if scipy.sparse.issparse(reg)
        else np.asarray(reg, dtype=np.float64)
    )

    if v_template.ndim != 2 or v_template.shape[1] != 3:
        raise ValueError(f"{file}: v_template has shape {v_template.shape}, expected (V, 3)")
    V = v_template.shape[0]
    if kintree.ndim != 2 or kintree.shape[0] != 2 or kintree.shape[1] != NUM_JOINTS:
        raise ValueError(
            f"{file}: kintree_table has shape {kintree.shape}, expected (2, {NUM_JOINTS}); "
            "only the 24-joint SMPL body is supported"
        )
    if weights.shape != (V, NUM_JOINTS):
        raise ValueError(
            f"{file}: weights has shape {weights.shape}, expected ({V}, {NUM_JOINTS}) "
            "(one row of skinning weights per vertex)"
        )
    if not np.array_equal(kintree[1], np.arange(NUM_JOINTS)):
        raise ValueError(
            f"{file}: kintree_table's second row (the joint ids) is {kintree[1].tolist()}, "
            f"expected 0..{NUM_JOINTS - 1} in order (SMPL's joint order)"
        )
    parents = kintree[0].copy()
    parents[0] = -1  # stored as uint32 max in the official files
    if parents.tolist() != list(SMPL_PARENTS):  # other trees were loaded under SMPL's names
        differ = [
            f"{SMPL_JOINT_NAMES[j]} under {int(p)} (SMPL: {SMPL_PARENTS[j]})"
            for j, p in enumerate(parents)
            if int(p) != SMPL_PARENTS[j]
        ]
        raise ValueError(
            f"{file}: kintree_table's first row (the parents) is not SMPL's tree: "
            f"{', '.join(differ)}; only the 24-joint SMPL body is supported"
        )
    if shapedirs.ndim == 2:  # some exports flatten (V*3, B)
        if shapedirs.shape[0] != 3 * V:
            raise ValueError(
                f"{file}: shapedirs has shape {shapedirs.shape}, expected ({V}, 3, B) or its "
                f"flattened ({3 * V}, B)"
            )
        shapedirs = shapedirs.reshape(V, 3, -1)
    if shapedirs.ndim == 3 and shapedirs.shape[2] == 0:
        raise ValueError(f"{file}: shapedirs has no shape components (shape {shapedirs.shape})")
    posedirs = raw.get("posedirs")
    if posedirs is not None:
        posedirs = _numbers(posedirs, "posedirs", file)
        n_pose = 9 * (NUM_JOINTS - 1)
        if posedirs.shape != (V, 3, n_pose):
            raise ValueError(
                f"{file}: posedirs has shape {posedirs.shape}, expected ({V}, 3, {n_pose})"
            )
        posedirs = posedirs.reshape(-1, n_pose).T.copy()  # smplx's (P, V*3) layout
    sums = weights.sum(axis=1, keepdims=True)
    if np.all(np.abs(sums - 1.0) <= WEIGHT_SUM_TOLERANCE):
        # the drift the check tolerates, taken out: a translation goes through the blend, so
        # rows off by 5e-5 moved a body 40 m from the origin by 2 mm (smplx adds it after)
        weights = weights / sums
    gender_name = _gender_of(file, gender)
    data = BodyModelData(
        v_template=v_template,
        shapedirs=shapedirs,
        J_regressor=reg,
        weights=weights,
        parents=parents,
        faces=faces,
        joint_names=SMPL_JOINT_NAMES,
        part_labels=parts_from_weights(weights, SMPL_JOINT_NAMES),
        part_names=PART_NAMES,
        posedirs=posedirs,
        name=(
            f"SMPL ({file.stem})"
            if gender_name is None
            else f"SMPL ({gender_name})"
            if file.stem.startswith("SMPL_")
            else f"SMPL ({gender_name}: {file.stem})"
        ),
        source=str(file),
        licence=SMPL_LICENCE_NOTE,
    )
    try:
        return data.validate()
    except ValueError as err:
        raise ValueError(f"{file}: {err}") from err

"""Human3.6M `cameras.h5` (the file of the 3d-pose-baseline project), and H36M's lens model.

Layout: `subject<S>/camera<C>/{R, T, f, c, k, p, Name}`, C = 1..4. `R` is stored transposed
(the world-to-camera rotation is `R.T`); `T` is the camera centre in world millimetres, so
X_cam = R (P - T). `f` = (fx, fy) and `c` = (cx, cy) in pixels; `Name` holds the camera id as
character codes. The H36M world is z-up, millimetres; we keep its axes and convert to metres.

H36M's distortion (3 radial k, 2 tangential p), from its projection code, with x, y the
normalised coordinates and r2 = x^2 + y^2:

    radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3;   tan = p1 y + p2 x
    x_d = x (radial + tan) + p2 r2;   y_d = y (radial + tan) + p1 r2

This is not OpenCV's tangential model, but it is exactly OpenCV's 12-term model (rational and
thin prism) with k1..k3 = k, k4..k6 = 0, OpenCV p1 = p1/2, p2 = p2/2, s1 = p2/2, s2 = 0,
s3 = p1/2, s4 = 0. Import is therefore exact. Export is exact for cameras whose distortion has
that structure (every camera read from H36M, and every purely radial one); any other camera is
refused, or, with `approximate_distortion=True`, fitted by linear least squares over the image
(the worst residual in pixels is reported in a warning).

The file has no image sizes. Known H36M camera ids get theirs (1000x1002 or 1000x1000); others
need `image_size=(w, h)`, unless the file was written by us (we store width/height attributes).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import h5py
import numpy as np

from calibration.camera import Camera, Rig
from calibration.formats._common import (
    RigFormatError,
    as_float_array,
    atomic_write,
    make_camera,
    make_rig,
    pixel_count,
)

MM_PER_M = 1000.0
# Image sizes (width, height) of the four H36M video cameras, from the dataset's metadata.
KNOWN_SIZES = {
    "54138969": (1000, 1002),
    "55011271": (1000, 1000),
    "58860488": (1000, 1000),
    "60457274": (1000, 1002),
}


# -- H36M lens model <-> OpenCV -------------------------------------------------------------------
def h36m_to_opencv(k, p) -> np.ndarray:
    """OpenCV 12-term distortion equal to H36M's (k1, k2, k3), (p1, p2)."""
    k = np.asarray(k, dtype=np.float64).ravel()
    p = np.asarray(p, dtype=np.float64).ravel()
    if k.size != 3 or p.size != 2:
        raise RigFormatError(
            f"H36M distortion needs 3 radial and 2 tangential terms, got {k.size} and {p.size}"
        )
    return np.array([k[0], k[1], p[0] / 2, p[1] / 2, k[2], 0, 0, 0, p[1] / 2, 0, p[0] / 2, 0])


def opencv_to_h36m(
    camera: Camera, approximate: bool = False, tol: float = 1e-12
) -> tuple[np.ndarray, np.ndarray, float]:
    """(k, p, worst error px) of H36M's model for a camera's OpenCV distortion.

    Exact (error 0) when the distortion has H36M's structure; otherwise a least-squares fit if
    `approximate`, else RigFormatError."""
    d = np.zeros(14)
    d[: camera.dist.size] = camera.dist
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d[:12]
    exact = (
        max(abs(k4), abs(k5), abs(k6), abs(s2), abs(s4), *np.abs(d[12:])) <= tol
        and abs(s1 - p2) <= tol
        and abs(s3 - p1) <= tol
    )
    if exact:
        return np.array([k1, k2, k3]), np.array([2 * p1, 2 * p2]), 0.0
    if not approximate:
        raise RigFormatError(
            f"camera '{camera.name}': its distortion {camera.dist.tolist()} has no exact "
            "equivalent in H36M's model (it needs s1 = p2, s3 = p1 and no other rational/prism "
            "terms); pass approximate_distortion=True to fit one"
        )
    return _fit_h36m(camera)


def _fit_h36m(camera: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    # Normalised undistorted coordinates covering the image, and their OpenCV-distorted images.
    u, v = np.meshgrid(np.linspace(0, camera.width - 1, 41), np.linspace(0, camera.height - 1, 41))
    xy = camera.undistort_points(np.stack([u.ravel(), v.ravel()], axis=1))
    x, y = xy[:, 0], xy[:, 1]
    pts = np.stack([x, y, np.ones_like(x)], axis=1)
    target = (camera.project(pts @ camera.R + camera.center) - camera.K[:2, 2]) / [
        camera.fx,
        camera.fy,
    ]
    r2 = x * x + y * y
    # x_d - x = x (k1 r2 + k2 r4 + k3 r6) + p1 x y + p2 (x^2 + r2); likewise for y.
    Ax = np.stack([x * r2, x * r2**2, x * r2**3, x * y, x * x + r2], axis=1)
    Ay = np.stack([y * r2, y * r2**2, y * r2**3, y * y + r2, x * y], axis=1)
    A = np.concatenate([Ax, Ay])
    b = np.concatenate([target[:, 0] - x, target[:, 1] - y])
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    resid = (A @ sol - b).reshape(2, -1).T * [camera.fx, camera.fy]
    return sol[:3], sol[3:], float(np.max(np.linalg.norm(resid, axis=1)))


# -- file I/O -----------------------------------------------------------------------------------
def subject_number(subject) -> int:
    """H36M subject `subject` given as a number or 'S<number>'."""
    s = str(subject)
    s = s[1:] if s[:1] in "sS" else s
    if not s.isdigit():
        raise RigFormatError(f"H36M subject must be a number or 'S<number>', got {subject!r}")
    return int(s)


def _subject_key(subject) -> str:
    return f"subject{subject_number(subject)}"


def image_size_of(
    path: Path, where: str, name: str, stored, image_size: tuple[int, int] | None
) -> tuple[int, int]:
    """A camera's (width, height): `stored` with it (as we write it), else the caller's
    `image_size`, else its known H36M size (a caller's size for a known camera was ignored: the
    videos of a user who resized them are not H36M's)."""
    if stored is not None:  # 1000.9 was 1000, true was 1, "abc" a bare int() error
        return (
            pixel_count(stored[0], path, f"{where} width"),
            pixel_count(stored[1], path, f"{where} height"),
        )
    if image_size is not None:
        try:  # 1000 was a bare TypeError, (1000,) an IndexError, an image's (h, w, 3) taken
            w, h = image_size
        except (TypeError, ValueError):
            raise RigFormatError(
                f"{path}: image_size is {image_size!r}, expected two numbers (width, height)"
            ) from None
        return tuple(pixel_count(v, path, f"image_size {(w, h)}") for v in (w, h))
    if name in KNOWN_SIZES:
        return KNOWN_SIZES[name]
    raise RigFormatError(
        f"{path}: {where} has no known image size; pass image_size=(width, height)"
    )


def _decode_name(raw) -> str:
    arr = np.asarray(raw)
    if arr.dtype.kind in "SO":
        return b"".join(np.atleast_1d(arr).astype(bytes)).decode()
    if arr.dtype.kind == "U":
        return "".join(np.atleast_1d(arr))
    codes = [int(c) for c in arr.ravel()]
    if all(0 <= c < 256 for c in codes):  # bytes, as we write them: UTF-8 (ASCII in H36M's own)
        try:
            return bytes(codes).decode("utf-8")
        except UnicodeDecodeError:
            pass
    return "".join(chr(c) for c in codes)  # character codes


def read(path: str | Path, subject=None, image_size: tuple[int, int] | None = None) -> Rig:
    """The cameras of one subject (`subject=1` or 'S1'; optional when the file holds one)."""
    path = Path(path)
    try:
        h5 = h5py.File(path, "r")
    except OSError as exc:
        raise RigFormatError(f"{path}: not a readable HDF5 file ({exc})") from exc
    with h5:
        subjects = sorted(k for k in h5.keys() if k.startswith("subject"))
        if subject is None:
            if len(subjects) != 1:
                raise RigFormatError(
                    f"{path}: holds subjects {subjects}; choose one with subject=..."
                )
            key = subjects[0]
        else:
            key = _subject_key(subject)
            if key not in h5:
                raise RigFormatError(f"{path}: no group '{key}' (subjects: {subjects})")
        group = h5[key]
        cam_keys = [k for k in group.keys() if k.startswith("camera")]
        bad = [k for k in cam_keys if not k[6:].isdigit()]
        if bad:
            raise RigFormatError(
                f"{path}: {key} has camera groups {bad}; expected camera<N> (camera1, camera2, ...)"
            )
        cameras = []
        for ck in sorted(cam_keys, key=lambda s: int(s[6:])):
            g = group[ck]
            missing = [d for d in ("R", "T", "f", "c", "k", "p") if d not in g]
            if missing:
                raise RigFormatError(f"{path}: {key}/{ck} lacks datasets {missing}")

            def dataset(name: str, shape: tuple[int, ...], g=g, ck=ck) -> np.ndarray:
                return as_float_array(g[name][()], shape, path, f"{key}/{ck} dataset {name}")

            R = dataset("R", (3, 3)).T  # stored transposed
            T = dataset("T", (3,)) / MM_PER_M
            f, c = dataset("f", (2,)), dataset("c", (2,))
            name = _decode_name(g["Name"][()]) if "Name" in g else ck
            has_size = "width" in g.attrs and "height" in g.attrs
            stored = (g.attrs["width"], g.attrs["height"]) if has_size else None
            size = image_size_of(path, f"{key}/{ck} (camera '{name}')", name, stored, image_size)
            cameras.append(
                make_camera(
                    path,
                    name,
                    K=[[f[0], 0, c[0]], [0, f[1], c[1]], [0, 0, 1]],
                    dist=h36m_to_opencv(dataset("k", (3,)), dataset("p", (2,))),
                    R=R,
                    t=-R @ T,
                    width=size[0],
                    height=size[1],
                    meta={"source": "h36m", "subject": key},
                )
            )
    return make_rig(path, cameras, up=(0.0, 0.0, 1.0), meta={"source": "h36m", "subject": key})


def write(rig: Rig, path: str | Path, subject=1, approximate_distortion: bool = False) -> None:
    """One subject's cameras as `subject<S>/camera<C>` (C = 1.. in rig order)."""
    key = _subject_key(subject)
    entries = []
    for c in rig:
        if c.skew:
            raise RigFormatError(f"camera '{c.name}': H36M has no skew, K[0, 1] = {c.skew}")
        k, p, err = opencv_to_h36m(c, approximate_distortion)
        if err > 0:
            warnings.warn(
                f"camera '{c.name}': H36M distortion fitted, worst error {err:.3g} px", stacklevel=2
            )
        entries.append((c, k, p))

    def _write(tmp: Path) -> None:
        with h5py.File(tmp, "w") as h5:
            for i, (c, k, p) in enumerate(entries):
                g = h5.create_group(f"{key}/camera{i + 1}")
                g["R"] = c.R.T
                g["T"] = (c.center * MM_PER_M).reshape(3, 1)
                g["f"] = np.array([[c.fx], [c.fy]])
                g["c"] = np.array([[c.cx], [c.cy]])
                g["k"] = k.reshape(3, 1)
                g["p"] = p.reshape(2, 1)
                g["Name"] = np.frombuffer(c.name.encode(), dtype=np.uint8)
                g.attrs["width"], g.attrs["height"] = c.width, c.height

    atomic_write(path, _write)


def sniff(path: Path, text: str | None) -> bool:
    return path.suffix.lower() in (".h5", ".hdf5")

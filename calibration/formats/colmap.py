"""COLMAP sparse models (a folder of cameras/images/points3D .bin or .txt), through pycolmap.

Reading: every registered image becomes one rig camera named after the image (its pose
`cam_from_world` is world to camera, OpenCV axes, as ours), with the intrinsics of its COLMAP
camera. COLMAP puts the centre of the top-left pixel at (0.5, 0.5), we at (0, 0): principal
points move by -0.5. A COLMAP model has no units and no up axis: pass `metres_per_unit` and
`up`. Supported camera models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV,
FULL_OPENCV (the others are fisheye or exotic and refused).

Writing: one COLMAP camera per rig camera (PINHOLE, OPENCV or FULL_OPENCV, the smallest that
holds its distortion) and one image named after the camera, with a trivial rig and frame each;
no 3D points. Skew and thin-prism terms have no COLMAP equivalent and are refused.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calibration.camera import Rig
from calibration.formats._common import RigFormatError, make_camera, make_rig

if TYPE_CHECKING:
    import pycolmap  # imported where used: 0.2 s that readers of other formats need not pay


def _model_dir(path: Path) -> Path:
    for cand in (path, path / "sparse" / "0", path / "0", path / "sparse"):
        if (cand / "cameras.bin").exists() or (cand / "cameras.txt").exists():
            return cand
    raise RigFormatError(
        f"{path}: no COLMAP model (cameras.bin or cameras.txt) here or in sparse/0"
    )


def _intrinsics(cam: pycolmap.Camera, path: Path, name: str) -> tuple[list, np.ndarray]:
    model = cam.model_name
    p = np.asarray(cam.params, dtype=np.float64)
    if model == "SIMPLE_PINHOLE":
        f, cx, cy, dist = p[0], p[1], p[2], np.zeros(5)
        fx = fy = f
    elif model == "PINHOLE":
        fx, fy, cx, cy, dist = p[0], p[1], p[2], p[3], np.zeros(5)
    elif model == "SIMPLE_RADIAL":
        fx = fy = p[0]
        cx, cy, dist = p[1], p[2], np.array([p[3], 0, 0, 0, 0])
    elif model == "RADIAL":
        fx = fy = p[0]
        cx, cy, dist = p[1], p[2], np.array([p[3], p[4], 0, 0, 0])
    elif model == "OPENCV":
        fx, fy, cx, cy = p[:4]
        dist = np.array([p[4], p[5], p[6], p[7], 0.0])
    elif model == "FULL_OPENCV":
        fx, fy, cx, cy = p[:4]
        d = p[4:12]
        dist = d[:5].copy() if not np.any(d[5:]) else d.copy()
    else:
        raise RigFormatError(
            f"{path}: image '{name}' uses COLMAP camera model {model}, which has no "
            "OpenCV pinhole equivalent here (supported: SIMPLE_PINHOLE, PINHOLE, "
            "SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV)"
        )
    return [[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]], dist


def _check_unit(metres_per_unit: float) -> float:
    """The model's length unit in metres: finite and positive (0 put every camera at the
    origin, a negative one mirrored the world, and the writer wrote NaN translations)."""
    try:
        unit = float(metres_per_unit)
    except (TypeError, ValueError):
        unit = float("nan")
    if not (np.isfinite(unit) and unit > 0):
        raise RigFormatError(
            f"COLMAP metres_per_unit must be a finite number > 0, got {metres_per_unit!r}"
        )
    return unit


def read(path: str | Path, metres_per_unit: float = 1.0, up=(0.0, 0.0, 1.0)) -> Rig:
    path = Path(path)
    metres_per_unit = _check_unit(metres_per_unit)
    import pycolmap

    model_dir = _model_dir(path)
    rec = pycolmap.Reconstruction()
    try:
        rec.read(model_dir)
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on bad files
        raise RigFormatError(f"{model_dir}: cannot read COLMAP model ({exc})") from exc
    cameras = []
    for image_id in sorted(rec.reg_image_ids()):
        img = rec.image(image_id)
        K, dist = _intrinsics(img.camera, path, img.name)
        T = img.cam_from_world().matrix()
        cameras.append(
            make_camera(
                path,
                img.name,
                K=K,
                dist=dist,
                R=T[:, :3],
                t=T[:, 3] * metres_per_unit,
                width=img.camera.width,
                height=img.camera.height,
                meta={
                    "source": "colmap",
                    "image_id": int(image_id),
                    "camera_model": img.camera.model_name,
                },
            )
        )
    return make_rig(path, cameras, up=_up_option(up, path), meta={"source": "colmap"})


def _up_option(up, path: Path) -> tuple[float, ...]:
    """The `up` read option as numbers (`up: z` was a bare "could not convert string to
    float"); make_rig checks that it is a unit 3-vector."""
    try:
        if isinstance(up, str):
            raise ValueError
        return tuple(float(v) for v in up)
    except (TypeError, ValueError):
        raise RigFormatError(
            f"{path}: the COLMAP read option up is {up!r}, expected the world's up axis as "
            "three numbers (e.g. [0, 0, 1])"
        ) from None


def _colmap_camera(cam, camera_id: int) -> pycolmap.Camera:
    import pycolmap

    if "\x00" in cam.name:  # the binary model ends a name there: read back cut, or unreadable
        raise RigFormatError(
            f"camera {cam.name!r}: a NUL character in its name, which a COLMAP image name "
            "cannot hold"
        )
    if cam.skew:
        raise RigFormatError(
            f"camera '{cam.name}': COLMAP models have no skew (K[0, 1] = {cam.skew})"
        )
    d = np.zeros(14)
    d[: cam.dist.size] = cam.dist
    if np.any(d[8:]):
        raise RigFormatError(
            f"camera '{cam.name}': thin-prism/tilt distortion terms "
            f"{d[8 : cam.dist.size].tolist()} have no COLMAP equivalent"
        )
    pp = [cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5]
    if not np.any(d):
        model, params = "PINHOLE", pp
    elif not np.any(d[4:]):
        model, params = "OPENCV", pp + d[:4].tolist()
    else:
        model, params = "FULL_OPENCV", pp + d[:8].tolist()
    return pycolmap.Camera(
        model=model, width=cam.width, height=cam.height, params=params, camera_id=camera_id
    )


def write(rig: Rig, path: str | Path, metres_per_unit: float = 1.0) -> None:
    """A binary COLMAP model in the folder `path` (model files replaced one by one, atomically;
    the text copies of those files, an older model that a reader would take instead, are
    removed; anything else in the folder is kept)."""
    import pycolmap

    metres_per_unit = _check_unit(metres_per_unit)
    rec = pycolmap.Reconstruction()
    for i, cam in enumerate(rig):
        rec.add_camera_with_trivial_rig(_colmap_camera(cam, i + 1))
        img = pycolmap.Image(name=cam.name, camera_id=i + 1, image_id=i + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(cam.R), cam.t / metres_per_unit)
        rec.add_image_with_trivial_frame(img, pose)

    path = Path(path)
    if path.exists() and not path.is_dir():
        raise RigFormatError(f"{path}: exists and is not a folder; a COLMAP model is a folder")
    path.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=path, prefix=".colmap-") as tmp:
        rec.write(tmp)
        # Each model file replaces its old version atomically; other files in the folder
        # (images, a database) are left alone.
        written = sorted(Path(tmp).iterdir())
        for f in written:
            os.replace(f, path / f.name)
    # an older model in the other encoding (cameras.txt beside the new cameras.bin) would be
    # read by other tools, or by a person, as the rig: it held the old poses
    for f in written:
        other = path / (f.stem + (".txt" if f.suffix == ".bin" else ".bin"))
        if f.suffix in (".bin", ".txt") and other.is_file():
            other.unlink()


def sniff(path: Path, text: str | None) -> bool:
    if not path.is_dir():
        return False
    try:
        _model_dir(path)
        return True
    except RigFormatError:
        return False

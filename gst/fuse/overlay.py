"""Overlay videos: the fitted bodies reprojected into every camera's own footage.

Per camera, each frame of its source video gets, per fused person, a sparse cloud of the fitted
mesh's vertices (every `vertex_step`-th, projected with the full lens model), the 24-joint
skeleton, and the 33 virtual markers as rings; frames the fit filled (nobody saw the person)
draw the skeleton grey.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import torch

from gst.body.model import BodyModel
from gst.body.skeleton import SMPL_PARENTS
from gst.fuse.fit import PersonFit

__all__ = ["write_overlays"]

_COLOURS = [(60, 180, 255), (255, 140, 60), (90, 220, 90), (220, 90, 220), (60, 230, 230)]


@torch.no_grad()
def _vertices(body: BodyModel, fit: PersonFit, ids: torch.Tensor) -> np.ndarray:
    T = len(fit.frames)
    out = []
    for a in range(0, T, 64):
        s = slice(a, min(T, a + 64))
        n = s.stop - s.start
        v = body(
            torch.as_tensor(fit.betas[None], dtype=body.dtype).expand(n, -1),
            torch.as_tensor(fit.body_pose[s], dtype=body.dtype),
            torch.as_tensor(fit.global_orient[s], dtype=body.dtype),
            torch.as_tensor(fit.transl[s], dtype=body.dtype),
            vertex_ids=ids,
        ).vertices
        out.append(v.double().numpy())
    return np.concatenate(out) if out else np.zeros((0, len(ids), 3))


def write_overlays(
    fits: list[PersonFit],
    body: BodyModel,
    rig,
    videos: dict[str, Path],
    out_dir: Path,
    vertex_step: int = 12,
    progress=None,
) -> list[Path]:
    """One `<camera>.mp4` per camera in `videos` (camera name -> source video)."""
    from gst.atomic import atomic_write

    out_dir.mkdir(parents=True, exist_ok=True)
    ids = torch.arange(0, body.num_vertices, vertex_step)
    verts = [_vertices(body, f, ids) for f in fits]
    index = [{int(fr): i for i, fr in enumerate(f.frames)} for f in fits]
    written = []
    names = [n for n in rig.names if n in videos]
    if progress is not None:
        names = progress(names, description="overlay videos", total=len(names))
    for name in names:
        cam = rig[name]
        cap = cv2.VideoCapture(str(videos[name]))
        if not cap.isOpened():
            raise OSError(f"overlay: cannot open video {videos[name]} of camera '{name}'")
        fps = cap.get(cv2.CAP_PROP_FPS) or 30.0

        def write(tmp: Path, cap=cap, cam=cam, fps=fps, name=name) -> None:
            # OpenCV picks the container from the extension: encode to a .mp4 name, then move.
            tmp_mp4 = f"{tmp}.mp4"
            writer = None
            try:
                frame_no = 0
                while True:
                    ok, img = cap.read()
                    if not ok:
                        break
                    if writer is None:
                        h, w = img.shape[:2]
                        fourcc = cv2.VideoWriter_fourcc(*"mp4v")
                        writer = cv2.VideoWriter(tmp_mp4, fourcc, fps, (w, h))
                        if not writer.isOpened():
                            raise OSError(f"overlay: cannot write {tmp}")
                    for k, fit in enumerate(fits):
                        i = index[k].get(frame_no)
                        if i is None:
                            continue
                        _draw(img, cam, fit, i, verts[k][i], _COLOURS[k % len(_COLOURS)])
                    cv2.putText(img, f"{frame_no}", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6,
                                (255, 255, 255), 1, cv2.LINE_AA)  # fmt: skip
                    writer.write(img)
                    frame_no += 1
                cap.release()
                if writer is None:
                    raise OSError(f"overlay: video {videos[name]} has no readable frame")
                writer.release()
                os.replace(tmp_mp4, tmp)
            except BaseException:
                # atomic_write removes `tmp` only: the partial encoding beside it stayed in
                # the overlay folder (a failed or interrupted video, one more each time)
                if writer is not None:
                    writer.release()
                Path(tmp_mp4).unlink(missing_ok=True)
                raise

        path = out_dir / f"{name}.mp4"
        atomic_write(path, write)
        written.append(path)
    return written


def _in_field(cam, X: np.ndarray) -> np.ndarray:
    """Points the camera's lens model can place: in front of it and near its image
    (calibration.Camera.in_field; a body beside a wide-angle camera is drawn nowhere rather
    than folded back into the picture by the distortion)."""
    return cam.in_field(X, min_depth=0.05)


def _draw(img, cam, fit: PersonFit, i: int, verts: np.ndarray, colour) -> None:
    h, w = img.shape[:2]
    ok = _in_field(cam, verts)
    if ok.any():
        for u, v in cam.project(verts[ok]).round().astype(int):
            if 0 <= u < w and 0 <= v < h:
                img[v, u] = colour
    joints = fit.joints[i]
    if not _in_field(cam, joints).all():
        return
    uv = cam.project(joints)
    line = colour if fit.observed[i] else (160, 160, 160)
    scale = max(1, round(max(h, w) / 640))
    for j, p in enumerate(SMPL_PARENTS):
        if p >= 0:
            a, b = tuple(uv[j].round().astype(int)), tuple(uv[p].round().astype(int))
            cv2.line(img, a, b, line, scale, cv2.LINE_AA)
    if _in_field(cam, fit.markers[i]).all():
        for u, v in cam.project(fit.markers[i]).round().astype(int):
            cv2.circle(img, (int(u), int(v)), 2 * scale, (255, 255, 255), 1, cv2.LINE_AA)

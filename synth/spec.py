"""Scene specs and presets: everything that defines a synthetic capture, validated and frozen.

`preset(name, **overrides)` gives a preset spec; `synth.scene.render_scene` renders one.
"""

from __future__ import annotations

import copy
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from synth.board import ChArUcoSpec


class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RigSpec(_Spec):
    """`synth.rigs.make_rig`'s arguments, bar the seed (None: the rig kind's default)."""

    kind: Literal["dome", "h36m", "hall"] = "dome"
    n_cameras: int | None = Field(None, ge=1, le=256)
    # even (the mp4v encoder drops an odd last column or row, leaving the video a pixel smaller
    # than the calibration and the truth) and below 8192 (its writer does not open at 8192)
    width: int | None = Field(None, ge=16, le=8190, multiple_of=2)
    height: int | None = Field(None, ge=16, le=8190, multiple_of=2)
    fov_deg: float | None = Field(None, gt=5, lt=150)
    focal_mm: float | None = Field(None, gt=0, allow_inf_nan=False)  # fov 5-150: make_rig
    distortion: Literal["none", "mild", "strong"] | list[float] | None = None
    fps: float | None = Field(None, gt=0, le=1000)

    @model_validator(mode="after")
    def _one_focal(self):
        if self.fov_deg is not None and self.focal_mm is not None:
            raise ValueError("give rig.fov_deg or rig.focal_mm, not both")
        return self


class BoardClipSpec(_Spec):
    squares_x: int = Field(5, ge=3, le=40)
    squares_y: int = Field(4, ge=3, le=40)
    square_size: float = Field(0.3, gt=0, le=1.0)
    marker_size: float = Field(0.24, gt=0, le=1.0)
    dictionary: str = "DICT_4X4_50"
    margin: float = Field(0.06, ge=0, le=0.5)
    n_frames: int = Field(40, ge=0, le=100_000)

    def board(self) -> ChArUcoSpec:
        return ChArUcoSpec(
            self.squares_x,
            self.squares_y,
            self.square_size,
            self.marker_size,
            self.dictionary,
            self.margin,
        )


class ImagingSpec(_Spec):
    antialias: int = Field(2, ge=1, le=8)
    background_samples: int = Field(2, ge=1, le=8)
    shadow_samples: int = Field(4, ge=1, le=8)
    noise_sigma: float = Field(1.5, ge=0, le=50)
    blur_sigma: float = Field(0.5, ge=0, le=10)
    exposure_jitter: float = Field(0.1, ge=0, le=0.9)
    vignetting: float = Field(0.2, ge=0, lt=1)
    write_depth: bool = True
    backend: Literal["embree", "trimesh"] = "embree"


class SceneSpec(_Spec):
    """Everything that defines a synthetic capture. Validated; frozen."""

    name: str = "synth"
    seed: int = Field(0, ge=0)
    n_frames: int = Field(48, ge=1, le=1_000_000)
    n_people: int = Field(2, ge=1, le=255)
    motions: list[list[str]] | None = None  # per-person programmes; None = sampled
    # Where people are: "loop" (runners around the volume, in-place movers apart) or "crowd"
    # (people a few decimetres apart, walkers crossing them: synth.crowd).
    layout: Literal["loop", "crowd"] = "loop"
    rig: RigSpec = RigSpec()
    board: BoardClipSpec = BoardClipSpec()
    imaging: ImagingSpec = ImagingSpec()
    body_model: str = "anny"
    preview_frame: int | None = None  # frame of the contact sheet (default: middle)

    @field_validator("name")
    @classmethod
    def _safe_name(cls, v: str) -> str:
        if not v or any(c in v for c in "/\\\0") or v.startswith("."):
            raise ValueError(f"scene name {v!r} must be a plain file name")
        return v

    @model_validator(mode="after")
    def _consistent(self):
        if self.motions is not None and len(self.motions) != self.n_people:
            raise ValueError(
                f"motions has {len(self.motions)} programmes but n_people is {self.n_people}"
            )
        for i, programme in enumerate(self.motions or ()):
            if (problem := programme_problem(programme)) is not None:
                raise ValueError(f"motions: person {i + 1}: {problem}")
        if self.preview_frame is not None and not 0 <= self.preview_frame < self.n_frames:
            raise ValueError(
                f"preview_frame {self.preview_frame} is outside 0..{self.n_frames - 1}"
            )
        if self.board.marker_size >= self.board.square_size:
            raise ValueError("board.marker_size must be smaller than board.square_size")
        return self


def _dome_rig(n_cameras: int, width: int, height: int) -> dict:
    """The small presets' rig: a dome of mildly distorted 30 fps cameras."""
    return dict(
        kind="dome", n_cameras=n_cameras, width=width, height=height, distortion="mild", fps=30.0
    )


_PRESET_FIELDS: dict[str, dict] = {
    # Small enough to render in well under 2 minutes on 2 CPU cores, board clip included.
    "demo": dict(
        n_frames=48,
        n_people=2,
        motions=[["run"], ["jump"]],
        rig=_dome_rig(6, 480, 360),
        board=dict(n_frames=40),
    ),
    # People who come within 0.5 m of each other, walkers crossing and hiding the others.
    "crowd": dict(
        n_frames=48, n_people=4, layout="crowd", rig=_dome_rig(7, 480, 360), board=dict(n_frames=40)
    ),
    "small": dict(n_frames=120, n_people=2, rig=_dome_rig(8, 640, 480), board=dict(n_frames=80)),
    "full": dict(
        n_frames=300,
        n_people=4,
        rig=dict(kind="hall", n_cameras=8, width=1920, height=1080, distortion="mild"),
        board=dict(n_frames=200, squares_x=7, squares_y=5, square_size=0.2, marker_size=0.15),
        imaging=dict(antialias=3),
    ),
}
# Each preset's scene is named after it.
PRESETS: dict[str, dict] = {name: dict(name=name, **f) for name, f in _PRESET_FIELDS.items()}


def programme_problem(programme) -> str | None:
    """What is wrong with a person's motion programme beyond unknown names (None: nothing):
    'random_static' poses the whole clip (`PersonSpec.motion_clip`), so it stands alone."""
    if "random_static" in programme and len(programme) > 1:
        return f"'random_static' must be the only motion of its programme, got {list(programme)}"
    return None


def _merge(base: dict, overrides: dict, within: str = "") -> dict:
    out = dict(base)
    for key, value in overrides.items():
        if "__" in key or "." in key:
            head, rest = key.replace(".", "__").split("__", 1)
            group = out.get(head) or {}
            if not isinstance(group, dict | BaseModel):
                # dict() of it failed with "'int' object is not iterable" or "dictionary update
                # sequence element #0 has length 1", naming neither the key nor the field
                raise TypeError(
                    f"override '{within}{key}': {within.replace('__', '.')}{head} is "
                    f"{group!r}, not a group of fields to set '{rest}' in"
                )
            out[head] = _merge(dict(group), {rest: value}, f"{within}{head}__")
        elif isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value, f"{within}{key}__")
        else:
            out[key] = value
    return out


def preset_fields(preset_name: str, /, **overrides) -> dict:
    """The fields of a preset with overrides, not yet validated (see `preset`): a copy, which
    the caller may change."""
    if preset_name not in PRESETS:
        raise KeyError(f"unknown synth preset '{preset_name}', expected one of {sorted(PRESETS)}")
    # deep: _merge copies only what it overrides, so the preset's own nested dicts and lists
    # (rig, board, motions) came back shared, and changing them changed the preset for good
    return _merge(copy.deepcopy(PRESETS[preset_name]), overrides)


def preset(preset_name: str, /, **overrides) -> SceneSpec:
    """A preset spec ('demo', 'crowd', 'small', 'full') with overrides. Nested fields take a dict
    (`rig={"width": 320}`) or a double-underscore key (`rig__width=320`). The preset's name is
    positional only: `name=` is an override like any other (the scene's own name)."""
    return SceneSpec.model_validate(preset_fields(preset_name, **overrides))

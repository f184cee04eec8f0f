"""Shared test settings and fixtures.

Under CI (CI=true) hypothesis runs derandomized, so a CI verdict is reproducible and does not
depend on which examples a fresh database happens to draw; local runs keep exploring new
examples (and remember failing ones in .hypothesis/).
"""

import os

import pytest
from hypothesis import settings

settings.register_profile("ci", derandomize=True, deadline=None, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


@pytest.fixture(scope="module")
def one_sample(tmp_path_factory):
    """One person (jumping) seen by 4 dome cameras over 2 frames, as 128 px crops: (crops, the
    first group of >= 2 views, the body model). Shared by the training tests."""
    from gst.body import load_body_model
    from gst.train.synthetic_crops import crops_from_synth_scene
    from synth.scene import preset, render_scene

    out = tmp_path_factory.mktemp("one_person")
    spec = preset(
        "demo",
        seed=7,
        n_frames=2,
        n_people=1,
        motions=[["jump"]],
        rig={"kind": "dome", "n_cameras": 4, "width": 320, "height": 240},
        board={"n_frames": 1},
    )
    render_scene(spec, out)
    crops = crops_from_synth_scene(out, crop_size=128)
    body = load_body_model("anny")
    return crops, crops.groups(min_views=2)[0], body


@pytest.fixture
def counter(tmp_path, monkeypatch):
    """The names of the fake pipeline stages (tests/fake_stages.py) that ran, in order."""
    path = tmp_path / "runs.txt"
    monkeypatch.setenv("FAKE_STAGE_COUNTER", str(path))

    def read() -> list[str]:
        return path.read_text().split() if path.exists() else []

    return read

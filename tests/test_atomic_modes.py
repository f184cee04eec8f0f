"""gst.atomic: files and folders written through it get the permissions a plain write would
give (the user's umask), not the 0600 / 0700 of the temporary files they are made as; its
strict-JSON helper."""

from __future__ import annotations

import os
import stat

from gst.atomic import atomic_dir, atomic_path


def test_atomic_files_and_folders_take_the_umask(tmp_path):
    """A rendered scene folder came out drwx------ (mkdtemp's 0700): other users of a shared
    disk or a Ray cluster's workers under another account could not read it."""
    old = os.umask(0o022)
    try:
        with atomic_dir(tmp_path / "scene") as staging:
            (staging / "a.txt").write_text("x")
        with atomic_path(tmp_path / "file.txt") as tmp:
            tmp.write_text("y")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "scene").stat().st_mode) == 0o755
    assert stat.S_IMODE((tmp_path / "file.txt").stat().st_mode) == 0o644


def test_finite_json_makes_every_undefined_number_null():
    import json

    import numpy as np

    from gst.atomic import finite_json

    value = {"a": float("nan"), "b": [1, np.float32("inf"), (2.5, -np.inf)], "c": np.int64(3)}
    got = finite_json(value)
    assert got == {"a": None, "b": [1, None, [2.5, None]], "c": 3}
    json.dumps(got, allow_nan=False, default=int)  # strict JSON now

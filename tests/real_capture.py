"""The real lab capture and the BlazePose models, for the tests that run on real frames (they
are skipped on a machine without them)."""

from pathlib import Path

import pytest

LAB = Path("/work/shared/real/pose2sim-multiperson")


def _models_ready() -> bool:
    try:
        from gst.detect.blazepose import import_litert
        from gst.detect.weights import model_paths

        import_litert()
        model_paths()
        return True
    except Exception:
        return False


# pytestmark of a test module that needs both.
NEEDS_MODELS_AND_LAB = [
    pytest.mark.skipif(not _models_ready(), reason="BlazePose models or LiteRT not installed"),
    pytest.mark.skipif(not LAB.is_dir(), reason="the real lab capture is not on this machine"),
]

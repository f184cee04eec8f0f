"""The real lab capture and the BlazePose models, for the tests that need them (they are
skipped on a machine without them)."""

from pathlib import Path

import pytest

LAB = Path("/work/shared/real/pose2sim-multiperson")


def models_ready() -> bool:
    """Whether LiteRT is installed and the BlazePose models are fetched."""
    try:
        from gst.detect.blazepose import import_litert
        from gst.detect.weights import model_paths

        import_litert()
        model_paths()
        return True
    except Exception:
        return False


NEEDS_MODELS = pytest.mark.skipif(
    not models_ready(),
    reason="BlazePose models not fetched (python -m gst.detect fetch) or LiteRT not installed",
)
NEEDS_LAB = pytest.mark.skipif(
    not LAB.is_dir(), reason=f"the real lab capture is not on this machine ({LAB})"
)
# pytestmark of a test module that needs both.
NEEDS_MODELS_AND_LAB = [NEEDS_MODELS, NEEDS_LAB]

"""gst.prefetch: items produced ahead in a thread."""


def test_a_prefetch_depth_below_one_is_refused_at_the_call():
    """The check sat inside the generator: `background(items, 0)` returned, and failed only at
    the first `next`, far from the call that was wrong."""
    import pytest

    from gst.prefetch import background

    with pytest.raises(ValueError, match="depth must be >= 1"):
        background(iter([1, 2]), 0)
    assert list(background(iter([1, 2]), 1)) == [1, 2]

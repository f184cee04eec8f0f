"""The common base of board-calibration errors, so callers can catch them all at once."""


class CalibrationError(RuntimeError):
    """Board calibration cannot proceed; the message names the camera(s) and the reason."""

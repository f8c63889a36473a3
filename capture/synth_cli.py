"""``capture synth`` (placeholder until the synthetic-take work lands)."""

from capture.errors import CaptureError


def synth_command() -> None:
    """Render a synthetic take of an actor with known truth."""
    raise CaptureError("capture synth is not available in this build yet")

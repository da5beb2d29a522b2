"""The one error type of kinetix.recording."""


class RecordingError(ValueError):
    """A recording cannot be written or read; the message says why in words a user can act on."""

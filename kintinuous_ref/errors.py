"""Errors meant for people: each says what went wrong and where, in one line."""


class KintinuousError(Exception):
    """Base of every error the command line reports as a one-line message."""


class DatasetError(KintinuousError):
    """A sequence on disk that cannot be read: missing, corrupt or inconsistent files."""


class ImageSizeError(DatasetError):
    """An image whose size differs from the camera's: every frame is likely to differ alike, so
    a run refuses it before its work rather than skipping it."""


class ConfigError(KintinuousError):
    """A parameter outside its sensible range."""


class TrackingError(KintinuousError):
    """A tracker that cannot produce a trustworthy pose."""


class InternalError(KintinuousError):
    """An unexpected exception (a bug), reported in one line that says so; its traceback goes to
    a crash log."""

"""User-facing exceptions of monodbh.

Every error meant for a user derives from :class:`MonodbhError`; its message is one line that
names the file (when there is one) and the problem. The ``dbh`` command line prints
``error: <message>`` on stderr and exits with status 1; programming errors (wrong argument types
or shapes passed to the API) raise the usual ``TypeError``/``ValueError`` instead.
"""
from __future__ import annotations

__all__ = ["MonodbhError", "PhotoError", "CalibrationError", "CameraFileError"]


class MonodbhError(Exception):
    """Base class of the errors shown to users as ``error: <message>``."""


class PhotoError(MonodbhError):
    """A photo cannot be read: missing, empty, truncated, corrupt or not an image."""


class CalibrationError(MonodbhError):
    """Calibration or pose estimation cannot be done with the given views or settings."""


class CameraFileError(MonodbhError):
    """A camera file (cam.yaml) cannot be read or written, or does not fit the photo."""

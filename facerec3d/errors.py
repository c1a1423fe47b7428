"""Errors raised by facerec3d.

ISO/IEC 19795-1 distinguishes a *failure to acquire* (no usable sample could be
obtained from a capture) from a *failure to enrol*; both are recorded by batch
jobs, which then carry on.
"""

from __future__ import annotations

from pathlib import Path


class FaceRec3DError(Exception):
    """Base class of every error facerec3d raises on purpose."""


class ScanFormatError(FaceRec3DError, ValueError):
    """A scan file is unreadable: truncated, corrupt, mis-sized, empty or absurd.

    The message always names the file and the reason.
    """

    def __init__(self, path: str | Path | None, reason: str):
        self.path = None if path is None else str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}" if self.path else reason)


class FailureToAcquire(FaceRec3DError):
    """No usable face could be obtained from a scan (ISO/IEC 19795-1 FTA)."""

    def __init__(self, reason: str, path: str | Path | None = None):
        self.path = None if path is None else str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}" if self.path else reason)

"""Errors raised by facerec3d.

ISO/IEC 19795-1 distinguishes a *failure to acquire* (no usable sample could be
obtained from a capture) from a *failure to enrol*; both are recorded by batch
jobs, which then carry on.
"""

from __future__ import annotations

from pathlib import Path


class FaceRec3DError(Exception):
    """Base class of every error facerec3d raises on purpose.

    Errors cross process boundaries (worker pools pickle them): an error is rebuilt from its message and
    attributes, not by calling its constructor again, so subclasses may take any arguments.
    """

    def __reduce__(self):
        return _rebuild, (type(self), self.args, self.__dict__)


def _rebuild(cls: type, args: tuple, state: dict) -> FaceRec3DError:
    error = cls.__new__(cls, *args)
    error.args = args
    error.__dict__.update(state)
    return error


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


class InputError(FaceRec3DError, ValueError):
    """Input that cannot be used as given: an option's value, a dataset, a run folder, a score file."""


class SettingsError(FaceRec3DError, ValueError):
    """A settings value (or file) that cannot be used: `field` is the dotted name, e.g. `resample.resolution_mm`.

    The message names the file (when known), the field and the reason, on one line.
    """

    def __init__(self, path: str | Path | None, field: str | None, reason: str):
        self.path = None if path is None else str(path)
        self.field, self.reason = field, reason
        where = ": ".join(x for x in (self.path, field) if x)
        super().__init__(f"{where}: {reason}" if where else reason)

    def within(self, path: str | Path | None = None, section: str | None = None) -> "SettingsError":
        """The same error inside a file (when it names none yet) and a section (`section.field`)."""
        field = ".".join(x for x in (section, self.field) if x) or None
        return SettingsError(self.path if self.path is not None else path, field, self.reason)


def threshold_text(value: float) -> str:
    """A verification threshold as printed beside the scores compared with it: short (4 significant digits) when
    that reads back as the same number, else every digit it takes (a threshold calibrated just above a score,
    6.000000000000001, is not "6", which a score of 6.0000 would seem to reach)."""
    text = f"{value:.4g}"
    return text if float(text) == value else repr(float(value))


def short_of(value: float, limit: float, digits: int = 1) -> str:
    """`value` printed for a message that says it falls short of `limit`, with as many decimals (at least
    `digits`) as it takes to read as less than the limit when printed (`short_of(5.96, 6)` is "5.96", never "6")."""
    for d in range(digits, 7):
        text = f"{value:.{d}f}"
        if float(text) < limit:
            return text
    return repr(float(value))

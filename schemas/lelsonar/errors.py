"""The one exception tree of lelsonar.

Every error raised on purpose derives from :class:`LelsonarError`, so a service
can catch the whole family in one place, count it, log it and keep serving.
Messages say what was wrong and, where there is one, the fix.
"""

from __future__ import annotations


class LelsonarError(Exception):
    """Root of every lelsonar error."""


# --- configuration and identifiers -------------------------------------------------
class ConfigError(LelsonarError):
    """A configuration value, flag or TOML entry is invalid."""


class InvalidIdentifierError(ConfigError):
    """An identifier that would go into a Zenoh key expression is unsafe."""


# --- decoding what came from the wire or a file -----------------------------------
class DecodeError(LelsonarError):
    """A payload could not be turned into a valid message."""


class SchemaVersionError(DecodeError):
    """The message carries a schema version this build does not speak."""


class PayloadTooLargeError(DecodeError):
    """A payload or a declared length exceeds the configured bound."""


class TruncatedDataError(DecodeError):
    """Packed data is shorter or longer than its declared length."""


class NonFiniteValueError(DecodeError):
    """A field that must be a finite number is NaN or infinite."""


class InvalidMessageError(DecodeError):
    """A field is out of range or inconsistent with another field."""


# --- devices -----------------------------------------------------------------------
class DeviceError(LelsonarError):
    """The motor or the sensor board failed."""


class DeviceTimeoutError(DeviceError):
    """A device did not answer in time, even after the retries."""


# --- recordings --------------------------------------------------------------------
class RecordingError(LelsonarError):
    """An MCAP recording cannot be written or read."""


class RecordingNotFoundError(RecordingError):
    """The recording's path does not exist or is a directory."""


class NotMcapError(RecordingError):
    """The file is not an MCAP file (e.g. a text file): it lacks the MCAP magic."""


class NoScansError(RecordingError):
    """The file is MCAP but holds no lelsonar scans (foreign channels only, or every scan unreadable)."""


# --- security and identity ---------------------------------------------------------
class SecurityError(ConfigError):
    """Certificates, keys or a secure configuration are missing, invalid, or would be overwritten."""


class ScannerMismatchError(InvalidMessageError):
    """The scanner id in the Zenoh key differs from the scanner id in the payload (a forgery or a bug)."""


class ClosedError(LelsonarError):
    """A component was called after it was closed (a message arriving as a bridge shuts down): what it was
    handed is not forwarded."""


# --- lelsonar's own invariants -----------------------------------------------------
class InternalError(LelsonarError):
    """lelsonar broke one of its own invariants: a bug to report (the message names it), not a fault of the
    input, the device or the set-up."""

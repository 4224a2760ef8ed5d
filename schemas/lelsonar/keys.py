"""Zenoh key expressions of the contract, and the validation of what goes into them.

====================================  ==========================  =================
key expression                        payload                     who puts it
====================================  ==========================  =================
``<prefix>/<scanner>/sample``         ``Sample``                  acquire
``<prefix>/<scanner>/scan``           ``ScanStart`` / ``ScanEnd``  acquire
``<prefix>/<scanner>/planes``         ``Reconstruction``          reconstruct (+ get)
``<prefix>/<scanner>/alive/<svc>``    liveliness token            every service
``<prefix>/<scanner>/log/<scan_id>``  queryable: recorded scan    acquire (get only)
====================================  ==========================  =================

A ``get`` on ``<prefix>/<scanner>/log/<scan_id>?steps=A-B;start=1;end=1``
returns what the acquirer recorded of that scan: the samples of steps A to B
(inclusive, at most :data:`MAX_LOG_STEPS_PER_QUERY`), and the ScanStart /
ScanEnd when asked for.  Each reply is one message, on the concrete key, with
its type in the encoding.  Use consolidation NONE: every reply has the same key.

The payload type travels in the Zenoh encoding, ``application/protobuf;<full name>``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from lelsonar.errors import InvalidIdentifierError

DEFAULT_PREFIX = "lelsonar"
#: Most samples one log query may ask for (the acquirer refuses larger ranges).
MAX_LOG_STEPS_PER_QUERY = 64
#: The encoding of the log's error reply "this scan is not (or no longer) held": the querier stops asking.
LOG_NOT_HELD_ENCODING = "text/plain;lelsonar.log.not_held"
_UINT64_MAX = 2**64 - 1
MAX_ID_LENGTH = 64
MAX_PREFIX_LENGTH = 200

# An allow-list is safer than banning Zenoh's specials (* $ # ? /) one by one.
_ID_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")


def validate_identifier(value: str, what: str = "scanner id") -> str:
    """Return ``value`` if it is safe as one chunk of a key expression.

    Raises
    ------
    InvalidIdentifierError
        If it is empty, too long, or holds anything but letters, digits, ``_ . -``.
    """
    if not isinstance(value, str) or not value:
        raise InvalidIdentifierError(f"{what} must be a non-empty string")
    if len(value) > MAX_ID_LENGTH:
        raise InvalidIdentifierError(f"{what} is {len(value)} characters long; the limit is {MAX_ID_LENGTH}")
    if not _ID_PATTERN.fullmatch(value):
        raise InvalidIdentifierError(
            f"{what} {value!r} may only hold letters, digits, '_', '.' and '-', and must start "
            "with a letter or digit (Zenoh treats * $ # ? / specially)"
        )
    return value


def validate_prefix(prefix: str) -> str:
    """Return ``prefix`` (e.g. ``robot7/lelsonar``) if each chunk is a valid identifier."""
    if not isinstance(prefix, str) or not prefix or len(prefix) > MAX_PREFIX_LENGTH:
        raise InvalidIdentifierError(f"key prefix must be 1 to {MAX_PREFIX_LENGTH} characters")
    for chunk in prefix.split("/"):
        validate_identifier(chunk, what=f"key prefix chunk of {prefix!r}")
    return prefix


@dataclass(frozen=True)
class ScannerKeys:
    """The key expressions of one scanner, or of all scanners with ``scanner_id='*'``."""

    prefix: str = DEFAULT_PREFIX
    scanner_id: str = "*"

    def __post_init__(self) -> None:
        validate_prefix(self.prefix)
        if self.scanner_id != "*":
            validate_identifier(self.scanner_id)

    def _key(self, leaf: str) -> str:
        return f"{self.prefix}/{self.scanner_id}/{leaf}"

    @property
    def sample(self) -> str:
        return self._key("sample")

    @property
    def scan(self) -> str:
        return self._key("scan")

    @property
    def planes(self) -> str:
        return self._key("planes")

    @property
    def odom(self) -> str:
        """Where the robot's odometry publishes its base pose (``lelsonar.v1.Odometry``)."""
        return self._key("odom")

    def alive(self, service: str = "*") -> str:
        if service != "*":
            validate_identifier(service, what="service name")
        return self._key(f"alive/{service}")

    def log(self, scan_id: int | str = "*") -> str:
        """The log queryable of one scan (``scan_id`` an unsigned 64-bit integer) or of all (``"*"``)."""
        if scan_id != "*":
            scan_id = validate_scan_id(scan_id)
        return self._key(f"log/{scan_id}")

    def scan_of_log_key(self, key: str) -> tuple[str, int]:
        """(scanner, scan_id) of a concrete log key under this prefix."""
        scanner = self.scanner_of(key)
        rest = key[len(self.prefix) + 1 + len(scanner) :]
        if not rest.startswith("/log/") or "/" in rest[len("/log/") :]:
            raise InvalidIdentifierError(f"key {key!r} is not a log key <prefix>/<scanner>/log/<scan_id>")
        return scanner, validate_scan_id(rest[len("/log/") :])

    def scanner_of(self, key: str) -> str:
        """The scanner id inside a concrete key received under this prefix, validated."""
        if not key.startswith(self.prefix + "/"):
            raise InvalidIdentifierError(f"key {key!r} is not under prefix {self.prefix!r}")
        return validate_identifier(self.scanner_chunk(key))

    def scanner_chunk(self, key: str) -> str:
        """The chunk of a received key where the scanner id sits, unvalidated (compare it, don't trust it)."""
        return key.removeprefix(self.prefix + "/").split("/", 1)[0]


def validate_scan_id(value: int | str) -> int:
    """A scan id as an int: an unsigned 64-bit integer, given as an int or as its decimal digits.

    Raises
    ------
    InvalidIdentifierError
        Anything else (signs, spaces, Zenoh specials, out of range).
    """
    if isinstance(value, bool):
        raise InvalidIdentifierError(f"scan id must be an integer, got {value!r}")
    if isinstance(value, str):
        if not value.isascii() or not value.isdigit() or len(value) > 20:
            raise InvalidIdentifierError(f"scan id {value[:40]!r} must be decimal digits (an unsigned 64-bit integer)")
        value = int(value)
    if not isinstance(value, int) or not 0 <= value <= _UINT64_MAX:
        raise InvalidIdentifierError(f"scan id {value!r} must be an unsigned 64-bit integer")
    return value

"""Zenoh key expressions of the contract, and the validation of what goes into them.

====================================  ==========================  =================
key expression                        payload                     who puts it
====================================  ==========================  =================
``<prefix>/<scanner>/sample``         ``Sample``                  acquire
``<prefix>/<scanner>/scan``           ``ScanStart`` / ``ScanEnd``  acquire
``<prefix>/<scanner>/planes``         ``Reconstruction``          reconstruct (+ get)
``<prefix>/<scanner>/alive/<svc>``    liveliness token            every service
====================================  ==========================  =================

The payload type travels in the Zenoh encoding, ``application/protobuf;<full name>``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from lelsonar.errors import InvalidIdentifierError

DEFAULT_PREFIX = "lelsonar"
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

    def alive(self, service: str = "*") -> str:
        if service != "*":
            validate_identifier(service, what="service name")
        return self._key(f"alive/{service}")

    def scanner_of(self, key: str) -> str:
        """The scanner id inside a concrete key received under this prefix."""
        head = self.prefix + "/"
        if not key.startswith(head):
            raise InvalidIdentifierError(f"key {key!r} is not under prefix {self.prefix!r}")
        return validate_identifier(key[len(head):].split("/", 1)[0])

    def scanner_chunk(self, key: str) -> str:
        """The chunk of a received key where the scanner id sits, unvalidated (compare it, don't trust it)."""
        return key.removeprefix(self.prefix + "/").split("/", 1)[0]

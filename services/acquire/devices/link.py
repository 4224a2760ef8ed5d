"""How fast bytes cross the two serial links of a scanner: the AX-12 bus and the sensor board's port.

Pure data and arithmetic, no I/O: the physical bound of a scan
(:mod:`lelsonar.acquire.scan_bound`) charges every byte at its link's rate, and the
emulators (:mod:`lelsonar.acquire.emulate.pty_link`) pace what they send and receive
with the same :class:`Link`, so the emulated scan pays what the real one would.

Two kinds of link:

* ``uart``: an asynchronous serial line, 8N1: 10 bits on the wire per byte (start,
  8 data, stop).  The AX-12 bus is one at its Baud Rate register (1 Mbps from the
  factory): 100,000 bytes/s, 10 µs per byte, half duplex.
* ``usb-fs``: a USB CDC device at full speed.  The bus signals at 12 Mbit/s, but a
  bulk endpoint (64-byte packets) carries at most 19 packets per 1 ms frame (USB 2.0
  §5.8.4, table 5-9): 1,216 bytes per frame, 1,216,000 bytes/s of payload at best,
  delivered frame by frame.  A 28,048-byte ACQ frame takes 23.1 ms, longer than the
  17.5 ms acoustic window it carries (``schemas/SENSOR_BOARD.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from lelsonar.errors import ConfigError

#: Link kinds a rig file may name (``[sensor_board] link``).
LINK_KINDS = ("usb-fs", "uart")

#: Bits on the wire per byte of an 8N1 UART (start + 8 data + stop).
UART_BITS_PER_BYTE = 10
#: USB full speed: payload bytes of one bulk packet, bulk packets per 1 ms frame at most (USB 2.0 table 5-9).
USB_FS_BULK_PACKET = 64
USB_FS_BULK_PACKETS_PER_FRAME = 19
USB_FS_FRAME_S = 1e-3


@dataclass(frozen=True)
class Link:
    """A byte link: its payload throughput and the granularity at which bytes arrive.

    Parameters
    ----------
    kind : {"usb-fs", "uart"}
    bytes_per_s : float
        Payload bytes per second at best.
    chunk_s : float
        Bytes arrive in chunks of this many seconds' worth (a USB frame is 1 ms); an
        emulator releases each chunk when its last byte would have arrived.
    """

    kind: str
    bytes_per_s: float
    chunk_s: float = 1e-3

    def __post_init__(self) -> None:
        if self.kind not in LINK_KINDS:
            raise ConfigError(f"link kind must be one of {', '.join(LINK_KINDS)}, got {self.kind!r}")
        if not (math.isfinite(self.bytes_per_s) and self.bytes_per_s > 0):
            raise ConfigError(f"link throughput must be positive, got {self.bytes_per_s} bytes/s")
        if not (math.isfinite(self.chunk_s) and self.chunk_s > 0):
            raise ConfigError(f"link chunk time must be positive, got {self.chunk_s} s")

    @classmethod
    def uart(cls, baudrate: int) -> Link:
        """An 8N1 UART at ``baudrate`` bits/s (10 bits per byte)."""
        if baudrate <= 0:
            raise ConfigError(f"baudrate must be positive, got {baudrate}")
        return cls("uart", baudrate / UART_BITS_PER_BYTE)

    @classmethod
    def usb_full_speed(cls) -> Link:
        """A USB CDC device at full speed: 19 bulk packets of 64 bytes per 1 ms frame at best."""
        per_frame = USB_FS_BULK_PACKET * USB_FS_BULK_PACKETS_PER_FRAME
        return cls("usb-fs", per_frame / USB_FS_FRAME_S, chunk_s=USB_FS_FRAME_S)

    @classmethod
    def named(cls, kind: str, baudrate: int) -> Link:
        """The link a rig file names: ``usb-fs`` (``baudrate`` unused), or ``uart`` at ``baudrate``."""
        if kind == "usb-fs":
            return cls.usb_full_speed()
        if kind == "uart":
            return cls.uart(baudrate)
        raise ConfigError(f"link must be one of {', '.join(LINK_KINDS)}, got {kind!r}")

    def seconds(self, nbytes: int) -> float:
        """Time for ``nbytes`` of payload to cross the link, s (first byte sent → last byte received)."""
        return nbytes / self.bytes_per_s

    @property
    def baudrate(self) -> int:
        """Bits per second on the wire of a UART link (``uart`` only)."""
        if self.kind != "uart":
            raise ConfigError(f"a {self.kind} link has no baud rate")
        return round(self.bytes_per_s * UART_BITS_PER_BYTE)

    @property
    def chunk_bytes(self) -> int:
        """Bytes per arrival chunk (at least 1)."""
        return max(1, int(self.bytes_per_s * self.chunk_s))

    def describe(self) -> str:
        if self.kind == "usb-fs":
            return f"USB full speed, {self.bytes_per_s / 1e6:.3f} MB/s (19 × 64 B bulk packets per ms)"
        return f"UART {self.bytes_per_s * UART_BITS_PER_BYTE / 1e6:g} Mbaud 8N1, {self.bytes_per_s / 1e3:g} kB/s"


#: The AX-12 bus at the factory Baud Rate (1 Mbps).
AX12_BUS = Link.uart(1_000_000)
#: The sensor board: USB CDC at full speed (a UART would be slower still for 28 KB frames).
SENSOR_BOARD_USB = Link.usb_full_speed()

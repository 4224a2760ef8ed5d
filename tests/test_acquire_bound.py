"""The physical bound of a scan: travel, windows and every byte on both links, by hand.

The sizes are written out from the protocols (design §6 for the AX-12, ``schemas/SENSOR_BOARD.md``
for the board) and checked against the codecs that put those bytes on the wire.
"""

from __future__ import annotations

import pytest

from lelsonar.acquire.config import AcquireConfig
from lelsonar.acquire.devices import sensor_frame as sf
from lelsonar.acquire.devices.link import AX12_BUS, SENSOR_BOARD_USB, Link
from lelsonar.acquire.emulate.ax12_emulator import encode_packet
from lelsonar.acquire.scan_bound import MOVE_READ_BYTES, MOVE_WRITE_BYTES, emulated_scan_bound, scan_bound
from lelsonar.errors import ConfigError

#: USB 2.0 table 5-9: full-speed bulk, 19 packets of 64 bytes per 1 ms frame at most.
USB_FS_BYTES_PER_S = 19 * 64 * 1000
#: The AX-12 bus at 1 Mbps, 8N1: 10 bits per byte.
AX12_BYTES_PER_S = 1_000_000 / 10


def test_the_links_rates_are_the_wires():
    assert SENSOR_BOARD_USB.bytes_per_s == USB_FS_BYTES_PER_S == 1_216_000
    assert SENSOR_BOARD_USB.chunk_bytes == 1216  # one USB frame's worth
    assert AX12_BUS.bytes_per_s == AX12_BYTES_PER_S and AX12_BUS.baudrate == 1_000_000
    assert Link.named("uart", 2_000_000).bytes_per_s == 200_000
    assert Link.named("usb-fs", 9600) == SENSOR_BOARD_USB  # a CDC board ignores the baud rate
    with pytest.raises(ConfigError):
        Link.named("usb-hs", 1)


def test_the_byte_counts_are_the_codecs():
    """What the bound charges per move and per shot is what the drivers and emulators send."""
    # AX-12: WRITE Goal Position (address + 2 bytes) and its bare status; READ 36..46 (address, length)
    # and its status with the 11 bytes.
    write, ack = encode_packet(1, 0x03, bytes([30, 0x00, 0x02])), encode_packet(1, 0)
    read, status = encode_packet(1, 0x02, bytes([36, 11])), encode_packet(1, 0, bytes(11))
    assert (len(write), len(ack), len(read), len(status)) == (9, 6, 8, 17)
    assert MOVE_WRITE_BYTES == 9 + 6 and MOVE_READ_BYTES == 8 + 17
    # The board: FIRE is 12 + 10 + 4 bytes; ACQ with 3,500 samples of 4 channels 12 + 32 + 28,000 + 4.
    fire = sf.encode_fire(1, sf.FireRequest(step=0, n_samples=3500, fs_hz=200_000))
    acq = sf.encode_acq(
        1, sf.AcqFrame(step=0, bits=12, fs_hz=200_000, status=0, t_fire_us=0, tof_ns=[0] * 4, waves=[[2048] * 3500] * 4)
    )
    assert (len(fire), len(acq)) == (26, 28_048)


def test_bound_of_the_paper_scan_on_usb_full_speed():
    """3,500 samples at 200 kHz over USB full speed, the servo on its factory 1 Mbps bus, Return Delay 0:
    four steps of 0, 3, 3 and 4 units at 1000 units/s.  Every move but the first is shorter than a frame's
    transfer (23.07 ms), so the pipelined bound hides all of them."""
    acq, fire, move_bus = 28_048 / USB_FS_BYTES_PER_S, 26 / USB_FS_BYTES_PER_S, 40 / AX12_BYTES_PER_S
    window = 3500 / 200_000
    moves = [move_bus + units / 1000 for units in (0, 3, 3, 4)]
    b = scan_bound(
        [100, 103, 106, 110],
        100,
        speed_units_s=1000.0,
        window_s=window,
        n_samples=3500,
        sensor_link=SENSOR_BOARD_USB,
        motor_link=AX12_BUS,
    )
    assert (b.fire_bytes, b.acq_bytes, b.move_bus_bytes) == (26, 28_048, 40)
    assert (b.travel_units, b.initial_units) == (10, 0)
    assert b.travel_s == pytest.approx(0.010)
    assert b.windows_s == pytest.approx(4 * 0.0175)
    assert b.sensor_link_s == pytest.approx(4 * (fire + acq))
    assert b.motor_link_s == pytest.approx(4 * 0.0004)
    assert b.overlap_s == pytest.approx(sum(moves[1:]))  # each under the previous frame
    assert b.total_s == pytest.approx(moves[0] + 4 * (fire + window) + 4 * acq, rel=1e-12)
    sequential = scan_bound(
        [100, 103, 106, 110],
        100,
        speed_units_s=1000.0,
        window_s=window,
        n_samples=3500,
        sensor_link=SENSOR_BOARD_USB,
        motor_link=AX12_BUS,
        pipelined=False,
    )
    assert sequential.total_s == pytest.approx(sum(moves) + 4 * (fire + window + acq), rel=1e-12)
    # The frame takes longer than the window it carries.
    assert acq > window


def test_bound_with_a_uart_board_and_a_move_longer_than_the_frame():
    """500 samples at 100 kHz over a 2 Mbaud UART (200 kB/s), Return Delay 250 (500 µs) before each of a
    move's two status packets; a 100-unit move takes longer than the 4,048-byte frame it overlaps, so that
    stretch costs the move, and only the frame's time is hidden."""
    link = Link.uart(2_000_000)
    acq, fire = (12 + 32 + 2 * 4 * 500 + 4) / 200_000, 26 / 200_000
    move_bus = 40 / AX12_BYTES_PER_S + 2 * 500e-6
    window = 500 / 100_000
    m0, m1 = move_bus, move_bus + 100 / 1000
    assert m1 > acq
    b = scan_bound(
        [0, 100],
        0,
        speed_units_s=1000.0,
        window_s=window,
        n_samples=500,
        sensor_link=link,
        motor_link=AX12_BUS,
        return_delay_s=500e-6,
    )
    assert b.acq_bytes == 4048
    assert b.motor_link_s == pytest.approx(2 * move_bus)
    assert b.overlap_s == pytest.approx(acq)
    assert b.total_s == pytest.approx(m0 + 2 * (fire + window) + max(acq, m1) + acq, rel=1e-12)


def test_the_emulated_rig_bound_is_its_schedule():
    """The bound the bench uses: the preset's 184 steps over 120° (409 units at the no-load 59 rpm,
    1208 units/s), 17.5 ms windows, and the default links."""
    b = emulated_scan_bound(AcquireConfig(device="emulated"))
    assert (b.steps, b.travel_units, b.initial_units) == (184, 409, 0)
    assert b.speed_units_s == pytest.approx(59 / 60 * 1024 / (300 / 360), rel=1e-3)
    assert b.window_s == pytest.approx(0.0175)
    assert b.sensor_link == SENSOR_BOARD_USB and b.motor_link == AX12_BUS
    assert b.sensor_link_s == pytest.approx(184 * 28_074 / USB_FS_BYTES_PER_S)
    assert b.pipelined and b.total_s < emulated_scan_bound(AcquireConfig(pipeline=False)).total_s

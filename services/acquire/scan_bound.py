"""The physical bound of a scan: what the servo, the air and the two serial links cannot do faster.

A scan is a chain of three physical processes per step: the servo travels to the
step's angle, the capsules listen for the acoustic window, and the bytes of every
command and answer cross their links.  :func:`scan_bound` adds them up for a
schedule, with the overlaps the pipelined loop realises (and no others), so that
``lelsonar bench acquire`` can hold the emulated scan against an honest figure.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from lelsonar.acquire.backends import emulated_servo
from lelsonar.acquire.config import AcquireConfig
from lelsonar.acquire.devices import ax12
from lelsonar.acquire.devices import sensor_frame as sf
from lelsonar.acquire.devices.link import Link
from lelsonar.acquire.devices.motor import MotorConfig
from lelsonar.acquire.rig import rig_links
from lelsonar.acquire.scan_loop import gamma_schedule
from lelsonar.acquire.service import sim_config

#: AX-12 bus bytes of one move as the driver makes it: WRITE Goal Position (2 data bytes) and its
#: status packet, then one READ of Present Position .. Moving (address, length) and its status.
MOVE_WRITE_BYTES = ax12.packet_size(1 + 2) + ax12.packet_size(0)
MOVE_READ_BYTES = ax12.packet_size(2) + ax12.packet_size(ax12.MOVE_READBACK_BYTES)


@dataclass(frozen=True)
class ScanBound:
    """The parts of the bound of one scan (all durations in s; see :func:`scan_bound`).

    Attributes
    ----------
    steps : int
    travel_units, initial_units : int
        AX-12 position units travelled over the scan, of which before the first shot.
    speed_units_s : float
    window_s : float
        One acoustic window.
    fire_bytes, acq_bytes : int
        One FIRE frame and one ACQ frame on the sensor board's link.
    move_bus_bytes : int
        AX-12 bus bytes of one move (commands and status packets).
    sensor_link, motor_link : Link
    travel_s, windows_s, sensor_link_s, motor_link_s : float
        Σ travel; steps × window; steps × (FIRE + ACQ) line time; steps × (the move's bus
        bytes' line time + a Return Delay per status packet).
    overlap_s : float
        What the pipelined loop hides: each move after the first runs while the previous
        frame crosses the link (0 if not ``pipelined``).
    pipelined : bool
    """

    steps: int
    travel_units: int
    initial_units: int
    speed_units_s: float
    window_s: float
    fire_bytes: int
    acq_bytes: int
    move_bus_bytes: int
    sensor_link: Link
    motor_link: Link
    travel_s: float
    windows_s: float
    sensor_link_s: float
    motor_link_s: float
    overlap_s: float
    pipelined: bool

    @property
    def link_s(self) -> float:
        """Both links' line time (before the overlap)."""
        return self.sensor_link_s + self.motor_link_s

    @property
    def total_s(self) -> float:
        """The bound: travel + windows + link time − what the pipeline overlaps."""
        return self.travel_s + self.windows_s + self.link_s - self.overlap_s


def scan_bound(
    goals_raw: Sequence[int],
    start_raw: int,
    *,
    speed_units_s: float,
    window_s: float,
    n_samples: int,
    sensor_link: Link,
    motor_link: Link,
    return_delay_s: float = 0.0,
    n_channels: int = sf.N_CHANNELS,
    pipelined: bool = True,
) -> ScanBound:
    """The shortest time a scan over ``goals_raw`` can take on these links.

    What it counts, per step k of N (goal ``g_k``, from ``g_{k-1}``; ``g_{-1}`` = ``start_raw``):

    * **move** ``m_k``: on the AX-12 bus (``motor_link``) the WRITE of Goal Position
      (9 bytes) and its status packet (6), the travel ``|g_k − g_{k−1}| / v``, then one READ
      of Present Position .. Moving (8) and its status packet (6 + 11): 40 bytes, plus a
      Return Delay before each of the two status packets.  The driver waits for the
      write's status before it times the travel, and must read once the servo has stopped
      (the sample's measured γ is that read-back), so the parts add up.
    * **shot**: the FIRE frame (16 + 10 bytes) on the sensor link, the acoustic window
      ``n_samples / fs``, then the ACQ frame (16 + 32 + 2 · n_channels · n_samples bytes;
      28,048 for 4 × 3,500) back over the link.

    Overlaps assumed when ``pipelined`` (and realised by
    :class:`~lelsonar.acquire.backends.DeviceScanner`): the move to step k+1 runs while
    step k's ACQ crosses the link, so that stretch costs ``max(ACQ, m_{k+1})`` instead
    of the sum.  Nothing overlaps an acoustic window: the servo must be still while the
    capsules listen, and the FIRE that starts it must follow the move.  The next FIRE
    also waits for the last ACQ: the board keeps one shot to resend after a corrupt
    frame (``schemas/SENSOR_BOARD.md``), so firing before it is safely in would lose it.

    Not counted: the host's own time (parsing, messages, MCAP), USB latency (an FTDI
    adapter's latency timer; none on a pty), acceleration and settling of the servo.

    Parameters
    ----------
    goals_raw : sequence of int
        The Goal Position of each step, as the driver writes it (clamped to the limits).
    start_raw : int
        Present Position before the scan.
    speed_units_s : float
        Travel speed, position units/s (:func:`~lelsonar.acquire.devices.ax12.speed_units_per_s`).
    window_s : float
        One acoustic window, s.
    n_samples : int
        Samples per channel per shot (sets the ACQ frame's size).
    sensor_link, motor_link : Link
    return_delay_s : float
        The servo's Return Delay Time (address 5; 0 in the emulated rig, 500 µs from the factory).
    n_channels : int
        Channels in an ACQ (4 in protocol version 1, whatever the mask).
    pipelined : bool

    Returns
    -------
    ScanBound
    """
    goals = [int(g) for g in goals_raw]
    if not goals:
        raise ValueError("scan_bound needs at least one step")
    if speed_units_s <= 0 or window_s <= 0 or n_samples < 0 or return_delay_s < 0:
        raise ValueError("scan_bound needs a positive speed and window, n_samples >= 0 and return_delay_s >= 0")
    travel = [abs(b - a) for a, b in zip([int(start_raw)] + goals[:-1], goals)]
    fire_bytes = sf.frame_size(sf.FIRE_PAYLOAD_SIZE)
    acq_bytes = sf.frame_size(sf.acq_payload_size(n_samples, n_channels))
    move_bus_bytes = MOVE_WRITE_BYTES + MOVE_READ_BYTES
    move_bus_s = motor_link.seconds(move_bus_bytes) + 2 * return_delay_s
    acq_s = sensor_link.seconds(acq_bytes)
    moves_s = [move_bus_s + units / speed_units_s for units in travel]
    n = len(goals)
    overlap = sum(min(acq_s, m) for m in moves_s[1:]) if pipelined else 0.0
    return ScanBound(
        steps=n,
        travel_units=sum(travel),
        initial_units=travel[0],
        speed_units_s=float(speed_units_s),
        window_s=float(window_s),
        fire_bytes=fire_bytes,
        acq_bytes=acq_bytes,
        move_bus_bytes=move_bus_bytes,
        sensor_link=sensor_link,
        motor_link=motor_link,
        travel_s=sum(travel) / speed_units_s,
        windows_s=n * window_s,
        sensor_link_s=n * (sensor_link.seconds(fire_bytes) + acq_s),
        motor_link_s=n * move_bus_s,
        overlap_s=overlap,
        pipelined=pipelined,
    )


def emulated_scan_bound(cfg: AcquireConfig, *, pipelined: bool | None = None) -> ScanBound:
    """:func:`scan_bound` of the scan ``--device emulated`` makes for ``cfg`` (an AcquireConfig).

    The schedule, window and samples of its preset; the goals as the driver computes them;
    the emulated servo's power-on position, speed and Return Delay; the links of the rig
    (:func:`~lelsonar.acquire.rig.rig_links`).  ``pipelined`` defaults to ``cfg.pipeline``.
    """
    sim = sim_config(cfg)
    servo = emulated_servo(cfg, sim)
    zero_raw = int(sim.servo.to_raw(0.0))
    goals = [
        min(ax12.POSITION_MAX, max(0, ax12.raw_from_gamma(float(g), zero_raw)))
        for g in gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
    ]
    motor_link, sensor_link = rig_links(cfg.rig)
    speed = ax12.speed_units_per_s(MotorConfig.moving_speed, servo.no_load_rpm)
    return scan_bound(
        goals,
        servo.initial_position,
        speed_units_s=speed,
        window_s=sim.window_samples / sim.sample_rate,
        n_samples=sim.window_samples,
        sensor_link=sensor_link,
        motor_link=motor_link,
        return_delay_s=servo.return_delay * ax12.RETURN_DELAY_UNIT_S,
        pipelined=cfg.pipeline if pipelined is None else pipelined,
    )

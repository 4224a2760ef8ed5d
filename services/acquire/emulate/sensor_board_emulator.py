"""A byte-exact sensor board (``schemas/SENSOR_BOARD.md``) on a raw pty.

The board answers FIRE with ACQ (or ERR).  What it "hears" comes from a *shot
source*, a callable ``(step, gamma, n_samples, fs_hz) -> (tof_ns, waves)``:

* ``tof_ns``: ``uint32 (4,)``, ``0xFFFFFFFF`` = no echo;
* ``waves``: ``(4, n_samples)`` as ``uint16`` offset-binary ADC codes, ``int16``
  signed codes (mid-scale = 0), or floating volts (converted with the board's
  :class:`~lelsonar.acquire.devices.sensor_frame.WaveScale`).

``gamma`` is read from a second callable at each FIRE; link it to the AX-12
emulator with :meth:`AX12Emulator.gamma_source` so each shot sees the angle the
servo is really at.  :func:`sim_shot_source` wraps the acoustic simulator;
:func:`echo_shot_source` is a trivial stand-in (one wall at a fixed range).

Timing: with ``realtime`` (the default) the ACQ leaves no earlier than the
acoustic window ``n_samples / fs_hz`` after the FIRE arrived, as on the real
board; computing the shot overlaps that wait.  With a ``link`` (the backend's and
``lelsonar emulate``'s choice: USB full speed) the FIRE arrives and the ACQ leaves
at the link's rate (:mod:`.pty_link`): a 28 KB frame takes 23 ms after the window.

Fault injection: bit flips in the next frames (payload or header), garbage
bytes before frames, dropped answers; or random ones with the configured
probabilities and seed.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from lelsonar import sim
from lelsonar.acquire.devices import sensor_frame as sf
from lelsonar.acquire.devices.link import Link
from lelsonar.acquire.emulate.pty_link import PtyDevice
from lelsonar.errors import ConfigError, DecodeError

#: ``(step, gamma_rad, n_samples, fs_hz) -> (tof_ns uint32 (4,), waves (4, n_samples))``
ShotSource = Callable[[int, float, int, float], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class SensorBoardEmulatorConfig:
    """Behaviour of the emulated board.

    Parameters
    ----------
    adc_bits : int
        ADC resolution reported in ACQ.
    full_scale_v : float
        Volts at the positive rail, for shot sources that return volts.
    max_samples : int
        Largest n_samples a FIRE may ask for (else ERR BAD_PARAM).
    realtime : bool
        Hold each ACQ until the acoustic window has passed since the FIRE.
    corrupt_probability : float
        Chance that an ACQ gets a bit flip in its payload.
    garbage_probability : float
        Chance that garbage precedes a frame.
    garbage_max_bytes : int
        Longest random garbage burst.
    seed : int
        Seed of the fault generator.
    link : Link, optional
        Pace the port at this link (e.g. :data:`~lelsonar.acquire.devices.link.SENSOR_BOARD_USB`); None: unpaced.
    """

    adc_bits: int = 12
    full_scale_v: float = 1.65
    max_samples: int = 16384
    realtime: bool = True
    corrupt_probability: float = 0.0
    garbage_probability: float = 0.0
    garbage_max_bytes: int = 64
    seed: int = 0
    link: Link | None = None

    def __post_init__(self) -> None:
        checks = (
            (1 <= self.adc_bits <= 16, "adc_bits must be 1..16"),
            (math.isfinite(self.full_scale_v) and self.full_scale_v > 0, "full_scale_v must be positive"),
            (0 < self.max_samples <= 0xFFFF, "max_samples must be 1..65535"),
            (0.0 <= self.corrupt_probability <= 1.0, "corrupt_probability must be in [0, 1]"),
            (0.0 <= self.garbage_probability <= 1.0, "garbage_probability must be in [0, 1]"),
            (self.garbage_max_bytes >= 1, "garbage_max_bytes must be >= 1"),
        )
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"SensorBoardEmulatorConfig: {message}")


class SensorBoardEmulator(PtyDevice):
    """The sensor board on a pty, answering FIRE from a shot source.

    Parameters
    ----------
    shot_source : ShotSource
    gamma_source : callable, optional
        Returns the present scanner angle γ (rad); 0 if not given.
    config : SensorBoardEmulatorConfig, optional
    clock : callable, optional
        Monotonic seconds (the board's µs clock for ``t_fire_us``).
    """

    def __init__(
        self,
        shot_source: ShotSource,
        gamma_source: Callable[[], float] | None = None,
        config: SensorBoardEmulatorConfig | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config or SensorBoardEmulatorConfig()
        super().__init__("sensor-board", self.config.link)
        self._shot_source = shot_source
        self._gamma_source = gamma_source or (lambda: 0.0)
        self._clock = clock
        self._epoch = clock()
        self._scale = sf.WaveScale(self.config.full_scale_v)
        # A FIRE is 10 bytes: anything much larger is a broken header.
        self._parser = sf.FrameParser(max_payload=1024)
        self._rng = np.random.default_rng(self.config.seed)
        self._lock = threading.Condition()
        self._corrupt_next: list[str] = []
        self._garbage_next: list[int] = []
        self._drop_next = 0
        self._last: sf.AcqFrame | None = None
        #: Counters: FIREs handled, ACQs resent from the buffer, frames sent, frames corrupted, ERRs sent.
        self.fires = 0
        self.resends = 0
        self.frames_sent = 0
        self.corrupted = 0
        self.errors_sent = 0
        #: (step, gamma) of the latest shots actually fired (bounded: the CLI runs for days).
        self.shots: collections.deque[tuple[int, float]] = collections.deque(maxlen=4096)
        #: (step, start, end) of their acoustic windows, monotonic s: the servo must be still in each.
        self.windows: collections.deque[tuple[int, float, float]] = collections.deque(maxlen=4096)

    # --- fault injection -----------------------------------------------------------------
    def inject_corruption(self, n: int = 1, where: Literal["payload", "header"] = "payload") -> None:
        """Flip one bit in each of the next ``n`` frames, in the payload/CRC or in the header."""
        if where not in ("payload", "header"):
            raise ValueError("where must be 'payload' or 'header'")
        with self._lock:
            self._corrupt_next.extend([where] * n)

    def inject_garbage(self, nbytes: int, n: int = 1) -> None:
        """Send ``nbytes`` random bytes before each of the next ``n`` frames."""
        with self._lock:
            self._garbage_next.extend([nbytes] * n)

    def drop_next(self, n: int = 1) -> None:
        """Do not answer the next ``n`` requests."""
        with self._lock:
            self._drop_next += n

    def wait_fires(self, count: int, timeout: float = 2.0) -> bool:
        """Block until at least ``count`` FIREs have been handled."""
        with self._lock:
            return self._lock.wait_for(lambda: self.fires >= count, timeout)

    # --- protocol ----------------------------------------------------------------------
    def _on_input(self, data: bytes, now: float) -> None:
        self._parser.feed(data)
        while True:
            try:
                frame = self._parser.next_frame()
            except sf.FrameCrcError as exc:
                self._send_err(exc.seq, sf.ErrCode.BAD_CRC, "FIRE failed its CRC32; send it again", now)
                continue
            except sf.FrameVersionError as exc:
                self._send_err(0, sf.ErrCode.BAD_VERSION, str(exc), now)
                continue
            except sf.FrameTooLargeError as exc:
                self._send_err(0, sf.ErrCode.BAD_PARAM, str(exc), now)
                continue
            if frame is None:
                return
            if frame.type != sf.FrameType.FIRE:
                self._send_err(frame.seq, sf.ErrCode.UNKNOWN_TYPE, f"type 0x{frame.type:02X}", now)
                continue
            self._handle_fire(frame, now)

    def _handle_fire(self, frame: sf.Frame, now: float) -> None:
        try:
            fire = sf.decode_fire(frame.payload)
        except DecodeError as exc:
            self._send_err(frame.seq, sf.ErrCode.BAD_PARAM, str(exc), now)
            return
        want_waves = bool(fire.flags & sf.FireFlag.WAVEFORMS)
        n = fire.n_samples if want_waves else 0
        if want_waves and not 0 < n <= self.config.max_samples or fire.fs_hz == 0 or fire.mask == 0:
            self._send_err(
                frame.seq,
                sf.ErrCode.BAD_PARAM,
                f"n_samples {fire.n_samples}, fs_hz {fire.fs_hz}, mask {fire.mask}",
                now,
            )
            return
        with self._lock:
            self.fires += 1
            self._lock.notify_all()
            drop = self._drop_next > 0
            if drop:
                self._drop_next -= 1
        if drop:
            return
        last = self._last
        if (
            fire.flags & sf.FireFlag.RESEND
            and last is not None
            and (last.step, last.n_samples, last.fs_hz) == (fire.step, n, fire.fs_hz)
        ):
            self.resends += 1
            resent = dataclasses.replace(last, status=last.status | sf.AcqStatus.RESENT)
            self._send(sf.encode_acq(frame.seq, resent), now)
            return
        try:
            acq = self._acquire(fire, n, now)
        except Exception as exc:  # a failing source must answer ERR, not kill the board
            self._send_err(frame.seq, sf.ErrCode.INTERNAL, f"{type(exc).__name__}: {exc}", now)
            return
        self._last = acq
        due = now + (n / fire.fs_hz if self.config.realtime else 0.0)
        self.windows.append((fire.step, now, now + n / fire.fs_hz))
        self._send(sf.encode_acq(frame.seq, acq), due)

    def _acquire(self, fire: sf.FireRequest, n: int, now: float) -> sf.AcqFrame:
        bits = self.config.adc_bits
        half, top = 1 << (bits - 1), (1 << bits) - 1
        gamma = float(self._gamma_source())
        self.shots.append((fire.step, gamma))
        tof, waves = self._shot_source(fire.step, gamma, max(n, 1), float(fire.fs_hz))
        tof = np.asarray(tof)
        waves = np.asarray(waves)
        if tof.shape != (sf.N_CHANNELS,) or waves.ndim != 2 or waves.shape[0] != sf.N_CHANNELS:
            raise ValueError(f"shot source returned tof {tof.shape} and waves {waves.shape}; need (4,) and (4, n)")
        if waves.dtype == np.uint16:
            codes = np.minimum(waves, top)
        elif waves.dtype == np.int16:
            codes = np.clip(waves.astype(np.int32) + half, 0, top).astype(np.uint16)
        elif np.issubdtype(waves.dtype, np.floating):
            codes = self._scale.to_codes(waves, bits)
        else:
            raise ValueError(f"shot source waves must be uint16, int16 or float, not {waves.dtype}")
        codes = codes[:, :n]
        if codes.shape[1] != n:
            raise ValueError(f"shot source returned {codes.shape[1]} samples, FIRE asked for {n}")
        tof = tof.astype(np.uint32)
        off = [ch for ch in range(sf.N_CHANNELS) if not fire.mask >> ch & 1]
        if off:
            codes = codes.copy()
            codes[off] = half
            tof[off] = sf.NO_ECHO
        status = sf.AcqStatus(0)
        if n and (codes.min() == 0 or codes.max() == top):
            status |= sf.AcqStatus.CLIPPED
        return sf.AcqFrame(
            step=fire.step,
            bits=bits,
            fs_hz=fire.fs_hz,
            status=int(status),
            t_fire_us=int((now - self._epoch) * 1e6) & 0xFFFFFFFF,
            tof_ns=tof,
            waves=codes,
        )

    def _send_err(self, seq: int, code: sf.ErrCode, text: str, now: float) -> None:
        self.errors_sent += 1
        self._send(sf.encode_err(seq, sf.ErrReport(code=int(code), text=text)), now)

    def _send(self, frame: bytes, due: float) -> None:
        """Apply the faults, then queue the frame."""
        cfg = self.config
        with self._lock:
            corrupt = self._corrupt_next.pop(0) if self._corrupt_next else None
            garbage = self._garbage_next.pop(0) if self._garbage_next else 0
        if corrupt is None and cfg.corrupt_probability and self._rng.random() < cfg.corrupt_probability:
            corrupt = "payload"
        if not garbage and cfg.garbage_probability and self._rng.random() < cfg.garbage_probability:
            garbage = int(self._rng.integers(1, cfg.garbage_max_bytes + 1))
        if corrupt is not None:
            damaged = bytearray(frame)
            # The header region starts after the sync so the frame is still *seen*, then lost.
            lo, hi = (sf.HEADER_SIZE, len(frame)) if corrupt == "payload" else (2, sf.HEADER_SIZE)
            bit = int(self._rng.integers(lo * 8, hi * 8))
            damaged[bit // 8] ^= 1 << (bit % 8)
            frame = bytes(damaged)
            self.corrupted += 1
        if garbage:
            frame = self._rng.integers(0, 256, size=garbage, dtype=np.uint8).tobytes() + frame
        self.frames_sent += 1
        self._schedule(frame, due)


# --- shot sources ----------------------------------------------------------------------
def echo_shot_source(
    distance_m: float = 1.0,
    *,
    speed_of_sound: float = 343.2,
    carrier_hz: float = 40_000.0,
    burst_s: float = 0.25e-3,
    amplitude_v: float = 0.5,
    noise_v: float = 0.0,
    seed: int = 0,
) -> ShotSource:
    """A stand-in source: every capsule hears one 40 kHz burst from a wall at ``distance_m``.

    Returns volts; the TOF is ``2 d / c``, or no echo if that is beyond the window.
    """
    if not (distance_m > 0 and speed_of_sound > 0):
        raise ConfigError("echo_shot_source: distance and speed of sound must be positive")
    rng = np.random.default_rng(seed)
    tof_s = 2.0 * distance_m / speed_of_sound

    def source(step: int, gamma: float, n_samples: int, fs_hz: float) -> tuple[np.ndarray, np.ndarray]:
        t = np.arange(n_samples) / fs_hz
        in_burst = (t >= tof_s) & (t < tof_s + burst_s)
        wave = np.where(in_burst, amplitude_v * np.sin(2 * np.pi * carrier_hz * (t - tof_s)), 0.0)
        waves = np.repeat(wave[None, :], sf.N_CHANNELS, axis=0)
        if noise_v:
            waves = waves + rng.normal(0.0, noise_v, waves.shape)
        echo = tof_s < n_samples / fs_hz
        tof = np.full(sf.N_CHANNELS, round(tof_s * 1e9) if echo else sf.NO_ECHO, dtype=np.uint32)
        return tof, waves.astype(np.float32)

    return source


def sim_shot_source(sim_config: sim.SimConfig, rng: np.random.Generator) -> ShotSource:
    """Wrap ``lelsonar.sim.simulate_step`` as a shot source.

    If a FIRE asks for another window or sample rate than ``sim_config`` has, a
    copy with ``window_samples`` and ``sample_rate`` replaced is used.
    """
    configs: dict[tuple[int, float], sim.SimConfig] = {}

    def source(step: int, gamma: float, n_samples: int, fs_hz: float) -> tuple[np.ndarray, np.ndarray]:
        key = (n_samples, fs_hz)
        cfg = configs.get(key)
        if cfg is None:
            cfg = sim_config
            if (cfg.window_samples, float(cfg.sample_rate)) != key:
                cfg = dataclasses.replace(cfg, window_samples=n_samples, sample_rate=fs_hz)
            configs[key] = cfg
        shot = sim.simulate_step(cfg, gamma, rng)
        tof = np.asarray(shot.tof, dtype=np.float64)
        # NaN (no echo) and anything the u32 field cannot hold become NO_ECHO.
        ns = np.round(np.nan_to_num(tof, nan=-1.0) * 1e9)
        tof_ns = np.where(np.isfinite(tof) & (ns >= 0) & (ns < sf.NO_ECHO), ns, sf.NO_ECHO).astype(np.uint32)
        return tof_ns, np.asarray(shot.waveforms, dtype=np.float32)

    return source

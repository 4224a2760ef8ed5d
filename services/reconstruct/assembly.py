"""One scan, assembled from its messages in whatever order they arrive (no I/O).

Samples are placed by step index, so arrival order does not matter; a second
copy of a step is dropped.  Per step the assembly keeps what the math needs —
measured γ, ranges, the energy of each capsule (eq. 10) — and the waveforms of
the latest step only, for display.

The per-step arrays grow with the highest step that actually arrived (doubling,
capped at ``ScanStart.steps``): a ScanStart claiming many steps costs nothing
until its samples come.  The assembly knows which steps it lacks
(:meth:`ScanAssembly.missing_steps`) and where each step came from (the live
stream or the acquirer's log), for the per-scan accounting.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from lelsonar import codec
from lelsonar.errors import ConfigError, InvalidMessageError
from lelsonar.geometry import ArrayGeometry, beam_points
from lelsonar.reconstruct.energy import ECHO_PEAK_WINDOW as ECHO_WINDOW, PRE_ECHO_WINDOW, EnergyModel, echo_amplitude, waveform_energy
from lelsonar.reconstruct.quality import DEGRADED, UNRELIABLE
from lelsonar.v1 import scan_pb2


_FLOAT32 = scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE


def _median_of_valid(distance: list[float]) -> float:
    """:func:`~lelsonar.reconstruct.energy.median_range` of one step, without numpy's per-call overhead:
    the same arithmetic on the same numbers (the mean of the two middle valid ranges), so the same bits."""
    valid = sorted(x for x in distance if x == x)
    c = len(valid)
    if not c:
        return math.nan
    return 0.5 * (valid[(c - 1) // 2] + valid[c // 2])


#: How far two statements of one length may differ (m): the radial offset in ScanStart.radial_offset and in
#: the capsules' array-frame positions.  A millimetre is far below the range noise and far above rounding.
_SAME_LENGTH = 1e-3


def geometry_from_start(start: codec.ScanStart) -> ArrayGeometry:
    """The array geometry a ``ScanStart`` describes (capsules on x at the radial offset).

    The radial offset is stated twice: ``radial_offset`` and the capsules' array-frame positions ``(x, r, 0)``.
    A writer may fill only one (proto3 leaves the other 0); both filled, they must agree.  An unset
    boresight (0, 0, 0) is the contract's +y, an unset rotation axis its x.

    Raises
    ------
    InvalidMessageError
        An array this build cannot describe (not a line along x facing +y, a rotation axis other than +x), or
        radial offsets that contradict each other; the message names the field to fix.
    """
    axis = start.rotation_axis
    if (axis.x, axis.y, axis.z) != (0.0, 0.0, 0.0):
        norm = math.sqrt(axis.x**2 + axis.y**2 + axis.z**2)
        if not (axis.x > 0 and math.hypot(axis.y, axis.z) <= 1e-3 * norm):
            raise InvalidMessageError(
                f"ScanStart.rotation_axis is ({axis.x:g}, {axis.y:g}, {axis.z:g}); this build supports rotation "
                "about +x only (γ right-handed about +x, beam along +y at γ = 0): state γ about +x")
    ordered = sorted(start.capsules, key=lambda c: c.capsule_id)
    for c in ordered:
        b = c.boresight
        unset = (b.x, b.y, b.z) == (0.0, 0.0, 0.0)
        if abs(c.position.z) > 1e-9 or not (unset or (abs(b.x) + abs(b.z) <= 1e-9 and abs(b.y - 1.0) <= 1e-9)):
            raise InvalidMessageError(
                f"capsule {c.capsule_id} is not on the x axis line facing +y; this build supports only linear arrays")
    radial = {round(c.position.y, 9) for c in ordered}
    if len(radial) > 1 and max(radial) - min(radial) > _SAME_LENGTH:
        raise InvalidMessageError(f"the capsules sit at different radial offsets {sorted(radial)} m (position.y); "
                                  "this build supports one line of capsules")
    from_positions = float(np.mean([c.position.y for c in ordered]))
    offset = start.radial_offset
    if offset == 0.0:
        offset = from_positions
    elif from_positions != 0.0 and abs(from_positions - offset) > _SAME_LENGTH:
        raise InvalidMessageError(
            f"ScanStart.radial_offset {offset} m contradicts the capsules' position.y {from_positions} m: the "
            "positions are in the array frame, so y is the radial offset; state the same value in both")
    return ArrayGeometry(capsule_x=tuple(c.position.x for c in ordered), radial_offset=offset)


#: Fewest readings a scan-wide check of the ranges against the waveforms or the speed of sound rests on.
RANGE_CHECK_MIN = 16
#: Largest median |distance / (c·tof/2) − 1| that is not a convention problem: 1 % is 3 K of air temperature,
#: or 1.5 cm at 1.5 m.
RANGE_TOF_TOLERANCE = 0.01
#: Smallest median ratio of an echo's peak (:data:`~lelsonar.reconstruct.energy.ECHO_PEAK_WINDOW` after the
#: time of flight) to the peak just before it (``PRE_ECHO_WINDOW``) for the ranges to match the waveforms.
#: A comparator fires on an echo's rising edge, over a threshold well above the noise: the echo's peak is
#: several times what precedes it.  A time of flight off by a factor (one-way, or a range taken for the round
#: trip) puts both windows on noise or inside one echo: a ratio near 1.
MIN_ECHO_RISE = 1.5
#: The ranges are checked (against the waveforms, against the time of flight) on every this-many-th step by
#: index: each check is a median over the scan, and a quarter of a 184-step scan's readings is 184 of them.
RISE_STRIDE = 4


#: Largest disagreement between ``ScanStart.sound_speed`` and c(air_temperature) that is still one air: 2 % is
#: 6 K, beyond what humidity (< 0.5 %) or a measured c explains.
SOUND_SPEED_TOLERANCE = 0.02


def air_sound_speed(start: codec.ScanStart) -> float | None:
    """c(T) = 331.3·√(T/273.15) m/s of ``ScanStart.air_temperature`` (K; design notes §8), None if unset."""
    t = start.air_temperature
    return 331.3 * math.sqrt(t / 273.15) if 200.0 < t < 350.0 else None


def speed_of_sound(start: codec.ScanStart) -> float | None:
    """The scan's speed of sound, m/s: ``ScanStart.sound_speed``, or from ``air_temperature`` (K) where the
    writer left it unset (0); None when neither is known."""
    if start.sound_speed > 0:
        return float(start.sound_speed)
    return air_sound_speed(start)


#: E0 for a ScanStart without a usable energy model: spherical spreading alone, E0 ∝ 1/d² (eq. 12 with
#: φ1 = φ2 = 0).  R is then uncalibrated but still relative, which is all the critical step and the energy
#: split use; the default method does not use R at all.
UNCALIBRATED_E0 = EnergyModel(1.0, 0.0, 0.0, d_min=0.01, d_max=100.0)


def energy_model_from_start(start: codec.ScanStart) -> tuple[EnergyModel, str | None]:
    """The scan's E0 (eq. 12), and why it is :data:`UNCALIBRATED_E0` instead (None if it is not).

    A scan is not thrown away for its calibration: the planes do not depend on it.
    """
    e = start.energy_model
    try:
        return EnergyModel(e.phi0, e.phi1, e.phi2, d_min=e.valid_min_range, d_max=e.valid_max_range), None
    except ConfigError as exc:
        return UNCALIBRATED_E0, f"its energy model is unusable ({exc}); E0 taken as 1/d², uncalibrated"


@dataclass
class StepView:
    """The latest step as it arrived, for display."""

    step: int
    time_ns: int
    gamma: float
    distance: np.ndarray     # (k,) m, NaN = no echo
    waveforms: np.ndarray    # (k, n) V
    sample_rate: float
    t0: float


@dataclass
class ScanAssembly:
    """Everything known about one (scanner, scan)."""

    start: codec.ScanStart
    geometry: ArrayGeometry = field(init=False)
    energy_model: EnergyModel = field(init=False)
    energy_model_problem: str | None = field(init=False)   # why E0 is the uncalibrated one, if it is
    gamma: np.ndarray = field(init=False)            # (steps,) rad, NaN until received
    gamma_commanded: np.ndarray = field(init=False)  # (steps,) rad, NaN until received
    sound_speed: float | None = field(init=False)    # m/s, None: neither stated nor a temperature to derive it
    #: Readings marked echo_valid = false that carry a range anyway (a writer that never sets the flag).
    unflagged_ranges: int = 0
    distance: np.ndarray = field(init=False)         # (steps, k) m, NaN = no echo / not received
    sensor_energy: np.ndarray = field(init=False)    # (steps, k) V²·s
    echo_amplitude: np.ndarray = field(init=False)   # (steps, k) V, peak of the first echo alone, NaN: none
    pre_echo_peak: np.ndarray = field(init=False)    # (steps, k) V, peak just before the first echo, NaN: none
    dc_level: np.ndarray = field(init=False)         # (steps, k) V, |mean| of each waveform (a receiver's offset)
    #: (steps, k) distance / (c·tof/2) where the reading gave both (NaN elsewhere): 1 when they agree.
    range_tof_ratio: np.ndarray = field(init=False)
    step_energy: np.ndarray = field(init=False)      # (steps,) E^γ, eq. 11
    expected_energy: np.ndarray = field(init=False)  # (steps,) E0(d_m), eq. 12
    ratio: np.ndarray = field(init=False)            # (steps,) R = E^γ / E0(d_m); 0 without a valid range
    time_ns: np.ndarray = field(init=False)          # (steps,)
    received: np.ndarray = field(init=False)         # (steps,) bool
    recovered_mask: np.ndarray = field(init=False)   # (steps,) bool: the step came from the acquirer's log
    end: codec.ScanEnd | None = None
    duplicates: int = 0
    #: Messages of this scan that were refused, by reason (the wire's ScanAccounting.rejected).
    rejected: Counter = field(default_factory=Counter)
    latest: StepView | None = None

    #: Rows allocated at first; the arrays double as higher steps arrive, up to ScanStart.steps.
    INITIAL_ROWS = 256

    def __post_init__(self) -> None:
        self.geometry = geometry_from_start(self.start)
        # Capsules are matched by the ids the ScanStart gave them (0..k-1 from our writer, any unique ids from
        # another); row i of the arrays is the i-th id in ascending order, as the geometry's capsule i.
        self._capsule_ids = sorted(c.capsule_id for c in self.start.capsules)
        self.sound_speed = speed_of_sound(self.start)
        self.energy_model, self.energy_model_problem = energy_model_from_start(self.start)
        self._allocate(min(self.start.steps, self.INITIAL_ROWS))

    def _allocate(self, n: int) -> None:
        """Hold ``n`` rows, keeping what is there (rows of steps not received stay empty)."""
        k = self.geometry.n_capsules

        def grown(name: str, tail: tuple[int, ...], fill, dtype=float) -> np.ndarray:
            new = np.full((n, *tail), fill, dtype=dtype)
            old = getattr(self, name, None)
            if isinstance(old, np.ndarray):
                new[:len(old)] = old
            return new

        self.gamma = grown("gamma", (), np.nan)
        self.gamma_commanded = grown("gamma_commanded", (), np.nan)
        self.distance = grown("distance", (k,), np.nan)
        self.sensor_energy = grown("sensor_energy", (k,), 0.0)
        self.echo_amplitude = grown("echo_amplitude", (k,), np.nan)
        self.pre_echo_peak = grown("pre_echo_peak", (k,), np.nan)
        self.dc_level = grown("dc_level", (k,), np.nan)
        self.range_tof_ratio = grown("range_tof_ratio", (k,), np.nan)
        self.step_energy = grown("step_energy", (), 0.0)
        self.expected_energy = grown("expected_energy", (), 0.0)
        self.ratio = grown("ratio", (), 0.0)
        self.time_ns = grown("time_ns", (), 0, np.int64)
        self.received = grown("received", (), False, bool)
        self.recovered_mask = grown("recovered_mask", (), False, bool)

    @property
    def key(self) -> tuple[str, int]:
        return (self.start.scanner_id, self.start.scan_id)

    @property
    def n_received(self) -> int:
        return int(np.count_nonzero(self.received))

    @property
    def n_recovered(self) -> int:
        return int(np.count_nonzero(self.recovered_mask))

    @property
    def expected_steps(self) -> int:
        """Steps this scan should have: ``ScanEnd.samples_sent`` once known (the scan loop sends steps
        0..samples_sent-1), else the whole schedule of the ScanStart."""
        if self.end is not None:
            return min(int(self.end.samples_sent), int(self.start.steps))
        return int(self.start.steps)

    def missing_steps(self, upto: int | None = None) -> np.ndarray:
        """Steps below ``upto`` (default :attr:`expected_steps`) that have not arrived, ascending."""
        n = self.expected_steps if upto is None else min(int(upto), int(self.start.steps))
        have = np.zeros(n, dtype=bool)
        m = min(n, len(self.received))
        have[:m] = self.received[:m]
        return np.flatnonzero(~have)

    @property
    def highest_step(self) -> int:
        """The highest step received, -1 before any."""
        steps = np.flatnonzero(self.received)
        return int(steps[-1]) if len(steps) else -1

    @property
    def complete(self) -> bool:
        """The ScanEnd came and every step it counts has arrived."""
        return self.end is not None and len(self.missing_steps()) == 0

    def add(self, sample: codec.Sample, origin: str = "live") -> bool:
        """Place a sample (``origin`` "live" or "recovered"); return False for a duplicate step.

        Raises
        ------
        InvalidMessageError
            A step outside the schedule, or capsules the ScanStart did not list.
        """
        step = sample.step
        if step >= self.start.steps:
            raise InvalidMessageError(f"step {step} is outside the schedule of {self.start.steps} steps")
        if step >= len(self.received):
            self._allocate(min(int(self.start.steps), max(2 * len(self.received), step + 1)))
        if self.received[step]:
            self.duplicates += 1
            return False
        k = self.geometry.n_capsules
        sensors = sample.sensors
        if [s.capsule_id for s in sensors] != self._capsule_ids:
            ids = [s.capsule_id for s in sensors]
            if sorted(ids) != self._capsule_ids:
                raise InvalidMessageError(f"sample {step} carries capsules {ids}; the scan has capsules "
                                          f"{self._capsule_ids}")
            sensors = sorted(sensors, key=lambda s: s.capsule_id)
        # One pass over the readings: the waveforms, and each echo's range and round trip.
        waves = []
        ranges = [math.nan] * k
        tof = [math.nan] * k
        c = self.sound_speed
        # The scan-wide checks of the ranges (writer_problems) are medians over tens of readings: every
        # RISE_STRIDE-th step (by index) gives them plenty, at a quarter of the cost.
        sampled = step % RISE_STRIDE == 0
        agree = [math.nan] * k if sampled else None
        for i, s in enumerate(sensors):
            waves.append(s.waveform)
            if s.echo_valid:
                # A writer may fill only one of the range and the round trip (the codec made sure one is > 0);
                # the other follows from the scan's speed of sound.
                d, t = s.distance, s.time_of_flight
                if not (d > 0 and t > 0):
                    if c is None:
                        raise InvalidMessageError(
                            f"sample {step} capsule {s.capsule_id} gives only its {'distance' if d > 0 else 'time of flight'}"
                            " and the ScanStart states neither sound_speed nor air_temperature to convert it: "
                            "fill both fields of the reading, or ScanStart.sound_speed")
                    d, t = (d, 2.0 * d / c) if d > 0 else (0.5 * c * t, t)
                elif sampled and c is not None:
                    agree[i] = d / (0.5 * c * t)
                ranges[i], tof[i] = d, t
            elif s.distance > 0:  # NaN compares false: only a positive range counts
                self.unflagged_ranges += 1
        first = waves[0]
        n, rate, t0 = first.sample_count, first.sample_rate, first.t0
        if any(w.sample_count != n for w in waves):
            raise InvalidMessageError(f"sample {step} has waveforms of different lengths "
                                      f"{sorted({w.sample_count for w in waves})}")
        # One (k, n) float32 array of the waveforms (ingest decoded and validated them); for float32 data a
        # read-only view of the joined bytes: one copy in all.
        if all(w.encoding == _FLOAT32 for w in waves):
            waveforms = np.frombuffer(b"".join([w.data for w in waves]), dtype="<f4").reshape(k, n)
        else:
            waveforms = np.stack([codec.unpack_waveform(w, validated=True) for w in waves])
        distance = np.array(ranges)
        checked = sampled and n > 0  # what precedes each echo, on a sampled step with waveforms
        before = None
        if all(w.sample_rate == rate and w.t0 == t0 for w in waves):
            energy = waveform_energy(waveforms, rate)
            amplitude = echo_amplitude(waveforms, rate, t0, tof)
            if checked:
                before = echo_amplitude(waveforms, rate, t0, tof, PRE_ECHO_WINDOW)
        else:  # each capsule on its own clock (the contract allows it): each waveform with its own
            energy = np.array([waveform_energy(wv, w.sample_rate) for wv, w in zip(waveforms, waves)])
            amplitude, before = (np.array([echo_amplitude(wv, w.sample_rate, w.t0, tt, window)
                                           for wv, w, tt in zip(waveforms, waves, tof)])
                                 for window in (ECHO_WINDOW, PRE_ECHO_WINDOW))
        self.gamma[step] = sample.gamma_measured
        self.gamma_commanded[step] = sample.gamma_commanded
        self.distance[step] = distance
        self.sensor_energy[step] = energy
        self.echo_amplitude[step] = amplitude
        if checked and before is not None:
            self.pre_echo_peak[step] = before
            self.dc_level[step] = np.abs(waveforms.mean(axis=-1, dtype=np.float64))
        if sampled:
            self.range_tof_ratio[step] = agree
        # R of this step, once, as energy_ratio() computes it for a whole scan (§4).
        self.step_energy[step] = total = float(energy.sum())
        d_m = _median_of_valid(ranges)
        if d_m == d_m:  # not NaN
            self.expected_energy[step] = expected = float(self.energy_model.expected_energy(d_m))
            self.ratio[step] = total / expected
        self.time_ns[step] = sample.acquisition_time_ns
        self.received[step] = True
        self.recovered_mask[step] = origin == "recovered"
        self.latest = StepView(step, sample.acquisition_time_ns, sample.gamma_measured, distance, waveforms, rate, t0)
        return True

    @property
    def gamma_unmeasured(self) -> bool:
        """Every received step's ``gamma_measured`` is exactly 0 (proto3's unset) while the commanded angles
        move: the writer never filled the measured angle, and :meth:`arrays` uses the commanded one."""
        steps = np.flatnonzero(self.received)
        return (len(steps) > 1 and not np.any(self.gamma[steps])
                and bool(np.ptp(self.gamma_commanded[steps]) > 0))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(steps, gamma, distance, ratio)`` of the received steps, in step order.

        γ is the measured angle, or the commanded one where no step's measured angle was filled
        (:attr:`gamma_unmeasured`): with every γ at 0 all beams would point one way.
        """
        steps = np.flatnonzero(self.received)
        gamma = self.gamma_commanded if self.gamma_unmeasured else self.gamma
        return steps, gamma[steps], self.distance[steps], self.ratio[steps]

    def writer_problems(self) -> list[tuple[str | None, str]]:
        """What the scan's writer left unset or stated otherwise than the contract, each with its fix.

        Returns ``(level, text)`` pairs: ``level`` is the verdict the problem imposes on every plane of the
        scan (``"degraded"``, ``"unreliable"``), or None where the estimate does not suffer (a fallback was
        taken) or there is no plane to judge.
        """
        out: list[tuple[str | None, str]] = []
        got = self.received
        if self.gamma_unmeasured:
            out.append((None, "no Sample filled gamma_measured (all 0): the commanded angles were used instead; "
                              "fill gamma_measured with the motor's measured angle"))
        if self.unflagged_ranges and not np.isfinite(self.distance[got]).any():
            out.append((None, f"no reading is marked echo_valid, yet {self.unflagged_ranges} carry a distance: set "
                              "echo_valid = true on readings with an echo (the contract reads no range from the "
                              "others)"))
        _, gamma, _, _ = self.arrays()
        if gamma.size and (float(np.ptp(gamma)) > 2.0 * math.pi or float(np.max(np.abs(gamma))) > 2.0 * math.pi):
            # The AX-12 turns through 300°: a sweep over a turn, or an angle beyond one, is not in radians.
            out.append((UNRELIABLE, f"γ spans {np.min(gamma):.1f} to {np.max(gamma):.1f} rad, beyond a turn: the "
                                    "angles are not in rad (degrees?); the contract's gamma_measured is in rad"))
        # Both peaks above the waveform's DC level (max |w| of a carrier burst or of noise over an offset is
        # |offset| + its own peak): a receiver's offset would otherwise pull the rise towards 1.
        dc = self.dc_level[got]
        with np.errstate(divide="ignore", invalid="ignore"):
            rise = (self.echo_amplitude[got] - dc) / (self.pre_echo_peak[got] - dc)
        rise = rise[np.isfinite(rise)]
        if rise.size >= RANGE_CHECK_MIN and float(np.median(rise)) < MIN_ECHO_RISE:
            out.append((UNRELIABLE, f"the waveforms show no echo starting at the readings' time of flight (median rise "
                                    f"×{np.median(rise):.2f} over the {1e3 * -PRE_ECHO_WINDOW[0]:.1f} ms before): "
                                    "the ranges do not match the waveforms (distance is one way, time_of_flight "
                                    "the round trip from firing, waveform.t0 the first sample's time)"))
        c_air = air_sound_speed(self.start)
        if self.start.sound_speed > 0 and c_air is not None and \
                abs(self.start.sound_speed / c_air - 1.0) > SOUND_SPEED_TOLERANCE:
            out.append((DEGRADED, f"ScanStart.sound_speed {self.start.sound_speed:.1f} m/s is not the speed of sound "
                                  f"at its air_temperature {self.start.air_temperature:.1f} K ({c_air:.1f} m/s): the "
                                  "range scale is uncertain"))
        ratio = self.range_tof_ratio[got]
        ratio = ratio[np.isfinite(ratio)]
        if ratio.size >= RANGE_CHECK_MIN:
            off = float(np.median(ratio)) - 1.0
            if abs(off) > RANGE_TOF_TOLERANCE:
                # The planes rest on the distance; which of the two fields is right the scan cannot tell (the
                # waveforms place the time of flight, not the speed of sound).  A few % is a scale error of
                # centimetres: degraded; beyond, one field is in another convention (a one-way time, a
                # round-trip path): unreliable.
                out.append((UNRELIABLE if abs(off) > 5 * RANGE_TOF_TOLERANCE else DEGRADED,
                            f"the readings' distance is {100 * off:+.0f} % off c·time_of_flight/2 at the stated "
                            f"speed of sound {self.sound_speed:.1f} m/s: the range scale is uncertain (distance is "
                            "one way, time_of_flight the round trip, sound_speed the air's)"))
        return out

    def raw_points(self, step: int) -> np.ndarray:
        """Eq. (9) points of one received step, (k, 3); NaN rows where no echo."""
        return beam_points(self.geometry, self.gamma[step:step + 1], self.distance[step:step + 1])[0]

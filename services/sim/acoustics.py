"""Air, beam and receiver physics of the simulated scanner.

Pure functions and frozen configuration; no I/O.

Choices worth knowing (all documented on the fields below):

* **Capsule radius 7 mm** (``ka = 5.13`` at 40 kHz, 20 °C).  The two-way
  pattern ``D²`` is −8.5 dB at 30° and −11.4 dB at 34°, first null at 48°.
  A 5 mm piston is so wide that the plane-a echo still carries
  more energy than the corner's curvature can beat, so ``E^γ`` has no peak at
  34° at all (it falls monotonically through it); 8 mm is so narrow that
  plane a is lost before 30° and the paper's "arc" shrinks.  7 mm keeps plane
  a above the comparator to ≈32° (arc at 20–30°), gives the energy a local
  peak 0.3° before the critical angle, and leaves the plane-b echo in a
  sidelobe (−23 dB two-way) at the critical position.
* **Corner gain 1.5 (+3.5 dB).**  The image model of a rigid right dihedral
  gives exactly a wall at the edge range (gain 1, as the issue states).  With
  gain 1, ``R = E^γ/E0(d_m)`` at the corner is ≈0.90 (the corner is 21 %
  farther than plane a and the calibrated ``E0`` is clipped at 1.8 m) while
  face-on ``R`` is ≈1.0, so the paper's indicator could not find the corner.
  The paper observes the energy "gets great" at the critical position
  (Fig. 4).  We model that excess as an empirical gain; it is a parameter.
  At 1.4 the energy peak sits 0.3° before the corner (plane a's fading
  echo tilts it) and argmax R misses by two steps in 2 of 100 seeds; at 1.5
  it is within one step in 100 of 100.
* **Diffuse coefficient 0.01 (−40 dB).**  Plywood is smooth at λ = 8.6 mm.
  The diffuse echo has a random phase and, face-on or at the corner, arrives
  with the strong echo: at 0.03 it made the energies ripple by ±6 % and
  argmax R miss in 13 of 100 seeds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import lambertw

from lelsonar.errors import ConfigError

#: 0 °C in kelvin.
ZERO_CELSIUS_K = 273.15

#: First zero of J1: the first null of the piston pattern is at ``ka·sinθ = 3.8317``.
J1_FIRST_ZERO = 3.831705970207512
#: ``2·J1(x)/x = 1/√2`` here: a piston's echo (``D²``) is half its face-on amplitude at ``ka·sinθ = 1.6163``.
PISTON_HALF_ECHO_X = 1.616339948310703


def sound_speed(temperature: float | np.ndarray) -> float | np.ndarray:
    """Speed of sound in dry air, ``c = 331.3·√(1 + T_C/273.15)``.

    Parameters
    ----------
    temperature : float or array
        Air temperature in **kelvin** (``T_C = T − 273.15``).

    Returns
    -------
    float or array
        m/s; 343.2 m/s at 293.15 K (20 °C).
    """
    return 331.3 * np.sqrt(np.asarray(temperature, dtype=float) / ZERO_CELSIUS_K)


def capsule_radius_for_beam_width(beam_width: float, speed: float, frequency: float) -> float:
    """The piston radius whose echo beam is ``beam_width`` wide: the full angle at which a mirror's echo, which
    a transceiver sees through ``D²`` (:func:`~lelsonar.signal.directivity.piston_directivity`), falls to half
    its face-on amplitude (−6 dB).

    ``D(θ)² = 1/2`` at ``ka·sin θ = x½`` (:data:`PISTON_HALF_ECHO_X`), so ``a = x½ / (k·sin(beam_width/2))``,
    ``k = 2πf/c``.

    Parameters
    ----------
    beam_width : float
        Full angle, rad, in (0, π).
    speed : float
        Speed of sound, m/s.
    frequency : float
        Carrier, Hz.
    """
    if not 0.0 < beam_width < math.pi:
        raise ConfigError(f"beam_width must be in (0°, 180°), got {math.degrees(beam_width):g}°")
    return PISTON_HALF_ECHO_X / (2.0 * math.pi * frequency / speed * math.sin(beam_width / 2.0))


def absorption_factor(path: np.ndarray, alpha_db_per_m: float) -> np.ndarray:
    """Amplitude left after air absorption over ``path`` metres, ``10^(−α·path/20)``."""
    return np.power(10.0, -alpha_db_per_m * np.asarray(path, dtype=float) / 20.0)


@dataclass(frozen=True)
class Acoustics:
    """What the air, the capsules and the surfaces do to the sound.

    Parameters
    ----------
    frequency : float
        Carrier, Hz (40 kHz capsules).
    capsule_radius : float
        Piston radius ``a``, m.  See the module notes for why 7 mm.
    absorption_db_per_m : float
        Air absorption α at the carrier, dB/m (ISO 9613-1: ≈1.3 dB/m at 40 kHz,
        20 °C, 50 % RH).
    corner_gain : float
        Amplitude of the corner double bounce relative to a wall at the edge
        range (empirical, see the module notes).
    corner_max_error : float
        Largest deviation of a dihedral from 90° that still retro-reflects, rad.
        A dihedral off by δ turns the return by 2δ; beyond a few degrees it
        misses the transceiver.
    diffuse_coefficient : float
        Amplitude of the diffuse backscatter where the boresight meets a panel,
        relative to a mirror echo at the same range (Lambert ``cos`` law).
    """

    frequency: float = 40_000.0
    capsule_radius: float = 0.007
    absorption_db_per_m: float = 1.3
    corner_gain: float = 1.5
    corner_max_error: float = math.radians(10.0)
    diffuse_coefficient: float = 0.01

    def __post_init__(self) -> None:
        _check_finite(
            self,
            (
                "frequency",
                "capsule_radius",
                "absorption_db_per_m",
                "corner_gain",
                "corner_max_error",
                "diffuse_coefficient",
            ),
        )
        if not 1e3 <= self.frequency <= 1e6:
            raise ConfigError(f"frequency must be in [1 kHz, 1 MHz], got {self.frequency} Hz")
        if not 0.0005 <= self.capsule_radius <= 0.05:
            raise ConfigError(f"capsule_radius must be in [0.5, 50] mm, got {self.capsule_radius} m")
        if not 0.0 <= self.absorption_db_per_m <= 20.0:
            raise ConfigError(f"absorption_db_per_m must be in [0, 20], got {self.absorption_db_per_m}")
        if not 0.0 <= self.corner_gain <= 10.0:
            raise ConfigError(f"corner_gain must be in [0, 10], got {self.corner_gain}")
        if not 0.0 <= self.corner_max_error < math.pi / 4:
            raise ConfigError(f"corner_max_error must be in [0, 45°), got {self.corner_max_error} rad")
        if not 0.0 <= self.diffuse_coefficient <= 1.0:
            raise ConfigError(f"diffuse_coefficient must be in [0, 1], got {self.diffuse_coefficient}")

    def wavenumber(self, speed: float) -> float:
        """``k = 2πf/c``, rad/m."""
        return 2.0 * math.pi * self.frequency / speed

    def main_lobe(self, speed: float) -> float:
        """Half-angle of the main lobe (first null of ``D``), rad; π/2 if there is no null."""
        ka = self.wavenumber(speed) * self.capsule_radius
        return math.asin(J1_FIRST_ZERO / ka) if ka > J1_FIRST_ZERO else math.pi / 2


#: The comparator's timing models (:attr:`Receiver.timing`).
TIMINGS = ("onset", "crossing")


@dataclass(frozen=True)
class Receiver:
    """The sensor board: comparator, timing noise, analogue chain and ADC.

    Parameters
    ----------
    echo_gain : float
        Volts at the ADC per unit of echo amplitude, V·m.  Echo amplitudes are
        ``reflectivity·D²·10^(−α·2d/20)/(2d)`` in 1/m, so with 2.5 V·m a
        face-on wall at 1.57 m peaks at ≈0.5 V.
    threshold : float
        Comparator level on the echo envelope, V.  0.05 V is −20 dB of the
        face-on echo at 1.57 m; it keeps plane a up to γ ≈ 32°.
    blanking_time : float
        The comparator ignores anything before this, s (it would fire on the
        transmit ring-down).
    envelope_time : float
        Rise time of the echo envelope ``(u/τ)²·exp(2(1 − u/τ))``, s; it peaks at
        ``u = τ`` and is cut at ``8τ`` (below 10⁻⁴ of the peak).
    tof_jitter : float
        Standard deviation of the timing noise, expressed as range, m.
    cycle_slip_probability : float
        Chance that the comparator fires one carrier cycle early or late
        (±λ/2 = ±4.3 mm of range), split evenly between the two.
    noise_std : float
        White noise at the ADC input, V.
    amplitude_noise : float
        Relative standard deviation of a multiplicative factor on every echo
        amplitude, drawn once per shot and capsule (log-normal,
        ``exp(σ·N − σ²/2)``, mean 1): coupling, capsule orientation and air
        turbulence.  The echo *energy* then varies by about ``2σ``.  0 (the
        default) draws nothing, so existing seeds give the same bytes.
    ringdown_amplitude, ringdown_time : float
        Transmit ring-down at t = 0: ``A·exp(−t/τ)·sin(2πft)``, V and s.
    adc_bits : int
        ADC resolution over ``±adc_range``.
    adc_range : float
        ADC full scale, ±V.
    timing : str
        When the comparator fires on the echo it picked (the earliest whose
        peak is over ``threshold``).  ``"onset"`` (the
        default): at the echo's arrival, plus the timing noise — a board whose
        time of flight does not depend on the echo's strength.
        ``"crossing"``: where the echo's envelope rises through ``threshold``
        (:func:`comparator_delay`), as a real comparator does: later on weaker
        echoes, by up to one ``envelope_time`` (0.15 ms, 26 mm of range) at the
        threshold itself and ≈0.02 ms (3.5 mm) on a face-on echo ten times over
        it.  Over a sweep the wall echo weakens off its normal (``D(ψ)²``), so
        the ranges walk with the beam angle.  Either draws the same random
        numbers.
    """

    echo_gain: float = 2.5
    threshold: float = 0.05
    blanking_time: float = 1.0e-3
    envelope_time: float = 0.15e-3
    tof_jitter: float = 0.002
    cycle_slip_probability: float = 0.02
    noise_std: float = 0.002
    amplitude_noise: float = 0.0
    ringdown_amplitude: float = 0.6
    ringdown_time: float = 0.1e-3
    adc_bits: int = 12
    adc_range: float = 2.5
    timing: str = "onset"

    def __post_init__(self) -> None:
        _check_finite(
            self,
            (
                "echo_gain",
                "threshold",
                "blanking_time",
                "envelope_time",
                "tof_jitter",
                "cycle_slip_probability",
                "noise_std",
                "amplitude_noise",
                "ringdown_amplitude",
                "ringdown_time",
                "adc_range",
            ),
        )
        if self.echo_gain <= 0:
            raise ConfigError(f"echo_gain must be > 0 V·m, got {self.echo_gain}")
        if self.threshold <= 0:
            raise ConfigError(f"threshold must be > 0 V, got {self.threshold}")
        if not 0 <= self.blanking_time < 0.1:
            raise ConfigError(f"blanking_time must be in [0, 0.1) s, got {self.blanking_time}")
        if not 1e-6 <= self.envelope_time <= 1e-2:
            raise ConfigError(f"envelope_time must be in [1 µs, 10 ms], got {self.envelope_time}")
        if not 0 <= self.tof_jitter <= 0.1:
            raise ConfigError(f"tof_jitter must be in [0, 0.1] m, got {self.tof_jitter}")
        if not 0 <= self.cycle_slip_probability <= 1:
            raise ConfigError(f"cycle_slip_probability must be in [0, 1], got {self.cycle_slip_probability}")
        if not 0 <= self.amplitude_noise <= 1:
            raise ConfigError(f"amplitude_noise must be in [0, 1] (relative), got {self.amplitude_noise}")
        if self.noise_std < 0 or self.ringdown_amplitude < 0 or self.ringdown_time <= 0:
            raise ConfigError("noise_std and ringdown_amplitude must be ≥ 0 and ringdown_time > 0")
        if not (isinstance(self.adc_bits, int) and 4 <= self.adc_bits <= 24):
            raise ConfigError(f"adc_bits must be an int in [4, 24], got {self.adc_bits!r}")
        if self.adc_range <= 0:
            raise ConfigError(f"adc_range must be > 0 V, got {self.adc_range}")
        if self.timing not in TIMINGS:
            raise ConfigError(f"timing must be one of {', '.join(TIMINGS)}, got {self.timing!r}")

    @property
    def adc_lsb(self) -> float:
        """Volts per ADC code."""
        return 2.0 * self.adc_range / 2**self.adc_bits


def echo_envelope(u: np.ndarray, rise: float | np.floating) -> np.ndarray:
    """Echo envelope ``(u/τ)²·exp(2(1 − u/τ))`` for ``u ≥ 0`` (0 before), peak 1 at ``u = τ``.

    The shape of a tone burst through two resonant transducers: a fast
    quadratic rise and an exponential ring-out.
    """
    x = np.maximum(np.asarray(u), 0.0) / rise
    return x * x * np.exp(2.0 * (1.0 - x))


def comparator_delay(peak: np.ndarray, threshold: float, rise: float) -> np.ndarray:
    """Time from an echo's arrival to its envelope's rise through the comparator ``threshold``, s.

    The envelope :func:`echo_envelope` scaled to ``peak`` rises as
    ``peak·x²·exp(2(1 − x))``, ``x = u/τ``; it reaches ``threshold`` where
    ``x·e^(−x) = √(threshold/peak)/e``, on the rising branch (x ≤ 1) of the
    Lambert W function: ``x = −W₀(−√(threshold/peak)/e)``.  So the delay
    depends on the echo's strength only through ``threshold/peak`` (the
    first echo over a comparator threshold sets the time of flight): 0.135 τ
    at ten times the threshold, 0.63 τ at 1.2 times, τ at the threshold itself.

    Parameters
    ----------
    peak : array
        Echo envelope peak, V (≥ ``threshold`` for an echo the comparator fires on).
    threshold : float
        Comparator level, V.
    rise : float
        Envelope rise time τ (:attr:`Receiver.envelope_time`), s.

    Returns
    -------
    array
        s, in ``[0, rise]``; ``rise`` where ``peak ≤ threshold`` (the envelope
        just touches the level at its peak), NaN where ``peak`` is NaN.
    """
    ratio = np.clip(threshold / np.asarray(peak, dtype=np.float64), 0.0, 1.0)
    # W₀ is NaN at its branch point −1/e itself (scipy); its value there is −1.
    x = np.where(ratio < 1.0, -lambertw(-np.sqrt(ratio) / math.e, 0).real, 1.0)
    return rise * np.where(np.isnan(ratio), np.nan, x)


def _check_finite(obj: object, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(obj, name)
        if not (isinstance(value, (int, float)) and math.isfinite(value)):
            raise ConfigError(f"{type(obj).__name__}.{name} must be a finite number, got {value!r}")

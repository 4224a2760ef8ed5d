"""What a scan's writer left unset or stated otherwise than the contract, each with its fix and the verdict it
imposes (:meth:`WriterChecks.writer_problems`)."""

from __future__ import annotations

import math

import numpy as np

from lelsonar.reconstruct.estimate.quality import DEGRADED, GOOD, UNRELIABLE
from lelsonar.reconstruct.estimate.robust import median
from lelsonar.reconstruct.stream.candidates import RANGE_CHECK_MIN
from lelsonar.reconstruct.stream.range_repair import NOISE_INDEPENDENT, RangeRepair
from lelsonar.reconstruct.stream.scan_start import SOUND_SPEED_TOLERANCE, air_sound_speed
from lelsonar.signal.echo_timing import walk_finding
from lelsonar.signal.energy import PRE_ECHO_WINDOW

#: Largest median |distance / (c·tof/2) − 1| that is not a convention problem: 1 % is 3 K of air temperature,
#: or 1.5 cm at 1.5 m.
RANGE_TOF_TOLERANCE = 0.01


class WriterChecks(RangeRepair):
    """The writer checks of a scan (a mixin of :class:`~lelsonar.reconstruct.stream.assembly.ScanAssembly`)."""

    def writer_problems(self) -> list[tuple[str | None, str]]:
        """What the scan's writer left unset or stated otherwise than the contract, each with its fix.

        Returns ``(level, text)`` pairs: ``level`` is the verdict the problem imposes on every plane of the
        scan (``"degraded"``, ``"unreliable"``), ``"good"`` for what every plane names without its verdict
        lowered (ranges re-timed, :meth:`walk_free`), or None where the estimate does not suffer (a fallback
        was taken) or there is no plane to judge.
        """
        out: list[tuple[str | None, str]] = []
        got = self.received
        if self.gamma_unmeasured:
            out.append(
                (
                    None,
                    "no Sample filled gamma_measured (all 0): the commanded angles were used instead; "
                    "fill gamma_measured with the motor's measured angle",
                )
            )
        if self.unflagged_ranges and not np.isfinite(self.distance[got]).any():
            out.append(
                (
                    None,
                    f"no reading is marked echo_valid, yet {self.unflagged_ranges} carry a distance: set "
                    "echo_valid = true on readings with an echo (the contract reads no range from the "
                    "others)",
                )
            )
        _, gamma, _, _ = self.arrays()
        if gamma.size and (float(np.ptp(gamma)) > 2.0 * math.pi or float(np.max(np.abs(gamma))) > 2.0 * math.pi):
            # The AX-12 turns through 300°: a sweep over a turn, or an angle beyond one, is not in radians.
            out.append(
                (
                    UNRELIABLE,
                    f"γ spans {np.min(gamma):.1f} to {np.max(gamma):.1f} rad, beyond a turn: the "
                    "angles are not in rad (degrees?); the contract's gamma_measured is in rad",
                )
            )
        noise, sigma = self.noise_triggers()
        readings = int(np.count_nonzero(np.isfinite(self.distance[got])))
        share = self.noise_share()
        found = np.count_nonzero(np.isfinite(self.recovered_echoes()[0])) if noise.any() else 0
        recovered = (
            f"; {found} of them re-timed from the first echo over the noise after it in their waveforms "
            "(constant-fraction times), the others left out"
            if found
            else "; left out"
        )
        independence = self.noise_independence() if share > 0.5 else math.nan
        match = self.ranges_match_waveforms()
        if not match and independence > NOISE_INDEPENDENT:
            # (σ over the echoes' windows: the time-of-flight windows may lie in the transmitter's ring-down.)
            out.append(
                (
                    DEGRADED,
                    f"{100 * share:.0f} % of the readings show no echo over the noise (σ "
                    f"{1e3 * self._recovery_sigma:.1f} mV) at their time of flight, and their ranges "
                    "change from step to step as independent draws do (median step "
                    f"{independence:.2f}× their spread), not as a surface's: the board's comparator "
                    f"fires on the noise (a threshold within a few σ of it){recovered}; their zero is "
                    "the strongest echoes' crossing of the noise's level, not the board's",
                )
            )
        elif not match:
            whole, echoes = self.echo_rise()
            rise = echoes if math.isfinite(echoes) else whole
            # Most readings marking noise is a board whose comparator fires on it, or ranges in another
            # convention than the waveforms (their echoes elsewhere): the windows alone cannot tell which.
            noisy = (
                f"{100 * share:.0f} % of the readings show no echo over the noise (σ {1e3 * sigma:.1f} mV) at "
                f"their time of flight{recovered}: the board's comparator fires on the noise (a threshold "
                "within a few σ of it), or "
                if share > 0.5
                else ""
            )
            out.append(
                (
                    UNRELIABLE,
                    f"the waveforms show no echo starting at the readings' time of flight (median rise "
                    f"×{rise:.2f} over the {1e3 * -PRE_ECHO_WINDOW[0]:.1f} ms before): {noisy}the "
                    "ranges do not match the waveforms (distance is one way, time_of_flight the "
                    "round trip from firing, waveform.t0 the first sample's time)",
                )
            )
        elif (
            noise.any()
        ):  # re-timed or left out (noise_triggers_recovered): named on every plane, the verdict left to the fit
            out.append(
                (
                    GOOD,
                    f"{np.count_nonzero(noise)} of the {readings} readings ({100 * share:.1f} %) show no "
                    f"echo over the noise (σ {1e3 * sigma:.1f} mV) at their time of flight: the board's "
                    f"comparator fired on noise{recovered}",
                )
            )
        walk = self.range_walk()[0]
        if walk.detected:  # re-timed (walk_free): named on every plane, the verdict left to the fit
            out.append((GOOD, walk_finding(walk)))
        c_air = air_sound_speed(self.start)
        if (
            self.start.sound_speed > 0
            and c_air is not None
            and abs(self.start.sound_speed / c_air - 1.0) > SOUND_SPEED_TOLERANCE
        ):
            out.append(
                (
                    DEGRADED,
                    f"ScanStart.sound_speed {self.start.sound_speed:.1f} m/s is not the speed of sound "
                    f"at its air_temperature {self.start.air_temperature:.1f} K ({c_air:.1f} m/s): the "
                    "range scale is uncertain",
                )
            )
        ratio = self.range_tof_ratio[got]
        ratio = ratio[np.isfinite(ratio)]
        if ratio.size >= RANGE_CHECK_MIN:
            off = median(ratio) - 1.0
            if abs(off) > RANGE_TOF_TOLERANCE:
                # The planes rest on the distance; which of the two fields is right the scan cannot tell (the
                # waveforms place the time of flight, not the speed of sound).  A few % is a scale error of
                # centimetres: degraded; beyond, one field is in another convention (a one-way time, a
                # round-trip path): unreliable.
                out.append(
                    (
                        UNRELIABLE if abs(off) > 5 * RANGE_TOF_TOLERANCE else DEGRADED,
                        f"the readings' distance is {100 * off:+.0f} % off c·time_of_flight/2 at the stated "
                        f"speed of sound {self.sound_speed:.1f} m/s: the range scale is uncertain (distance is "
                        "one way, time_of_flight the round trip, sound_speed the air's)",
                    )
                )
        return out

"""Write a simulated scan as the MCAP recording ``lelsonar acquire --device sim`` would make.

The scan loop and recorder are the acquisition service's own
(:func:`lelsonar.acquire.scan_loop.run_scan`, :class:`lelsonar.log.recording.McapRecorder`);
only the scanner differs: :class:`ScanReplay` hands out the shots of an
already simulated :class:`SimulatedScan`, so the file holds exactly the scan a
benchmark reconstructed, and ``lelsonar reconstruct --source FILE --json``
reproduces its estimate.  The ground truth goes into the ``lelsonar.config``
metadata record (never on the wire).
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from lelsonar.acquire.backends import sim_info
from lelsonar.acquire.scan_loop import ScanIdentity, ScanOutput, run_scan
from lelsonar.acquire.scanner import MotorReading, StepMeasurement
from lelsonar.errors import ConfigError
from lelsonar.log.recording import McapRecorder
from lelsonar.sim.scan import SimulatedScan

#: Acquisition time of step 0 of a recorded simulated scan, ns (fixed, so files are reproducible).
EPOCH_NS = 1_800_000_000_000_000_000
#: Time between recorded steps, ns.
STEP_NS = 20_000_000


class ScanReplay:
    """A :class:`SimulatedScan` as a :class:`lelsonar.acquire.scanner.Scanner`: step ``k`` returns shot ``k``."""

    def __init__(self, scan: SimulatedScan) -> None:
        if scan.waveforms.shape[-1] == 0:
            raise ConfigError("a recorded scan needs its waveforms (simulate_scan(..., with_waveforms=True))")
        self.scan = scan
        self.info = sim_info(scan.config, "sim")

    def measure(
        self,
        step: int,
        gamma_commanded: float,
        *,
        next_gamma: float | None = None,
        while_listening: Callable[[], None] | None = None,
    ) -> StepMeasurement:
        """Shot ``step`` as recorded (nothing to move, nothing to listen to: the hints are not needed)."""
        return simulated_step(self.scan, step, EPOCH_NS + step * STEP_NS)

    def close(self) -> None:
        pass


def simulated_step(scan, step: int, acquisition_time_ns: int) -> StepMeasurement:
    """Step ``step`` of an already simulated sweep (an L scan or a world's) as the scanner would measure it."""
    return StepMeasurement(
        gamma_measured=float(scan.gamma_measured[step]),
        motor=MotorReading(present_position_raw=int(scan.gamma_raw[step]), load=0.0, voltage=12.0, temperature=313.15),
        time_of_flight=np.asarray(scan.tof[step]),
        waveforms=np.asarray(scan.waveforms[step]),
        t0=float(scan.t0),
        acquisition_time_ns=acquisition_time_ns,
    )


def truth_metadata(scan: SimulatedScan) -> dict[str, str]:
    """The scan's ground truth as metadata strings: true planes (JSON) and the critical step."""
    planes = {p.label: {"normal": [float(v) for v in p.normal], "offset": float(p.offset)} for p in scan.truth.planes}
    return {
        "truth_planes": json.dumps(planes),
        "truth_critical_step": str(scan.truth.critical_step),
        "truth_critical_angle": repr(float(scan.truth.critical_angle)),
    }


def record_scan(
    scan: SimulatedScan,
    path: Path | str,
    energy_model,
    *,
    scanner_id: str = "sim",
    scan_id: int = 1,
    metadata: Mapping[str, str] | None = None,
    compression: str = "zstd",
):
    """Record ``scan`` to ``path`` through the acquisition scan loop.

    Parameters
    ----------
    scan : SimulatedScan
        With waveforms.
    path : path
        The ``.mcap`` file to write (its folder is created).
    energy_model : EnergyModel
        ``E0(d)`` announced in ``ScanStart`` (what the reconstruction will use).
    scanner_id, scan_id
        Identity in every message.
    metadata : mapping, optional
        Extra ``lelsonar.config`` metadata (e.g. the scene family and seed); the
        ground truth of :func:`truth_metadata` is always added.
    compression : {"zstd", "lz4", "none"}

    Returns
    -------
    ScanEnd
        Complete unless the loop failed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"device": "sim", "scanner_id": scanner_id, **truth_metadata(scan), **dict(metadata or {})}
    truth = [(p.label, p.normal, p.offset, p.corners) for p in scan.truth.planes]
    with McapRecorder(path, compression=compression, metadata=meta, truth=truth) as recorder:
        return run_scan(
            ScanReplay(scan),
            np.asarray(scan.gamma_commanded),
            ScanIdentity(scanner_id, int(scan_id)),
            energy_model,
            ScanOutput(recorder, None),
            threading.Event(),
        )

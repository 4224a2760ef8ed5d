"""Configuration of the acquisition service: frozen, validated on creation.

Filled from a TOML file and flags by :mod:`lelsonar.cli.acquire` only.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

from lelsonar.acquire.backends import DEVICES
from lelsonar.acquire.rig import Rig, require_for_serial, serial_overrides
from lelsonar.energy_model import EnergyModel
from lelsonar.errors import ConfigError
from lelsonar.keys import validate_identifier, validate_prefix


@dataclass(frozen=True)
class AcquireConfig:
    """What `lelsonar acquire` does.

    Parameters
    ----------
    scanner_id : str
        Goes into every key expression; letters, digits, ``_ . -``.
    prefix : str
        Key-expression prefix, e.g. ``robot7/lelsonar``.
    device : {"sim", "emulated", "serial"}
    preset : str
        Simulator preset that sets the scene (sim, emulated) and the default schedule.
    steps, gamma_start, gamma_stop : optional
        Override the preset's schedule (rad).
    radial_offset : float, optional
        Override the capsules' distance from the axis, m.
    motor_port, sensor_port : str, optional
        Serial devices for ``device="serial"``.
    out_dir : Path
    mcap_name : str
        File name of the recording; several scans get ``-<n>`` before the suffix.
    record : bool
    scans : int
    interval : float
        s between scans.
    seed : int
        Seeds the simulator.
    waveform_int16 : bool
        Send waveforms as int16 with a scale (half the bytes) instead of float32.
    compression : {"zstd", "lz4", "none"}
    fsync : bool
        ``fsync`` the recording after every step: durable on disk across a power
        cut, not only across a killed process (every step is always handed to the
        OS before it is published).
    energy_model : EnergyModel, optional
        φ of eq. (12); default: the simulator's calibration.
    serve_log_for : float
        s to keep answering log queries (``<prefix>/<scanner>/log/<scan_id>``) after the last scan
        ends, so a reconstructor that missed steps can still recover them; also how long an ended
        scan stays in the served log.  0 serves only while scanning.
        φ of eq. (12); default: the rig's (serial) or the simulator's calibration.
    rig : Rig, optional
        The rig tables of ``--config`` (:mod:`lelsonar.acquire.rig`); ``device="serial"``
        takes everything from it (flags override), never from a simulator preset.  The
        emulated devices take their links from it (:func:`~lelsonar.acquire.rig.rig_links`).
    pipeline : bool
        Move the servo to the next step while the board sends the current shot's frame
        (never during an acoustic window), and record and publish each sample while the
        next shot listens.  False: one step after the other (for comparison).
    paced_links : bool
        ``device="emulated"``: the emulators send and receive at the links' rates, so the
        scan pays the line time a real one would.  False: as fast as the ptys move bytes
        (quick tests).
    world : Path, optional
        ``device="sim"``: a world file (``docs/worlds.md``); one scan per pose, each
        ``ScanStart`` with the odometry's pose.  ``scans`` is then the number of poses.
    """

    scanner_id: str = "scanner1"
    prefix: str = "lelsonar"
    device: str = "emulated"
    preset: str = "paper-test1"
    steps: int | None = None
    gamma_start: float | None = None
    gamma_stop: float | None = None
    radial_offset: float | None = None
    motor_port: str | None = None
    sensor_port: str | None = None
    out_dir: Path = Path("out")
    mcap_name: str = "scan.mcap"
    record: bool = True
    scans: int = 1
    interval: float = 0.0
    seed: int = 0
    waveform_int16: bool = False
    compression: str = "zstd"
    fsync: bool = False
    energy_model: EnergyModel | None = None
    serve_log_for: float = 10.0
    rig: Rig | None = None
    pipeline: bool = True
    paced_links: bool = True
    world: Path | None = None

    def __post_init__(self) -> None:
        validate_identifier(self.scanner_id)
        validate_prefix(self.prefix)
        if self.device not in DEVICES:
            raise ConfigError(f"--device must be one of {', '.join(DEVICES)}, got {self.device!r}")
        if self.device == "serial":
            require_for_serial(self.rig, serial_overrides(self))
        if self.steps is not None and not 2 <= self.steps <= 4096:
            raise ConfigError(f"steps must be in [2, 4096], got {self.steps}")
        for name in ("gamma_start", "gamma_stop"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and abs(v) <= math.radians(150)):
                raise ConfigError(f"{name} must be within ±150° (the AX-12 turns 300°), got {math.degrees(v):.1f}°")
        if not (math.isfinite(self.serve_log_for) and self.serve_log_for >= 0):
            raise ConfigError(f"serve_log_for must be >= 0 s, got {self.serve_log_for}")
        if self.scans < 1 or self.interval < 0:
            raise ConfigError("scans must be >= 1 and interval >= 0 s")
        if not self.mcap_name.endswith(".mcap") or "/" in self.mcap_name:
            raise ConfigError(f"mcap_name must be a file name ending in .mcap, got {self.mcap_name!r}")
        if self.compression not in ("zstd", "lz4", "none"):
            raise ConfigError(f"compression must be zstd, lz4 or none, got {self.compression!r}")
        object.__setattr__(self, "out_dir", Path(self.out_dir))
        if self.world is not None:
            object.__setattr__(self, "world", Path(self.world))
            if self.device != "sim":
                raise ConfigError(f"--world needs --device sim (the world is simulated), got --device {self.device}")
            if self.gamma_start is not None or self.gamma_stop is not None:
                raise ConfigError("--gamma-start/--gamma-stop do not apply with --world; set [scanner] sweep in it")

    def mcap_path(self, index: int) -> Path:
        if self.scans == 1:
            return self.out_dir / self.mcap_name
        stem = self.mcap_name[: -len(".mcap")]
        return self.out_dir / f"{stem}-{index + 1}.mcap"

    def as_metadata(self) -> dict[str, str]:
        """The configuration as MCAP metadata (strings)."""
        skip = {"energy_model", "rig"} | ({"preset", "seed"} if self.device == "serial" else set())  # sim only
        out = {k: str(v) for k, v in asdict(self).items() if k not in skip}
        if self.rig is not None:
            out["rig"] = str(self.rig.path)
            out.update({f"rig.{t}.{k}": str(v) for t, kv in self.rig.values.items() for k, v in kv.items()})
        if self.energy_model is not None:
            out["energy_model"] = str(asdict(self.energy_model))
        return out

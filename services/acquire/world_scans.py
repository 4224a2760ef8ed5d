"""``acquire --device sim --world FILE``: one simulated sweep per pose of a world, each with its odometry pose.

Each pose's sweep is simulated whole (:func:`lelsonar.sim.world_render.simulate_world_scan`)
and handed to the scan loop shot by shot by :class:`WorldReplay`, stamped as it goes, so
the recording and the Zenoh stream are those of any other scan.  The pose in
``ScanStart`` is the odometry's (:mod:`lelsonar.sim.odometry`), in the ``odom`` frame;
the true pose and the world go into the recording's metadata as ground truth.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lelsonar import poses
from lelsonar.acquire.scanner import ScannerInfo, StepMeasurement
from lelsonar.acquire.simulated import simulated_step
from lelsonar.geometry import array_pose, quaternion_from_matrix
from lelsonar.sim.odometry import OdometryPose, array_covariance, simulate_odometry
from lelsonar.sim.world import World, load_world
from lelsonar.sim.world_geometry import WorldModel, build_model
from lelsonar.sim.world_render import WorldRig, WorldScan, simulate_world_scan, world_rig

#: The frame the scans' poses are given in.
ODOM_FRAME = "odom"


class WorldReplay:
    """One simulated sweep as a :class:`~lelsonar.acquire.scanner.Scanner`: step ``k`` returns shot ``k``."""

    def __init__(self, scan: WorldScan, pose: poses.PoseWithCovariance) -> None:
        self.scan = scan
        self.info = ScannerInfo(
            device="sim",
            geometry=scan.geometry,
            sample_rate=scan.sample_rate,
            window_samples=int(scan.waveforms.shape[-1]),
            air_temperature=scan.temperature,
            sound_speed=scan.sound_speed,
            pose=pose,
        )

    def measure(
        self,
        step: int,
        gamma_commanded: float,
        *,
        next_gamma: float | None = None,
        while_listening: Callable[[], None] | None = None,
    ) -> StepMeasurement:
        return simulated_step(self.scan, step, time.time_ns())

    def close(self) -> None:
        pass


@dataclass(frozen=True, eq=False)
class WorldRun:
    """A world ready to be scanned pose by pose.

    Attributes
    ----------
    path : Path
    world : World
    model : WorldModel
    rig : WorldRig
    odometry : list of OdometryPose
        The odometry's estimate of each pose.
    seed : int
    """

    path: Path
    world: World
    model: WorldModel
    rig: WorldRig
    odometry: list[OdometryPose]
    seed: int

    @property
    def schedule(self) -> np.ndarray:
        return self.rig.gamma_commanded()

    def pose_message(self, index: int) -> poses.PoseWithCovariance:
        """The array frame at pose ``index`` as the odometry has it, in ``odom``, with its covariance."""
        o = self.odometry[index]
        rot, trans = array_pose(o.x, o.y, o.heading, self.rig.mount, self.rig.height, self.rig.tilt)
        return poses.pose_message(ODOM_FRAME, trans, quaternion_from_matrix(rot), array_covariance(o.covariance))

    def scanner(self, index: int) -> WorldReplay:
        """The sweep at pose ``index`` (simulated now; seeded by the run's seed and the pose)."""
        rng = np.random.default_rng([self.seed, index])
        return WorldReplay(simulate_world_scan(self.model, index, rig=self.rig, seed=rng), self.pose_message(index))

    def metadata(self, index: int, scan: WorldScan | None = None) -> dict[str, str]:
        """Ground truth for the recording of pose ``index``: the world, the true pose, the odometry's, and
        (given its ``scan``) which element of the world set each reading: ``truth_echo_element`` per step and
        capsule, an index into ``truth_elements`` (−1 for none), and ``truth_echo_kind``, its
        :class:`~lelsonar.sim.scan.EchoSource` (a diffuse echo names the mirror element of its surface)."""
        p = self.world.poses[index]
        o = self.odometry[index]
        echoes = {}
        if scan is not None:
            echoes = {
                "truth_elements": json.dumps([e.describe() for e in self.model.elements]),
                "truth_echo_element": json.dumps(np.where(scan.echo_source > 0, scan.echo_index, -1).tolist()),
                "truth_echo_kind": json.dumps(scan.echo_source.tolist()),
            }
        return echoes | {
            "world_file": str(self.path),
            "world_name": self.world.name,
            "pose_index": str(index),
            "truth_pose": json.dumps({"x": p.x, "y": p.y, "heading": p.heading, "frame_id": "map"}),
            "odometry_pose": json.dumps({"x": o.x, "y": o.y, "heading": o.heading, "frame_id": ODOM_FRAME}),
            "truth_world": json.dumps(world_json(self.world)),
        }


def world_json(world: World) -> dict:
    """The world as JSON (m and rad): room, walls, boxes, mount, poses — what viewers draw as truth."""
    return {
        "name": world.name,
        "floor": world.room.floor,
        "ceiling": world.room.ceiling,
        "walls": [
            {"from": list(w.start), "to": list(w.end), "bottom": w.bottom, "height": w.height, "name": w.name}
            for w in world.walls
        ],
        "boxes": [{"center": list(b.center), "size": list(b.size), "yaw": b.yaw, "name": b.name} for b in world.boxes],
        "mount": world.scanner.mount,
        "scanner_height": world.scanner.height,
        "poses": [{"x": p.x, "y": p.y, "heading": p.heading} for p in world.poses],
    } | _optional_scanner_keys(world)


def _optional_scanner_keys(world: World) -> dict:
    """The mount's tilt and the capsules' beam width (rad) where the world sets them: a world without them
    describes itself as before."""
    sc = world.scanner
    out: dict = {}
    if sc.tilt != 0.0:
        out["scanner_tilt"] = sc.tilt
    if sc.beam_width is not None:
        out["beam_width"] = sc.beam_width
    return out


def world_from_json(text: str) -> dict:
    """:func:`world_json`'s output read back (from a recording's metadata); raises ValueError if it is not."""
    data = json.loads(text)
    if not isinstance(data, dict) or not isinstance(data.get("walls"), list):
        raise ValueError("not a lelsonar world")
    return data


def prepare_world(path: Path | str, seed: int = 0, *, steps: int | None = None) -> WorldRun:
    """Load ``path`` and set up its scans: model, rig, odometry."""
    world = load_world(path)
    rig = world_rig(world, steps=steps)
    return WorldRun(
        path=Path(path),
        world=world,
        model=build_model(world),
        rig=rig,
        odometry=simulate_odometry(world.poses, world.odometry),
        seed=int(seed),
    )

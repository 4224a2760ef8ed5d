"""A simulated world as truth in Rerun, and where each scan was: static entities under ``<root>/map``."""

from __future__ import annotations

import math

import numpy as np
import rerun as rr

from lelsonar.view.rerun_layout import join_path

_WORLD_RGB = (150, 150, 150)
_BOX_RGB = (190, 160, 110)
_PATH_RGB = (120, 200, 255)
_POSE_RGB = (255, 200, 0)


def log_world_truth(rec: rr.RecordingStream, world: dict, root: str = "/") -> None:
    """A simulated world (a recording's ``truth_world`` metadata) under ``<root>/map/truth``: wall outlines,
    boxes, the robot's true path and poses.  Static: the world does not move."""
    base = join_path(root, "map", "truth")
    floor = float(world.get("floor") or 0.0)
    strips = []
    for w in world.get("walls", []):
        (x0, y0), (x1, y1) = w["from"], w["to"]
        z0 = floor + float(w.get("bottom", 0.0))
        z1 = z0 + float(w["height"])
        strips.append([[x0, y0, z0], [x1, y1, z0], [x1, y1, z1], [x0, y0, z1], [x0, y0, z0]])
    if strips:
        rec.log(f"{base}/walls", rr.LineStrips3D(np.array(strips, dtype=np.float64), colors=_WORLD_RGB), static=True)
    boxes = world.get("boxes", [])
    if boxes:
        rec.log(
            f"{base}/boxes",
            rr.Boxes3D(
                centers=[[b["center"][0], b["center"][1], floor + b["size"][2] / 2] for b in boxes],
                half_sizes=[[s / 2 for s in b["size"]] for b in boxes],
                rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1], radians=float(b["yaw"])) for b in boxes],
                colors=_BOX_RGB,
                labels=[b.get("name", "") for b in boxes],
            ),
            static=True,
        )
    poses = world.get("poses", [])
    if poses:
        path = np.array([[p["x"], p["y"], floor + 0.01] for p in poses], dtype=np.float64)
        rec.log(f"{base}/path", rr.LineStrips3D([path], colors=_PATH_RGB), static=True)
        heads = np.array([[0.2 * math.cos(p["heading"]), 0.2 * math.sin(p["heading"]), 0.0] for p in poses])
        rec.log(
            f"{base}/poses",
            rr.Arrows3D(origins=path, vectors=heads, colors=_PATH_RGB, labels=[str(i + 1) for i in range(len(poses))]),
            static=True,
        )


def log_scan_pose(
    rec: rr.RecordingStream, scanner_id: str, scan_id: int, position, heading: float, frame_id: str, root: str = "/"
) -> None:
    """Where a scan was (its ``ScanStart`` pose) under ``<root>/map/poses/<scanner>/<scan>``: an arrow along the
    γ = 0 beam, labelled with the pose's frame."""
    p = np.array(position, dtype=np.float64).reshape(1, 3)
    rec.log(
        join_path(root, "map", "poses", rr.escape_entity_path_part(scanner_id), str(int(scan_id))),
        rr.Arrows3D(
            origins=p,
            vectors=[[0.25 * math.cos(heading), 0.25 * math.sin(heading), 0.0]],
            colors=_POSE_RGB,
            labels=f"scan {scan_id} ({frame_id})",
        ),
        static=True,
    )

"""Foxglove live: ``reconstruct --foxglove [HOST:]PORT`` serves a Foxglove WebSocket (foxglove-sdk).

The only module that imports ``foxglove`` (foxglove-sdk).  The messages are the
ones :mod:`lelsonar.draw.visual` builds for recordings, serialized as protobuf, so
the live view and a recording opened in Foxglove look the same.  Open
``examples/foxglove-layout.json`` in Foxglove and connect to
``ws://HOST:PORT``.

Topics: ``/tf`` (world → array, per step), ``/tf_capsules`` (array → each
capsule), ``/lelsonar/array`` (the capsules), ``/lelsonar/points`` (the latest
step's points), ``/lelsonar/scan_points`` (every
raw point of the scan so far), ``/lelsonar/planes`` (planes, normals, labels,
the edge, coloured by method and by quality), ``/lelsonar/truth`` (the true
planes of a simulated scene), ``/lelsonar/energy`` (E^γ, E0(d_m), R and the
critical step, plottable JSON), ``/log``, and ``/lelsonar/map/scene`` (the map as
the mapper publishes it: :class:`FoxgloveMapView`, ``mapper --foxglove``).

Protocol notes (foxglove-sdk 0.30): the server speaks the subprotocol
``foxglove.sdk.v1`` only, and foxglove-sdk has no option to speak the older
``foxglove.websocket.v1``: the Foxglove app (web or desktop, 2.x) connects;
a client that offers only ``foxglove.websocket.v1`` (Lichtblick, Foxglove
Studio 1.x) is refused (HTTP 400) and should open a recording instead
(``reconstruct --record`` or ``export``).  A data frame is ``0x01 | u32
subscription id | u64 log time | payload``.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import foxglove
import numpy as np
from google.protobuf.message import Message

from lelsonar import codec
from lelsonar.draw import visual
from lelsonar.draw.map_scene import TOPIC_MAP_SCENE, MapScene
from lelsonar.draw.palette import QUALITY_NAME
from lelsonar.errors import ConfigError
from lelsonar.reconstruct.stream.assembly import ScanAssembly, StepView
from lelsonar.v1 import map_pb2

#: WebSocket subprotocols a client may offer; foxglove-sdk 0.30 needs the first.
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
TOPIC_TRUTH = visual.TOPIC_TRUTH

_PROTO_TOPICS: dict[str, type[Message]] = {
    visual.TOPIC_TF: visual.FrameTransform,
    visual.TOPIC_CAPSULE_TF: visual.FrameTransforms,
    visual.TOPIC_ARRAY: visual.SceneUpdate,
    visual.TOPIC_POINTS: visual.PointCloud,
    visual.TOPIC_SCAN_POINTS: visual.PointCloud,
    visual.TOPIC_PLANES: visual.SceneUpdate,
    visual.TOPIC_WORLD: visual.SceneUpdate,
    TOPIC_TRUTH: visual.SceneUpdate,
    visual.TOPIC_LOG: visual.Log,
    TOPIC_MAP_SCENE: visual.SceneUpdate,
}


def parse_host_port(text: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``PORT`` or ``HOST:PORT`` (``[::1]:PORT`` for IPv6) → (host, port); port 0 picks a free one."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = default_host, text
    host = host.strip("[]") or default_host
    try:
        value = int(port)
    except ValueError:
        raise ConfigError(f"--foxglove takes PORT or HOST:PORT, got {text!r}") from None
    if not 0 <= value <= 65535:
        raise ConfigError(f"--foxglove port must be in [0, 65535], got {value}")
    return host, value


class _Subscriptions(foxglove.ServerListener):
    """Counts channel subscriptions, so callers can wait for a viewer instead of sleeping."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.topics: dict[str, int] = {}

    def on_subscribe(self, client, channel) -> None:
        with self._cond:
            self.topics[channel.topic] = self.topics.get(channel.topic, 0) + 1
            self._cond.notify_all()

    def on_unsubscribe(self, client, channel) -> None:
        with self._cond:
            self.topics[channel.topic] = max(0, self.topics.get(channel.topic, 0) - 1)
            self._cond.notify_all()

    def wait(self, topics: Sequence[str], timeout: float, stop: threading.Event | None = None) -> bool:
        """True once every topic has a subscriber; False after ``timeout`` s or once ``stop`` is set."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                if all(self.topics.get(t, 0) > 0 for t in topics):
                    return True
                left = deadline - time.monotonic()
                if left <= 0 or (stop is not None and stop.is_set()):
                    return False
                # In slices: a signal handler sets ``stop`` without notifying this condition.
                self._cond.wait(min(left, 0.1) if stop is not None else left)


class FoxgloveServer:
    """A Foxglove WebSocket server with the lelsonar channels, on its own foxglove-sdk context.

    Parameters
    ----------
    host, port : str, int
        Where to listen; port 0 picks a free port (see :attr:`port`).
    name : str
        The server name Foxglove shows.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, name: str = "lelsonar") -> None:
        self.context = foxglove.Context()
        self.subscriptions = _Subscriptions()
        try:
            self._server = foxglove.start_server(
                name=name, host=host, port=port, context=self.context, server_listener=self.subscriptions
            )
        except RuntimeError as exc:  # foxglove-sdk 0.30: "FoxgloveError: Failed to bind port: ..."
            raise ConfigError(f"cannot serve Foxglove on {host}:{port}: {exc}") from None
        self.host = host
        self._channels: dict[str, foxglove.Channel] = {}
        for topic, cls in _PROTO_TOPICS.items():
            schema = foxglove.Schema(
                name=cls.DESCRIPTOR.full_name, encoding="protobuf", data=visual.file_descriptor_set(cls)
            )
            self._channels[topic] = foxglove.Channel(
                topic, message_encoding="protobuf", schema=schema, context=self.context
            )
        schema = foxglove.Schema(
            name=visual.ENERGY_SCALARS_NAME,
            encoding="jsonschema",
            data=visual.json_schema_bytes(visual.ENERGY_SCALARS_SCHEMA),
        )
        self._channels[visual.TOPIC_ENERGY] = foxglove.Channel(
            visual.TOPIC_ENERGY, message_encoding="json", schema=schema, context=self.context
        )

    @property
    def port(self) -> int:
        return self._server.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def log(self, topic: str, message: Message, t_ns: int) -> None:
        self._channels[topic].log(message.SerializeToString(), log_time=int(t_ns))

    def log_json(self, topic: str, payload: dict, t_ns: int) -> None:
        self._channels[topic].log(payload, log_time=int(t_ns))

    def wait_for_subscribers(self, topics: Sequence[str], timeout: float, stop: threading.Event | None = None) -> bool:
        """True once every topic has a subscriber; False after ``timeout`` s or once ``stop`` is set (Ctrl-C)."""
        return self.subscriptions.wait(topics, timeout, stop)

    def close(self) -> None:
        for ch in self._channels.values():
            ch.close()
        self._server.stop()


class FoxgloveObserver:
    """Implements :class:`lelsonar.reconstruct.stream.service.Observer` on a :class:`FoxgloveServer`.

    Parameters
    ----------
    server : FoxgloveServer
    truth : list of (label, normal, offset, corners), optional
        True planes to draw (simulated scenes), grey.
    """

    def __init__(self, server: FoxgloveServer, truth=None) -> None:
        self.server = server
        self.truth = truth
        self._planes = visual.PlaneScene()
        self._points: dict[tuple[str, int], dict[int, np.ndarray]] = {}
        self._critical: dict[tuple[str, int], int] = {}
        self._last_t = 0

    def scan_started(self, scan: ScanAssembly) -> None:
        s = scan.start
        t = s.start_time_ns
        self._last_t = t
        self._points[scan.key] = {}
        self._statics(scan, t)
        self.server.log(visual.TOPIC_TF, visual.array_transform(s.gamma_start, t), t)
        self.event(
            "info",
            f"scan {s.scan_id} of {s.scanner_id}: {s.steps} steps, device {s.device or 'unknown'}, "
            f"c = {s.sound_speed:.1f} m/s",
            t,
        )

    def _statics(self, scan: ScanAssembly, t: int) -> None:
        # The WebSocket keeps no latest value per topic: sent again at every step, so that a
        # viewer that connects mid-scan still gets the capsule frames, the array and the truth.
        s = scan.start
        self.server.log(visual.TOPIC_CAPSULE_TF, visual.capsule_transforms(s, t), t)
        self.server.log(visual.TOPIC_ARRAY, visual.array_model(s, t), t)
        for tf in visual.pose_transforms(s, t):  # where the robot was: map → odom → base_link → world
            self.server.log(visual.TOPIC_TF, tf, t)
        pose = visual.pose_scene(s, t)
        if pose is not None:
            self.server.log(visual.TOPIC_WORLD, pose, t)
        if self.truth:
            self.server.log(TOPIC_TRUTH, visual.truth_scene(self.truth, s.scanner_id, t), t)

    def step(self, scan: ScanAssembly, view: StepView, energy: float, expected: float, ratio: float) -> None:
        t = view.time_ns
        self._last_t = t
        self._statics(scan, t)
        self.server.log(visual.TOPIC_TF, visual.array_transform(view.gamma, t), t)
        steps = self._points.setdefault(scan.key, {})
        pts = scan.raw_points(view.step)
        steps[view.step] = pts
        order = sorted(steps)
        allpts = np.concatenate([steps[k] for k in order]) if order else np.empty((0, 3))
        step_ids = np.concatenate([np.full(len(steps[k]), k) for k in order]) if order else np.empty(0)
        caps = np.concatenate([np.arange(len(steps[k])) for k in order]) if order else np.empty(0)
        ok = np.isfinite(allpts).all(axis=1)
        latest = np.isfinite(pts).all(axis=1)
        self.server.log(visual.TOPIC_POINTS, visual.point_cloud(pts[latest], t), t)
        self.server.log(
            visual.TOPIC_SCAN_POINTS, visual.point_cloud(allpts[ok], t, step=step_ids[ok], capsule=caps[ok]), t
        )
        self.server.log_json(
            visual.TOPIC_ENERGY,
            visual.energy_scalars(
                scan.start.scanner_id,
                scan.start.scan_id,
                view.step,
                view.gamma,
                energy,
                expected,
                ratio,
                self._critical.get(scan.key),
            ),
            t,
        )

    def estimate(self, scan: ScanAssembly, message: codec.Reconstruction, results, partial) -> None:
        step = int(message.last_step)
        t = int(scan.time_ns[step]) if step < len(scan.time_ns) and scan.time_ns[step] > 0 else self._last_t
        if message.HasField("critical_step"):
            crit = int(message.critical_step)
            if self._critical.get(scan.key) != crit:
                self._critical[scan.key] = crit
                self.event("info", f"critical step {crit} at γ = {math.degrees(message.critical_angle):.2f}°", t)
        self.server.log(visual.TOPIC_PLANES, self._planes.update(message, t), t)
        if results is not None:
            if step < len(scan.step_energy):
                # The final's critical step (the fitted edge's) closes the series, which so far held the
                # provisional one (the energy peak's).
                self.server.log_json(
                    visual.TOPIC_ENERGY,
                    visual.energy_scalars(
                        scan.start.scanner_id,
                        scan.start.scan_id,
                        step,
                        float(scan.gamma[step]),
                        float(scan.step_energy[step]),
                        float(scan.expected_energy[step]),
                        float(scan.ratio[step]),
                        self._critical.get(scan.key),
                    ),
                    t,
                )
            self._points.pop(scan.key, None)
            lines = [f"final estimate of scan {message.scan_id} after step {step}"]
            for p in message.planes:
                lines.append(
                    f"  {p.method} {p.label}: h = {p.offset:.4f} m, σ = {p.sigma * 1e3:.1f} mm, "
                    f"{QUALITY_NAME.get(p.quality, 'unknown')}"
                    + (f" ({'; '.join(p.quality_reasons)})" if p.quality_reasons else "")
                )
            lines += [f"  {f}" for f in message.failures]
            self.event("info", "\n".join(lines), t)

    def event(self, level: str, text: str, time_ns: int | None = None) -> None:
        t = self._last_t if time_ns is None else time_ns
        self.server.log(visual.TOPIC_LOG, visual.log_message(level, text, t), t)


@contextmanager
def open_foxglove(address: str, *, truth_preset: str | None = None) -> Iterator[FoxgloveObserver]:
    """Serve Foxglove at ``[HOST:]PORT`` for the duration of the block; the observer draws on it."""
    host, port = parse_host_port(address)
    truth = None
    if truth_preset:
        from lelsonar.view.rerun_observer import preset_truth  # brings in rerun (heavy): only for a truth preset

        truth = preset_truth(truth_preset)
    server = FoxgloveServer(host, port)
    try:
        yield FoxgloveObserver(server, truth)
    finally:
        server.close()


def layout_json() -> str:
    """The Foxglove layout shipped as ``examples/foxglove-layout.json``, in the format the app exports and imports.

    A 3D view (the scan's points coloured by step, the latest step's points, the
    planes, the truth, the array and its capsule frames, following the world
    frame); plots of E^γ against E0(d_m), of each capsule's range, of R, and of the
    critical step, each on its own axis; and the log.  Works live and on a recording:
    a recording carries the same topics (``/lelsonar/energy`` from the acquisition,
    without the critical step, which only a reconstruction finds).  (foxglove-sdk's
    ``foxglove.layouts`` builds the notebook widget's format, not this one.)
    Regenerate the file with ``python -m lelsonar.bridge.foxglove > examples/foxglove-layout.json``.
    """
    import json

    def series(topic: str, field: str, label: str, color: str) -> dict:
        return {
            "value": f"{topic}.{field}",
            "enabled": True,
            "timestampMethod": "receiveTime",
            "label": label,
            "color": color,
        }

    def plot(title: str, paths: list[dict]) -> dict:
        return {
            "paths": paths,
            "showLegend": True,
            "legendDisplay": "floating",
            "showXAxisLabels": True,
            "showYAxisLabels": True,
            "isSynced": True,
            "xAxisVal": "timestamp",
            "foxglovePanelTitle": title,
        }

    scene_topic = {"visible": True}
    config = {
        "3D!lelsonar": {
            "foxglovePanelTitle": "scan",
            "followTf": visual.WORLD_FRAME,
            "followMode": "follow-pose",
            "cameraState": {
                "distance": 5.0,
                "perspective": True,
                "phi": 60.0,
                "thetaOffset": 45.0,
                "target": [0.0, 0.8, 0.5],
                "targetOffset": [0.0, 0.0, 0.0],
                "targetOrientation": [0.0, 0.0, 0.0, 1.0],
                "fovy": 45.0,
                "near": 0.01,
                "far": 5000.0,
            },
            "scene": {"transforms": {"showLabel": True, "axisScale": 0.5}},
            "transforms": {},
            "layers": {
                "grid": {
                    "visible": True,
                    "layerId": "foxglove.Grid",
                    "frameId": visual.WORLD_FRAME,
                    "size": 4,
                    "divisions": 8,
                    "position": [0, 0, 0],
                    "rotation": [0, 0, 0],
                }
            },
            "topics": {
                visual.TOPIC_SCAN_POINTS: {
                    "visible": True,
                    "pointSize": 6,
                    "colorMode": "colormap",
                    "colorField": "step",
                    "colorMap": "turbo",
                },
                # The latest step's points, bigger and white: where the beams land now.
                visual.TOPIC_POINTS: {"visible": True, "pointSize": 12, "colorMode": "flat", "flatColor": "#ffffff"},
                visual.TOPIC_PLANES: scene_topic,
                TOPIC_TRUTH: scene_topic,
                visual.TOPIC_ARRAY: scene_topic,
                TOPIC_MAP_SCENE: scene_topic,
            },
        },
        "Plot!energy": plot(
            "energy E^γ and E0(d_m), V²·s",
            [
                series(visual.TOPIC_ENERGY, "energy", "E^γ", "#1f77b4"),
                series(visual.TOPIC_ENERGY, "expected_energy", "E0(d_m)", "#ff7f0e"),
                # An acquisition recording has no reconstruction, but its own per-step energies:
                series(visual.TOPIC_STEP, "energy", "E^γ (acquisition)", "#9467bd"),
            ],
        ),
        "Plot!ratio": plot("ratio R = E^γ / E0(d_m)", [series(visual.TOPIC_ENERGY, "ratio", "R", "#2ca02c")]),
        "Plot!critical": plot(
            "critical step (step number)",
            [series(visual.TOPIC_ENERGY, "critical_step", "critical step", "#d62728")],
        ),
        "Plot!ranges": plot(
            "ranges per capsule, m",
            [
                series(visual.TOPIC_STEP, f"range.{name}", f"range {name}", color)
                for name, color in zip("ABCD", ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728"))
            ],
        ),
        "RosOut!log": {
            "foxglovePanelTitle": "log",
            "searchTerms": [],
            "minLogLevel": 1,
            "topicToRender": visual.TOPIC_LOG,
        },
    }
    layout = {
        "configById": config,
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1.0},
        "layout": {
            "first": "3D!lelsonar",
            "direction": "row",
            "splitPercentage": 60,
            "second": {
                "first": {"first": "Plot!energy", "second": "Plot!ranges", "direction": "column"},
                "direction": "column",
                "splitPercentage": 40,
                "second": {
                    "first": {"first": "Plot!ratio", "second": "Plot!critical", "direction": "row"},
                    "second": "RosOut!log",
                    "direction": "column",
                    "splitPercentage": 60,
                },
            },
        },
    }
    return json.dumps(layout, indent=2, ensure_ascii=False) + "\n"


if __name__ == "__main__":
    print(layout_json(), end="")


class FoxgloveMapView:
    """Draws each ``Map`` on ``/lelsonar/map/scene`` of a :class:`FoxgloveServer` (the scene a mapper's MCAP
    records), so the map grows live as the mapper fuses scans."""

    def __init__(self, server: FoxgloveServer) -> None:
        self.server = server
        self._scene = MapScene()
        self._lock = threading.Lock()

    def __call__(self, msg: map_pb2.Map, free_space=None) -> None:
        """Draw ``msg``; ``free_space`` (a shapely geometry in the map frame) where the caller has the fusion."""
        with self._lock:
            update = self._scene.update(msg, free_space=free_space)
        self.server.log(TOPIC_MAP_SCENE, update, msg.stamp_ns)


@contextmanager
def open_foxglove_map(address: str) -> Iterator[FoxgloveMapView]:
    """Serve the map on Foxglove at ``[HOST:]PORT`` for the duration of the block."""
    host, port = parse_host_port(address)
    server = FoxgloveServer(host, port, name="lelsonar mapper")
    try:
        yield FoxgloveMapView(server)
    finally:
        server.close()

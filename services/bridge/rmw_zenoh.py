"""ROS 2 topics on Zenoh the way rmw_zenoh puts them, with no ROS install.

Targets ``rmw_zenoh_cpp`` ≥ 0.2.4 (Jazzy) and 0.6 (Kilted), whose design
(ros2/rmw_zenoh ``docs/design.md``, ``liveliness_utils.cpp``,
``attachment_helpers.cpp``) fixes what a publisher must get right:

* **Data key:** ``<domain>/<topic without its leading and trailing slash>/<DDS type>/<RIHS01 hash>``,
  e.g. ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66…``.  A subscriber
  declares the same key, so the type hash must equal the one its ROS 2 build
  computes, or it sees nothing.
* **Liveliness tokens** (the graph: ``ros2 node list``, ``ros2 topic list``):
  a node ``@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>``
  and per publisher
  ``@ros2_lv/<domain>/<zid>/<nid>/<id>/MP/<enclave>/<namespace>/<node>/<topic>/<DDS type>/<hash>/<qos>``,
  every ``/`` inside a chunk mangled to ``%`` and an empty chunk written ``%``.
  The QoS chunk is
  ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<s>,<ns>``
  with every component that equals rmw_zenoh's default (RELIABLE, VOLATILE,
  KEEP_LAST, depth 42, infinite durations, AUTOMATIC) left empty; a non-default
  one is the ``rmw/types.h`` enum value (TRANSIENT_LOCAL = 1).
* **Attachment** on every put, 33 bytes: i64 LE sequence number (per publisher,
  from 1), i64 LE source timestamp (Unix ns), LEB128 length 16 (``0x10``), the
  16-byte publisher GID.  A sample without it is dropped by rmw_zenoh.
* **Payload:** CDR with its 4-byte encapsulation header (``00 01 00 00``), no
  Zenoh encoding.
* **GID:** XXH3-128 (seed 0) of the entity's liveliness token, ``low64`` then
  ``high64``, each little-endian — what rmw_zenoh derives for its own entities
  and for remote ones it learns from tokens (``ros2 topic info -v``).  Stock
  XXH3-128 (PyPI ``xxhash``) equals rmw_zenoh's ``simplified_XXH3_128bits``.

**Publishers** are declared as rmw_zenoh declares its own (``rmw_publisher_data.cpp``): every one
a zenoh-ext ``AdvancedPublisher``; a ``TRANSIENT_LOCAL`` topic (``/tf_static``, the planes, the
estimate) with a cache of ``depth`` samples, publisher detection and, being RELIABLE, sample-miss
detection by sporadic heartbeat every 0.5 s, so a late or lossy subscriber fetches what it lacks;
congestion control DROP for KEEP_LAST (every topic here), so a slow ROS subscriber never stalls the
bridge (BLOCK is for KEEP_ALL, which no topic here uses).  See :func:`publisher_options`.
"""

from __future__ import annotations

import re
import struct
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import xxhash
import zenoh
import zenoh.ext

from lelsonar.bridge import ros2
from lelsonar.errors import ClosedError, ConfigError
from lelsonar.net.transport import TransportError, ZenohSettings, zenoh_reason

ADMIN_SPACE = "@ros2_lv"
RMW_ZENOH_DEFAULT_DEPTH = 42
DURABILITY_TRANSIENT_LOCAL = 1  # rmw/types.h rmw_qos_durability_policy_e
GID_SIZE = 16
#: rmw_zenoh's ``SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD`` (RELIABLE + TRANSIENT_LOCAL publishers), s.
SAMPLE_MISS_HEARTBEAT_PERIOD = 0.5

_NODE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_NAMESPACE = re.compile(r"/|(/[A-Za-z_][A-Za-z0-9_]*)+")
_TOPIC = re.compile(r"(/[A-Za-z_][A-Za-z0-9_]*)+")


@contextmanager
def open_ros_session(settings: ZenohSettings) -> Iterator[zenoh.Session]:
    """A Zenoh session as rmw_zenoh configures its own: the lelsonar settings plus timestamping.

    rmw_zenoh enables ``timestamping`` in both of its default configs, and a zenoh-ext
    AdvancedPublisher (TRANSIENT_LOCAL topics) needs it.
    """
    cfg = settings.to_config()
    cfg.insert_json5("timestamping/enabled", "true")
    try:
        session = zenoh.open(cfg)
    except zenoh.ZError as exc:
        raise TransportError(
            f"cannot open a Zenoh {settings.mode} session: {zenoh_reason(exc)}; is the robot's router "
            f"(ros2 run rmw_zenoh_cpp rmw_zenohd) listening on {', '.join(settings.connect or ('its config file',))}?"
        ) from None
    try:
        yield session
    finally:
        session.close()


def dds_type_name(msgtype: str) -> str:
    """``std_msgs/msg/String`` → ``std_msgs::msg::dds_::String_`` (the name rmw puts in keys)."""
    parts = msgtype.split("/")
    if len(parts) != 3 or not all(parts):
        raise ConfigError(f"a ROS 2 type is package/msg/Name, got {msgtype!r}")
    return f"{parts[0]}::{parts[1]}::dds_::{parts[2]}_"


def mangle(chunk: str) -> str:
    """One liveliness chunk: every ``/`` becomes ``%``; an empty chunk is ``%``."""
    return chunk.replace("/", "%") if chunk else "%"


def topic_key(domain_id: int, topic: str, msgtype: str, type_hash: str) -> str:
    """The data key expression of a topic."""
    name = topic[1:] if topic.startswith("/") else topic
    name = name[:-1] if name.endswith("/") else name
    return f"{domain_id}/{name}/{dds_type_name(msgtype)}/{type_hash}"


def qos_chunk(qos: ros2.TopicQos) -> str:
    """The QoS chunk of a publisher token (RELIABLE, KEEP_LAST, infinite durations, AUTOMATIC)."""
    durability = str(DURABILITY_TRANSIENT_LOCAL) if qos.transient_local else ""
    depth = "" if qos.depth == RMW_ZENOH_DEFAULT_DEPTH else str(qos.depth)
    return f":{durability}:,{depth}:,:,:,,"


def node_token(domain_id: int, zid: str, node_id: int, namespace: str, node: str, enclave: str = "") -> str:
    return f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{node_id}/NN/{mangle(enclave)}/{mangle(namespace)}/{node}"


def publisher_token(
    domain_id: int,
    zid: str,
    node_id: int,
    entity_id: int,
    namespace: str,
    node: str,
    topic: str,
    msgtype: str,
    type_hash: str,
    qos: ros2.TopicQos,
    enclave: str = "",
) -> str:
    return (
        f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{entity_id}/MP/{mangle(enclave)}/{mangle(namespace)}/{node}"
        f"/{mangle(topic)}/{dds_type_name(msgtype)}/{type_hash}/{qos_chunk(qos)}"
    )


def publisher_options(qos: ros2.TopicQos) -> dict:
    """The keyword arguments of ``zenoh.ext.declare_advanced_publisher`` that rmw_zenoh uses for ``qos``.

    Every topic here is RELIABLE and KEEP_LAST: congestion control DROP (rmw_zenoh blocks only for
    KEEP_ALL); TRANSIENT_LOCAL adds the cache of ``depth`` samples, publisher detection and miss
    detection by sporadic heartbeat.
    """
    options: dict = {
        "congestion_control": zenoh.CongestionControl.DROP,
        "reliability": zenoh.Reliability.RELIABLE,
    }
    if qos.transient_local:
        options.update(
            cache=zenoh.ext.CacheConfig(qos.depth),
            publisher_detection=True,
            sample_miss_detection=zenoh.ext.MissDetectionConfig(
                heartbeat=None, sporadic_heartbeat=SAMPLE_MISS_HEARTBEAT_PERIOD
            ),
        )
    return options


def gid_of(token: str) -> bytes:
    """The 16-byte GID rmw_zenoh derives from a liveliness token."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_SIZE, "little")  # low64 LE, high64 LE


def attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The 33-byte rmw_zenoh attachment of one put."""
    if len(gid) != GID_SIZE:
        raise ConfigError(f"a GID has {GID_SIZE} bytes, got {len(gid)}")
    return struct.pack("<qqB", sequence_number, source_timestamp_ns, GID_SIZE) + bytes(gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """``(sequence number, source timestamp ns, gid)`` of an attachment (the inverse of :func:`attachment`)."""
    if len(data) != 33 or data[16] != GID_SIZE:
        raise ConfigError(f"not an rmw_zenoh attachment: {len(data)} bytes")
    seq, ts = struct.unpack_from("<qq", data)
    return seq, ts, bytes(data[17:])


@dataclass
class _Publisher:
    key: str
    token_key: str
    gid: bytes
    msgtype: str
    zpub: zenoh.Publisher | zenoh.ext.AdvancedPublisher
    token: zenoh.LivelinessToken
    seq: int = 1


class RmwZenohNode:
    """One ROS 2 node as rmw_zenoh shows it: a node token and one publisher per topic.

    Parameters
    ----------
    session : zenoh.Session
        Connected to the robot's Zenoh router (``ros2 run rmw_zenoh_cpp rmw_zenohd``).
    name, namespace : str
        The node's name and namespace (``/`` for none).
    domain_id : int
        ``ROS_DOMAIN_ID``.
    """

    def __init__(
        self,
        session: zenoh.Session,
        *,
        name: str = "lelsonar_bridge",
        namespace: str = "/",
        domain_id: int = 0,
        distro: str = "jazzy",
    ) -> None:
        if not _NODE_NAME.fullmatch(name):
            raise ConfigError(f"a ROS 2 node name is letters, digits and _, not starting with a digit; got {name!r}")
        if not _NAMESPACE.fullmatch(namespace):
            raise ConfigError(f"a ROS 2 namespace is / or /a/b; got {namespace!r}")
        if not 0 <= domain_id <= 232:
            raise ConfigError(f"ROS_DOMAIN_ID must be in [0, 232], got {domain_id}")
        if distro != "jazzy":
            raise ConfigError("the live bridge speaks Jazzy/Kilted rmw_zenoh (type hashes); Humble has none")
        self._session = session
        self.name, self.namespace, self.domain_id, self.distro = name, namespace, domain_id, distro
        self.zid = str(session.info.zid())
        self._lock = threading.Lock()
        self._next_id = 0
        self.node_id = self._take_id()
        self.node_token_key = node_token(domain_id, self.zid, self.node_id, namespace, name)
        self._node_token = session.liveliness().declare_token(self.node_token_key)
        self._publishers: dict[str, _Publisher] = {}
        self._closed = False

    def _take_id(self) -> int:
        n = self._next_id
        self._next_id += 1
        return n

    def publisher(self, topic: str, msgtype: str) -> _Publisher:
        """The publisher of ``topic``, declared (key, token, cache) on first use."""
        with self._lock:
            if self._closed:
                raise ClosedError(f"the ROS 2 node {self.name} is closed: {topic} is published no more")
            pub = self._publishers.get(topic)
            if pub is not None:
                if pub.msgtype != msgtype:
                    raise ConfigError(f"{topic} already carries {pub.msgtype}, not {msgtype}")
                return pub
            if not _TOPIC.fullmatch(topic):
                raise ConfigError(f"not a valid absolute ROS 2 topic name: {topic!r}")
            qos = ros2.topic_qos(topic)
            h = ros2.type_hash(msgtype, self.distro)
            key = topic_key(self.domain_id, topic, msgtype, h)
            token_key = publisher_token(
                self.domain_id,
                self.zid,
                self.node_id,
                self._take_id(),
                self.namespace,
                self.name,
                topic,
                msgtype,
                h,
                qos,
            )
            zpub = zenoh.ext.declare_advanced_publisher(self._session, key, **publisher_options(qos))
            token = self._session.liveliness().declare_token(token_key)
            pub = self._publishers[topic] = _Publisher(key, token_key, gid_of(token_key), msgtype, zpub, token)
            return pub

    def publish(self, message: ros2.RosMessage) -> None:
        """Serialise and put one message (callable as a :class:`~lelsonar.bridge.ros2.Ros2View` sink)."""
        pub = self.publisher(message.topic, message.msgtype)
        payload = ros2.serialize(message.message, message.msgtype, self.distro)
        # (Under the lock: a put while close() undeclares its publisher is refused by Zenoh.)
        with self._lock:
            if self._closed:
                raise ClosedError(f"the ROS 2 node {self.name} is closed: {message.topic} is published no more")
            seq = pub.seq
            pub.seq += 1
            pub.zpub.put(payload, attachment=attachment(seq, time.time_ns(), pub.gid))

    @property
    def publishers(self) -> dict[str, _Publisher]:
        return dict(self._publishers)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            for pub in self._publishers.values():
                pub.token.undeclare()
                pub.zpub.undeclare()
            self._publishers.clear()
            self._node_token.undeclare()

    def __enter__(self) -> RmwZenohNode:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

"""``lelsonar recover IN -o OUT``: rewrite what survived of a recording as a valid, indexed MCAP.

Like ``mcap recover``: every intact message (see :mod:`lelsonar.log.reader`)
is written again, with its channel, schema, times and sequence, into a new file
with a summary, chunk indexes and statistics, plus the metadata and
attachments that survived.  The result opens in any indexed reader, in
``rerun`` and in Foxglove.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from lelsonar.errors import RecordingError
from lelsonar.log.reader import Salvage
from lelsonar.log.recording import CHANNEL_METADATA, Recording, open_recording

_COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


@dataclass(frozen=True)
class RecoverReport:
    """What :func:`recover` wrote.

    Attributes
    ----------
    source : Salvage
        The reader's account of the input (damage, orphans).
    messages_written : int
    channels_written : int
    output : Path
    """

    source: Salvage
    messages_written: int
    channels_written: int
    output: Path


def recover(src: Path | str, dst: Path | str, *, compression: str = "zstd") -> RecoverReport:
    """Write every salvageable message of ``src`` to a new, finished MCAP file ``dst``.

    Parameters
    ----------
    src, dst : Path or str
        ``dst`` is written to a temporary name beside it and renamed at the end,
        so an interrupted recover never leaves a half-written output.
    compression : {"zstd", "lz4", "none"}

    Returns
    -------
    RecoverReport

    Raises
    ------
    RecordingError
        ``src`` is missing, a directory or not MCAP (subclasses), ``dst`` is ``src``,
        or ``dst`` cannot be written.
    """
    src, dst = Path(src), Path(dst)
    if compression not in _COMPRESSIONS:
        raise RecordingError(f"compression must be one of {', '.join(_COMPRESSIONS)}, got {compression!r}")
    if dst.exists() and src.exists() and dst.resolve() == src.resolve():
        raise RecordingError(f"recover would overwrite its input {src}; give another output path with -o")
    rec = open_recording(src)  # with lost channel records renamed from the recorder's channel metadata
    tmp = dst.with_name(f".{dst.name}.partial")
    try:
        dst.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            written, channels = _write(rec, f, _COMPRESSIONS[compression])
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, dst)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise RecordingError(f"cannot write {dst}: {exc.strerror or exc}") from None
    return RecoverReport(rec.salvage, written, channels, dst)


def _write(rec: Recording, f, compression: CompressionType) -> tuple[int, int]:
    """Copy every intact message, read chunk by chunk; a channel first seen inside a chunk is written when met."""
    s = rec.salvage
    writer = McapWriter(f, compression=compression)
    writer.start(library="lelsonar recover")
    for name, record in s.metadata.items():
        if not name.startswith(CHANNEL_METADATA):  # channel ids change: written afresh below
            writer.add_metadata(name, record)
    for t_log, t_create, name, media, data in s.attachments:
        writer.add_attachment(create_time=t_create, log_time=t_log, name=name, media_type=media, data=data)
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int | None] = {}

    def channel(cid: int) -> int | None:
        if cid in channel_ids:
            return channel_ids[cid]
        ch = s.channels.get(cid)
        new = None
        if ch is not None:
            schema_id = 0
            schema = s.schemas.get(ch.schema_id) if ch.schema_id else None
            if schema is not None and schema.id not in schema_ids:
                schema_ids[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if schema is not None:
                schema_id = schema_ids[schema.id]
            if schema is not None or not ch.schema_id:  # a lost schema: the messages cannot be decoded by anyone
                new = writer.register_channel(ch.topic, ch.message_encoding, schema_id, dict(ch.metadata))
                if f"{CHANNEL_METADATA}{cid}" in s.metadata:
                    writer.add_metadata(f"{CHANNEL_METADATA}{new}", s.metadata[f"{CHANNEL_METADATA}{cid}"])
        channel_ids[cid] = new
        return new

    for cid in sorted(s.channels):
        channel(cid)
    n = 0
    for m in rec.messages(verify_all=True):
        if m.channel_id not in s.channels:
            continue  # an orphan: its channel is unknown
        new = channel(m.channel_id)
        if new is None:
            continue
        writer.add_message(new, log_time=m.log_time, data=m.data, publish_time=m.publish_time, sequence=m.sequence)
        n += 1
    writer.finish()
    return n, sum(1 for new in channel_ids.values() if new is not None)

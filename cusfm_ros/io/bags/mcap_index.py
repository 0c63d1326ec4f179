"""Messages of chosen topics located through an MCAP file's indexes, read without reading
the chunks around them.

The keyframe stage's first pass needs each image's header stamp, not its pixels, and the
odometry, tf and camera info between the images: through rosbags every chunk holding one of
them was read whole and checksummed (803 MB at 300 stereo street frames, 2.4 of that stage's
3.9 s on 2 cores; for the odometry and camera info alone, 48 of the 123 samples of the
stage's thread on the H100 machine, street 300, 2026-12-07). MCAP's summary lists every
chunk, and each chunk's message index gives every message's offset inside the chunk: in an
uncompressed chunk a message is read from there (for a header stamp, the first 12 bytes of
its CDR payload). The ``mcap`` library parses the records; the byte arithmetic between them
(where a chunk's records start, where a message's payload starts) is the MCAP
specification's, which no library call exposes without reading the whole chunk. Messages
read so are not checked against their chunk's CRC: the second pass, which reads the images
through rosbags, checks every chunk that holds one.

Returns None, for the caller to read the messages as before, wherever the shortcut does not
apply: not MCAP, no summary or chunk index (a truncated or unindexed file), no statistics or
fewer indexed messages than they count, a compressed chunk holding the topic, a message
encoding other than CDR, or an index that points at anything but that channel's message.
"""

from __future__ import annotations

import logging
import os
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

logger = logging.getLogger(__name__)

_MESSAGE_OPCODE = 0x05
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, record length, channel, sequence, times
_MESSAGE_FIELDS = 2 + 4 + 8 + 8  # channel, sequence, log and publish time: before the data
_CHUNK_FIXED = 1 + 8 + 8 + 8 + 8 + 4 + 4  # opcode, length, start/end time, size, crc, str len
_HEADER_BYTES = 12  # CDR encapsulation, then std_msgs/Header's stamp (sec, nanosec)


@dataclass(frozen=True)
class IndexedMessage:
    """Where one message's CDR payload lies in its file."""

    log_time_ns: int
    topic: str
    file: Path
    payload_at: int
    """Byte offset of the payload in ``file``."""
    payload_size: int
    head: bytes
    """The payload's first (up to) 12 bytes: a header's stamp without another read."""


def read_payload(handle, message: IndexedMessage) -> bytes:
    """The message's payload from ``handle`` (an open binary file of ``message.file``);
    ``OSError`` when the file ends before it."""
    data = os.pread(handle.fileno(), message.payload_size, message.payload_at)
    if len(data) != message.payload_size:
        raise OSError(f"{message.file} ends inside a message of {message.topic}")
    return data


def storage_files(path: Path) -> list[Path] | None:
    """The MCAP files of a bag (a ``.mcap`` file, or a rosbag2 directory of MCAP storage
    without file or message compression), in recording order; None otherwise."""
    if path.is_file():
        return [path] if path.suffix == ".mcap" else None
    import yaml

    try:
        info = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        if info.get("storage_identifier") != "mcap" or \
                str(info.get("compression_mode") or "none").lower() != "none":
            return None
        files = [path / Path(name).name for name in info["relative_file_paths"]]
    except (OSError, KeyError, TypeError, AttributeError, yaml.YAMLError):
        return None
    return files if files and all(f.is_file() for f in files) else None


def indexed_messages(files: list[Path], topics: Iterable[str]
                     ) -> list[IndexedMessage] | None:
    """Every message on ``topics`` in ``files``, in the order a reader yields them (log time,
    then place in the recording), located but not read; None where the indexes cannot give
    them (module docstring)."""
    from mcap.exceptions import McapError
    from mcap.reader import SeekingReader
    from mcap.records import MessageIndex
    from mcap.stream_reader import StreamReader

    topics = set(topics)
    found: list[tuple[tuple[int, int, int, int], IndexedMessage]] = []
    try:
        for number, path in enumerate(files):
            with open(path, "rb") as handle:
                summary = SeekingReader(handle).get_summary()
                if summary is None or not summary.chunk_indexes:
                    return None
                channels = {i: c for i, c in summary.channels.items() if c.topic in topics}
                if any(c.message_encoding != "cdr" for c in channels.values()):
                    return None
                # the statistics say how many messages each channel has: a file whose
                # chunks do not index them all is read as before
                counts = summary.statistics.channel_message_counts if summary.statistics \
                    else None
                if counts is None:
                    return None
                indexed = {i: 0 for i in channels}
                for chunk in summary.chunk_indexes:
                    wanted = [i for i in chunk.message_index_offsets if i in channels]
                    if not wanted:
                        continue
                    if chunk.compression:
                        return None
                    records_at = (chunk.chunk_start_offset + _CHUNK_FIXED
                                  + len(chunk.compression.encode()) + 8)
                    for channel in wanted:
                        handle.seek(chunk.message_index_offsets[channel])
                        index = next(StreamReader(handle, skip_magic=True).records)
                        if not isinstance(index, MessageIndex) or index.channel_id != channel:
                            return None
                        for log_time, offset in index.records:
                            at = records_at + offset
                            head = os.pread(handle.fileno(), _MESSAGE_HEAD.size + _HEADER_BYTES,
                                            at)
                            if len(head) < _MESSAGE_HEAD.size:
                                return None
                            opcode, length, channel_id, _, _, _ = _MESSAGE_HEAD.unpack_from(head)
                            if opcode != _MESSAGE_OPCODE or channel_id != channel or \
                                    length < _MESSAGE_FIELDS:
                                return None
                            size = length - _MESSAGE_FIELDS
                            found.append(((log_time, number, chunk.chunk_start_offset, offset),
                                          IndexedMessage(log_time, channels[channel].topic,
                                                         path, at + _MESSAGE_HEAD.size, size,
                                                         head[_MESSAGE_HEAD.size:][:size])))
                            indexed[channel] += 1
                if any(indexed[i] != counts.get(i, 0) for i in channels):
                    return None
    except (OSError, McapError, StopIteration, struct.error, ValueError) as exc:
        logger.debug("MCAP indexes unusable (%s); reading the messages", exc)
        return None
    found.sort(key=lambda entry: entry[0])
    return [message for _, message in found]


def header_stamps(files: list[Path], topics: Iterable[str]) -> dict[str, list[int]] | None:
    """Header stamp (ns) of every message on ``topics`` in ``files``, per topic in the order
    a reader yields them; None where the indexes cannot give them (module docstring)."""
    from cusfm_ros.errors import BagError
    from cusfm_ros.io.bags.messages import header_stamp_from_raw

    topics = set(topics)
    found = indexed_messages(files, topics)
    if found is None:
        return None
    stamps: dict[str, list[int]] = {topic: [] for topic in topics}
    try:
        for message in found:
            stamps[message.topic].append(header_stamp_from_raw(message.head, cdr=True))
    except BagError as exc:  # a payload shorter than a stamp: read the messages instead
        logger.debug("MCAP indexes unusable (%s); reading the messages", exc)
        return None
    return stamps

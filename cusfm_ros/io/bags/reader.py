"""Streaming access to recorded bags through rosbags' ``AnyReader``.

Opens rosbag2 directories (mcap or sqlite3 storage), bare ``.mcap`` / ``.db3`` files and ROS 1
``.bag`` files. Messages are streamed one at a time (a 50 GB bag is never loaded), and errors
from the storage layer become one ``BagError`` naming the bag, the problem and the fix.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cusfm_ros.errors import BagError, one_line
from cusfm_ros.io.bags.messages import header_stamp_from_raw, typestore

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class TopicInfo:
    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class RawMessage:
    topic: str
    msgtype: str
    bag_stamp_ns: int
    """When the recorder received it (not the header stamp)."""
    raw: bytes


class BagReader:
    """``with BagReader(path) as bag: for message in bag.messages([...]): ...``"""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f"{self.path}: no such bag (pass a rosbag2 directory, a .mcap or "
                           ".db3 file, or a ROS 1 .bag file)")
        if self.path.is_file() and self.path.suffix not in (".mcap", ".db3", ".bag"):
            raise BagError(f"{self.path}: unknown bag storage {self.path.suffix!r} "
                           "(supported: rosbag2 directory, .mcap, .db3, ROS 1 .bag)")
        if self.path.is_dir() and not (self.path / "metadata.yaml").is_file():
            raise BagError(f"{self.path}: directory has no metadata.yaml, so it is not a "
                           "rosbag2 recording (for a lone storage file, pass the .mcap/.db3 "
                           "itself; after a crash, `ros2 bag reindex` restores metadata.yaml)")
        self._reader = None

    def __enter__(self) -> BagReader:
        from rosbags.highlevel import AnyReader

        try:
            self._reader = AnyReader([self.path], default_typestore=typestore())
            self._reader.open()
        except Exception as exc:  # rosbags raises many types for broken files
            detail = one_line(str(exc))[:200]  # keep the fix below in view
            raise BagError(f"{self.path}: cannot open the bag ({type(exc).__name__}: {detail}); "
                           "it is corrupt, truncated or of an unknown storage format "
                           "(for rosbag2, `ros2 bag reindex` may repair it)") from None
        return self

    def __exit__(self, *exc_info) -> None:
        if self._reader is not None:
            try:
                self._reader.close()
            except Exception:  # closing a broken bag must not hide the original error
                logger.debug("error while closing %s", self.path, exc_info=True)
            self._reader = None

    @property
    def is_ros2(self) -> bool:
        return bool(self._reader.is2)

    def topics(self) -> dict[str, TopicInfo]:
        out: dict[str, TopicInfo] = {}
        for connection in self._reader.connections:
            previous = out.get(connection.topic)
            count = connection.msgcount + (previous.count if previous else 0)
            out[connection.topic] = TopicInfo(connection.topic, connection.msgtype, count)
        return dict(sorted(out.items()))

    @property
    def start_ns(self) -> int:
        return int(self._reader.start_time)

    @property
    def end_ns(self) -> int:
        return int(self._reader.end_time)

    def messages(self, topics: Iterable[str], *, from_index: bool = False
                 ) -> Iterator[RawMessage]:
        """Every message on ``topics`` in bag order. ``from_index``: on an uncompressed,
        indexed MCAP bag, each message is read alone where the indexes place it
        (``mcap_index``: no chunk read whole, none checked against its CRC), for a few small
        messages between big ones; through rosbags otherwise."""
        wanted = set(topics)
        located = self._located(wanted) if from_index else None
        if located is not None:
            yield from self._read_located(*located)
            return
        connections = [c for c in self._reader.connections if c.topic in wanted]
        count = 0
        try:
            for connection, stamp, raw in self._reader.messages(connections=connections):
                count += 1
                yield RawMessage(connection.topic, connection.msgtype, int(stamp), bytes(raw))
        except BagError:
            raise
        except Exception as exc:
            raise BagError(f"{self.path}: the bag is corrupt or truncated after {count} "
                           f"messages ({type(exc).__name__}: {exc}); re-record or repair it "
                           "(`ros2 bag reindex` for rosbag2)") from None

    def _located(self, topics: set[str]) -> tuple[list, dict[str, str]] | None:
        """The messages on ``topics`` located through the MCAP indexes, and each topic's
        message type; None where the indexes cannot give them or a topic has two types."""
        from cusfm_ros.io.bags.mcap_index import indexed_messages

        types: dict[str, set[str]] = {}
        for connection in self._reader.connections:
            if connection.topic in topics:
                types.setdefault(connection.topic, set()).add(connection.msgtype)
        if any(len(names) != 1 for names in types.values()):
            return None
        files = self._mcap_files()
        located = None if files is None else indexed_messages(files, topics)
        return None if located is None else (located, {t: n.pop() for t, n in types.items()})

    def _read_located(self, located: list, types: dict[str, str]) -> Iterator[RawMessage]:
        from cusfm_ros.io.bags.mcap_index import read_payload

        handles: dict[Path, Any] = {}
        count = 0
        try:
            for message in located:
                handle = handles.get(message.file)
                if handle is None:
                    handle = handles[message.file] = open(message.file, "rb")
                raw = read_payload(handle, message)
                count += 1
                yield RawMessage(message.topic, types[message.topic], message.log_time_ns, raw)
        except OSError as exc:
            raise BagError(f"{self.path}: the bag is corrupt or truncated after {count} "
                           f"messages ({exc}); re-record or repair it (`ros2 bag reindex` "
                           "for rosbag2)") from None
        finally:
            for handle in handles.values():
                handle.close()

    def indexed_header_stamps(self, topics: Iterable[str]) -> dict[str, list[int]] | None:
        """Header stamps of every message on ``topics`` (per topic, in ``messages`` order)
        read from an MCAP bag's indexes, no message read (``mcap_index``); None where the
        bag cannot give them so (``messages`` then)."""
        from cusfm_ros.io.bags.mcap_index import header_stamps

        files = self._mcap_files()
        return None if files is None else header_stamps(files, topics)

    def _mcap_files(self) -> list[Path] | None:
        """The bag's MCAP files, where their indexes may be read (``mcap_index``)."""
        from cusfm_ros.io.bags.mcap_index import storage_files

        return storage_files(self.path) if self.is_ros2 else None

    def deserialize(self, message: RawMessage) -> Any:
        try:
            return self._reader.deserialize(message.raw, message.msgtype)
        except Exception as exc:
            raise BagError(f"{self.path}: cannot decode a {message.msgtype} message on "
                           f"{message.topic} ({type(exc).__name__}: {exc}); the message is "
                           "corrupt or its type definition differs from ROS 2 Jazzy's") from None

    def header_stamp_ns(self, message: RawMessage) -> int:
        """Header stamp without decoding the body (cheap for images)."""
        try:
            return header_stamp_from_raw(message.raw, cdr=self.is_ros2)
        except BagError as exc:
            raise BagError(f"{self.path}: {message.topic}: {exc}") from None

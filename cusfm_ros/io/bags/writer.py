"""Writing rosbag2 recordings (mcap or sqlite3) that ``ros2 bag info/play`` accept.

The bag is written into a temporary directory beside the target and renamed when complete, so
an interrupted run never leaves a bag that looks finished.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability
from rosbags.interfaces import QosTime
from rosbags.rosbag2 import StoragePlugin, Writer

from cusfm_ros.errors import ConfigError
from cusfm_ros.io.atomic import atomic_directory
from cusfm_ros.io.bags.messages import typestore

STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
_INFINITE = QosTime(2147483647, 4294967295)  # how rosbag2 records "default" durations


def qos(latched: bool = False, depth: int = 10) -> Qos:
    """Reliable QoS; ``latched`` adds transient-local durability (as /tf_static needs)."""
    return Qos(QosHistory.KEEP_LAST, 1 if latched else depth, QosReliability.RELIABLE,
               QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
               _INFINITE, _INFINITE, QosLiveliness.AUTOMATIC, _INFINITE, False)


class BagWriter:
    """Context manager: ``with BagWriter(path) as bag: bag.write(topic, type, stamp, msg)``."""

    def __init__(self, path: str | os.PathLike, storage: str = "mcap") -> None:
        if storage not in STORAGES:
            raise ConfigError(f"unknown bag storage {storage!r} (use {', '.join(STORAGES)})")
        self.path = Path(path)
        self.storage = storage
        self._connections: dict[str, Any] = {}
        self._atomic = None
        self._writer: Writer | None = None

    def __enter__(self) -> BagWriter:
        # rosbags names the storage file after the bag directory and creates that directory
        # itself: write to <tmp>/<name>/ so the file is <name>.mcap, then move it into place.
        self._atomic = atomic_directory(self.path)
        self._tmp = self._atomic.__enter__()
        self._writer = Writer(self._tmp / self.path.name, version=9,
                              storage_plugin=STORAGES[self.storage])
        self._writer.open()
        return self

    def add_topic(self, topic: str, msgtype: str, latched: bool = False) -> None:
        self._connections[topic] = self._writer.add_connection(
            topic, msgtype, typestore=typestore(), offered_qos_profiles=[qos(latched)])

    def write(self, topic: str, msgtype: str, stamp_ns: int, message: Any) -> None:
        if topic not in self._connections:
            self.add_topic(topic, msgtype)
        data = typestore().serialize_cdr(message, msgtype)
        self._writer.write(self._connections[topic], int(stamp_ns), data)

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            self._writer.close()
        except BaseException as error:
            self._atomic.__exit__(type(error), error, error.__traceback__)  # drops the temp dir
            raise
        if exc_type is None:
            inner = self._tmp / self.path.name
            for entry in inner.iterdir():
                entry.rename(self._tmp / entry.name)
            inner.rmdir()
        self._atomic.__exit__(exc_type, exc, tb)

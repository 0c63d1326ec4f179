"""A bag's identity for resume decisions: a content hash, not a path or an mtime.

For each storage file (and a rosbag2 directory's ``metadata.yaml``): its name, size and the
sha256 of its first and last MiB — where MCAP keeps its header and its summary/chunk index,
and sqlite3 its header and latest pages — so a copied bag keeps its identity and another
recording, or the same one re-recorded or truncated, gets a new one, without reading
gigabytes on every run.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from cusfm_ros.io.bags.reader import BagReader

_EDGE = 1 << 20


def _file_identity(digest, path: Path) -> None:
    size = path.stat().st_size
    digest.update(f"{path.name}\0{size}\0".encode())
    with open(path, "rb") as handle:
        digest.update(handle.read(_EDGE))
        if size > 2 * _EDGE:
            handle.seek(size - _EDGE)
            digest.update(handle.read(_EDGE))
        elif size > _EDGE:
            digest.update(handle.read())


def bag_identity(path: str | os.PathLike) -> str:
    """Content identity of a rosbag2 directory, .mcap/.db3 file or ROS 1 .bag."""
    path = Path(path)
    BagReader(path)  # the same one-line errors for a missing or unknown bag
    digest = hashlib.sha256()
    files = [path] if path.is_file() else sorted(
        p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))
    for file in files:
        _file_identity(digest, file)
    return digest.hexdigest()

"""Content digests of run-directory artifacts (files and directories), cached by size and
modification time so an unchanged multi-gigabyte store is hashed once, not on every run."""

from __future__ import annotations

import hashlib
import json
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from cusfm_ros.io.atomic import atomic_write

_CHUNK = 1 << 20


def file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


class DigestCache:
    """``digest(path)``: sha256 of a file's bytes, or of a directory's sorted (relative path,
    file digest) list; hidden entries (temporary files) are left out."""

    def __init__(self, cache_file: Path, root: Path) -> None:
        self.cache_file = Path(cache_file)
        self.root = Path(root)
        self._entries: dict[str, dict] = {}
        self._dirty = False
        if self.cache_file.is_file():
            try:
                self._entries = json.loads(self.cache_file.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError, OSError):
                self._entries = {}

    def _file(self, path: Path) -> str:
        stat = path.stat()
        key = os.path.relpath(path, self.root)
        entry = self._entries.get(key)
        if entry and entry["size"] == stat.st_size and entry["mtime_ns"] == stat.st_mtime_ns:
            return entry["sha256"]
        value = file_digest(path)
        self._entries[key] = {"size": stat.st_size, "mtime_ns": stat.st_mtime_ns,
                              "sha256": value}
        self._dirty = True
        return value

    def digest(self, path: Path) -> str | None:
        path = Path(path)
        if path.is_file():
            return self._file(path)
        if not path.is_dir():
            return None
        names = []
        for folder, dirs, files in os.walk(path):
            dirs[:] = sorted(d for d in dirs if not d.startswith("."))
            names += [Path(folder) / name for name in sorted(f for f in files
                                                             if not f.startswith("."))]
        # hashlib releases the GIL on large buffers: a folder of keyframe images (2 GB at
        # 1000 stereo frames) is hashed on several threads, each file as before
        with ThreadPoolExecutor(min(8, os.cpu_count() or 1)) as pool:
            file_digests = list(pool.map(self._file, names))
        digest = hashlib.sha256()
        for full, value in zip(names, file_digests):
            digest.update(os.path.relpath(full, path).encode() + b"\0")
            digest.update(value.encode() + b"\n")
        return digest.hexdigest()

    @property
    def entries(self) -> dict[str, dict]:
        """Every file's known digest (relative path -> size, mtime_ns, sha256): what another
        process's cache of the same run directory can ``learn``."""
        return dict(self._entries)

    def learn(self, entries: dict[str, dict]) -> None:
        """Take the digests another process's cache of this run directory computed (a forked
        stage's outputs); a file changed since is hashed again, as ever, by size and mtime."""
        if entries != self._entries:
            self._entries.update(entries)
            self._dirty = True

    def save(self) -> None:
        if self._dirty:
            with atomic_write(self.cache_file) as handle:
                json.dump(self._entries, handle)
            self._dirty = False

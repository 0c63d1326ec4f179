"""``pairs.txt``: one image pair per line, two image names separated by a space (hloc's and
COLMAP's pair-list format)."""

from __future__ import annotations

import os
from pathlib import Path

from cusfm_ros.errors import FormatError
from cusfm_ros.io.atomic import atomic_write


def write_pairs(path: str | os.PathLike, pairs: list[tuple[str, str]]) -> None:
    for a, b in pairs:
        if not a or not b or any(c.isspace() for c in a + b):
            raise FormatError(path, None, f"image names with spaces cannot be listed: {a!r} "
                              f"{b!r}")
    with atomic_write(path) as handle:
        handle.writelines(f"{a} {b}\n" for a, b in pairs)


def read_pairs(path: str | os.PathLike) -> list[tuple[str, str]]:
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, None, "no such file", "run the pairs stage")
    pairs = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 2:
            raise FormatError(path, str(number), f"expected two image names, got {line!r}")
        pairs.append((parts[0], parts[1]))
    return pairs

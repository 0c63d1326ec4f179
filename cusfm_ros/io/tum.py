"""TUM trajectory files: ``stamp tx ty tz qx qy qz qw`` per line, ``world_from_body``.

Stamps are seconds as decimal text; they are parsed exactly into integer nanoseconds (no float
round-off) and written with nine decimals, so stamps and translations round-trip exactly;
quaternions pass through a rotation matrix and come back to within 1e-15.
"""

from __future__ import annotations

import os
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from cusfm_ros.core.geometry import (QUAT_NORM_TOLERANCE, matrices_from_quat_xyzw,
                                     matrices_to_quat_xyzw)
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import FormatError
from cusfm_ros.io.atomic import atomic_write


def parse_stamp_ns(text: str) -> int:
    """Decimal seconds text -> integer nanoseconds, rounding beyond 1 ns."""
    value = Decimal(text)
    if not value.is_finite():
        raise InvalidOperation
    return int((value * 1_000_000_000).to_integral_value())


def format_stamp(stamp_ns: int) -> str:
    sign = "-" if stamp_ns < 0 else ""
    seconds, nanos = divmod(abs(int(stamp_ns)), 1_000_000_000)
    return f"{sign}{seconds}.{nanos:09d}"


def read_tum(path: str | os.PathLike) -> Trajectory:
    """Read a TUM file, rejecting malformed lines, NaN/inf, non-unit quaternions and
    duplicate or decreasing stamps with a ``FormatError`` naming the file and line."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, None, "no such file")
    stamps: list[int] = []
    rows: list[list[float]] = []
    previous_line = 0
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise FormatError(path, None, "not a text file", "a TUM file has lines 'stamp tx ty "
                          "tz qx qy qz qw'") from None
    for line_number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        where = f"line {line_number}"
        if len(fields) != 8:
            raise FormatError(path, where, f"expected 8 fields 'stamp tx ty tz qx qy qz qw', "
                              f"found {len(fields)}")
        try:
            stamp = parse_stamp_ns(fields[0])
            values = [float(v) for v in fields[1:]]
        except (InvalidOperation, ValueError):
            raise FormatError(path, where, f"non-numeric field in {line!r}") from None
        if not np.all(np.isfinite(values)):
            raise FormatError(path, where, "pose contains NaN or inf")
        if not -2**62 < stamp < 2**62:
            raise FormatError(path, where, f"stamp {fields[0]} s is out of range",
                              "TUM stamps are seconds (nanoseconds written as seconds?)")
        norm = float(np.linalg.norm(values[3:]))
        if abs(norm - 1.0) > QUAT_NORM_TOLERANCE:
            raise FormatError(path, where, f"quaternion norm is {norm:.6g}, not 1",
                              "write unit quaternions qx qy qz qw")
        if stamps and stamp <= stamps[-1]:
            kind = "duplicate" if stamp == stamps[-1] else "decreasing"
            raise FormatError(path, where, f"{kind} stamp {fields[0]} after line "
                              f"{previous_line}", "stamps must be strictly increasing")
        stamps.append(stamp)
        rows.append(values)
        previous_line = line_number
    if not rows:
        raise FormatError(path, None, "contains no poses")
    data = np.asarray(rows)
    return Trajectory(np.asarray(stamps, dtype=np.int64),
                      matrices_from_quat_xyzw(data[:, :3], data[:, 3:]))


__all__ = ["Trajectory", "format_stamp", "format_tum", "parse_stamp_ns", "read_tum",
           "write_tum"]


def format_tum(trajectory: Trajectory) -> str:
    translations, quats = matrices_to_quat_xyzw(trajectory.world_from_body)
    lines = []
    for stamp, t, q in zip(trajectory.stamps_ns, translations, quats):
        values = " ".join(repr(float(v)) for v in (*t, *q))
        lines.append(f"{format_stamp(stamp)} {values}\n")
    return "".join(lines)


def write_tum(path: str | os.PathLike, trajectory: Trajectory) -> None:
    text = format_tum(trajectory)
    with atomic_write(path) as handle:
        handle.write(text)

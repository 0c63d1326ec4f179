"""PLY point clouds: binary little-endian ``x y z`` (double) + ``red green blue`` (uchar).

The reader accepts any vertex layout of scalar properties (float or double positions, optional
colours) in binary little-endian or ASCII, which covers what COLMAP, Open3D and CloudCompare
write; faces and other elements after the vertices are ignored.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cusfm_ros.errors import FormatError
from cusfm_ros.io.atomic import atomic_write

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def write_ply(path: str | os.PathLike, points_m: np.ndarray, rgb: np.ndarray | None = None
              ) -> None:
    """Write (N, 3) points and optional (N, 3) uint8 colours."""
    points = np.asarray(points_m, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise FormatError(path, None, f"points must be (N, 3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise FormatError(path, None, "points contain NaN or inf; refusing to write")
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if rgb is not None:
        rgb = np.asarray(rgb)
        if rgb.shape != points.shape:
            raise FormatError(path, None, f"colours must be (N, 3) like the points, got "
                              f"{rgb.shape}")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertices = np.empty(len(points), dtype=fields)
    vertices["x"], vertices["y"], vertices["z"] = points.T
    header = ["ply", "format binary_little_endian 1.0", "comment written by cusfm_ros",
              f"element vertex {len(points)}", "property double x", "property double y",
              "property double z"]
    if rgb is not None:
        vertices["red"], vertices["green"], vertices["blue"] = rgb.astype(np.uint8).T
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header.append("end_header")
    with atomic_write(path, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii"))
        handle.write(vertices.tobytes())


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a PLY point cloud -> (N, 3) float64 points and (N, 3) uint8 colours or None."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, None, "no such file")
    with open(path, "rb") as handle:
        if handle.readline().strip() != b"ply":
            raise FormatError(path, "line 1", "not a PLY file (missing 'ply' magic)")
        fmt, count, fields, element = None, None, [], None
        line_number = 1
        while True:
            raw = handle.readline()
            line_number += 1
            if not raw:
                raise FormatError(path, None, "header has no 'end_header'")
            words = raw.decode("ascii", errors="replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                element = words[1]
                if element == "vertex":
                    count = int(words[2])
            elif words[0] == "property" and element == "vertex":
                if words[1] == "list":
                    raise FormatError(path, f"line {line_number}", "list properties in "
                                      "vertices are not supported")
                if words[1] not in _PLY_TYPES:
                    raise FormatError(path, f"line {line_number}", f"unknown type {words[1]}")
                fields.append((words[2], _PLY_TYPES[words[1]]))
        names = [name for name, _ in fields]
        if count is None or not {"x", "y", "z"} <= set(names):
            raise FormatError(path, None, "no vertex element with x, y, z properties")
        if fmt == "binary_little_endian":
            dtype = np.dtype([(n, "<" + t) for n, t in fields])
            data = handle.read(dtype.itemsize * count)
            if len(data) != dtype.itemsize * count:
                raise FormatError(path, None, f"file is truncated: header promises {count} "
                                  f"vertices")
            vertices = np.frombuffer(data, dtype=dtype)
        elif fmt == "ascii":
            rows = [handle.readline().split() for _ in range(count)]
            if any(len(r) < len(fields) for r in rows):
                raise FormatError(path, None, "file is truncated or a vertex line is short")
            dtype = np.dtype([(n, t) for n, t in fields])
            vertices = np.array([tuple(r[:len(fields)]) for r in rows], dtype=dtype)
        else:
            raise FormatError(path, None, f"unsupported PLY format {fmt!r}")
    points = np.stack([vertices[a].astype(np.float64) for a in "xyz"], axis=1)
    rgb = None
    if {"red", "green", "blue"} <= set(names):
        rgb = np.stack([vertices[c] for c in ("red", "green", "blue")], axis=1).astype(np.uint8)
    return points, rgb

"""Bundle Adjustment in the Large (BAL) text files: a header ``C P M``, M lines ``camera point
u v``, then 9 values per camera and 3 per point, one per line
(https://grail.cs.washington.edu/projects/bal/)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cusfm_ros.core.mapping.bal_model import BalProblem
from cusfm_ros.errors import ConfigError, CusfmError
from cusfm_ros.io.atomic import atomic_write


def read_bal(path: str | os.PathLike) -> BalProblem:
    path = Path(path)
    try:
        tokens = path.read_text().split()
    except (OSError, UnicodeDecodeError) as exc:
        raise CusfmError(f"{path}: cannot read a BAL problem ({exc})") from None
    try:
        c, p, m = (int(t) for t in tokens[:3])
        expected = 3 + 4 * m + 9 * c + 3 * p
        if c < 1 or p < 1 or m < 1 or len(tokens) != expected:
            raise ValueError(f"header says {c} cameras, {p} points, {m} observations: "
                             f"{expected} values expected, found {len(tokens)}")
        obs = np.array(tokens[3:3 + 4 * m], dtype=np.float64).reshape(m, 4)
        values = np.array(tokens[3 + 4 * m:], dtype=np.float64)
    except ValueError as exc:
        raise CusfmError(f"{path}: not a BAL problem ({exc})") from None
    if not np.all(np.isfinite(values)) or not np.all(np.isfinite(obs)):
        raise CusfmError(f"{path}: the BAL problem holds NaN or inf")
    try:
        return BalProblem(values[:9 * c].reshape(c, 9), values[9 * c:].reshape(p, 3),
                          obs[:, 0].astype(np.int64), obs[:, 1].astype(np.int64), obs[:, 2:])
    except ConfigError as exc:
        raise CusfmError(f"{path}: {exc}") from None


def write_bal(problem: BalProblem, path: str | os.PathLike) -> None:
    """Round trip exact: values are written with 17 significant digits."""
    lines = [f"{len(problem.cameras)} {len(problem.points3d_in_world)} "
             f"{len(problem.obs_camera)}"]
    lines += [f"{c} {p} {u:.17g} {v:.17g}" for c, p, (u, v) in
              zip(problem.obs_camera, problem.obs_point, problem.obs_uv_px)]
    lines += [f"{value:.17g}" for value in problem.cameras.ravel()]
    lines += [f"{value:.17g}" for value in problem.points3d_in_world.ravel()]
    with atomic_write(path) as handle:
        handle.write("\n".join(lines) + "\n")

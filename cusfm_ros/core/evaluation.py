"""Trajectory accuracy: absolute trajectory error (ATE) with evo's conventions.

Association (nearest stamp within ``max_diff_s``, starting from the trajectory with fewer poses,
ties to the earlier stamp), Umeyama alignment of the estimate onto the reference and the
statistics match ``evo_ape tum REF EST -a`` (``-as`` for Sim(3)); a test cross-checks evo.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from cusfm_ros.core.geometry import Sim3, umeyama_alignment
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import ConfigError, EvaluationError, GeometryError

ALIGNMENTS = ("se3", "sim3", "none")


@dataclass(frozen=True)
class AteOptions:
    align: str = "se3"
    """``se3`` (rigid, default as in evo -a), ``sim3`` (with scale, evo -as) or ``none``."""
    max_diff_s: float = 0.01
    """Largest stamp difference for two poses to be associated (evo's default)."""

    def __post_init__(self) -> None:
        if self.align not in ALIGNMENTS:
            raise ConfigError(f"unknown alignment {self.align!r} (use {', '.join(ALIGNMENTS)})")
        if not 0 <= self.max_diff_s < 1e6:
            raise ConfigError(f"max_diff_s must be finite and >= 0 (seconds), got "
                              f"{self.max_diff_s}")


@dataclass
class AteResult:
    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    n: int
    alignment: Sim3 = field(repr=False)
    errors_m: np.ndarray = field(repr=False)

    def stats(self) -> dict[str, float | int]:
        """The JSON-facing statistics (metres), keys as ``cusfm evaluate --json`` prints."""
        keys = ("rmse", "mean", "median", "std", "min", "max", "n")
        values = asdict(self)
        return {k: values[k] for k in keys}


def associate(reference_stamps_ns: np.ndarray, estimate_stamps_ns: np.ndarray,
              max_diff_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (reference, estimate) of associated poses, as evo's ``associate_trajectories``.

    For every stamp of the shorter trajectory (the first one on equal lengths) the nearest stamp
    of the other is taken if within ``max_diff_s``; on a tie the earlier stamp wins.
    """
    ref = np.asarray(reference_stamps_ns, dtype=np.int64)
    est = np.asarray(estimate_stamps_ns, dtype=np.int64)
    max_diff_ns = int(round(max_diff_s * 1e9))
    second_longer = len(est) > len(ref)
    short, long_ = (ref, est) if second_longer else (est, ref)
    in_range = (short >= long_[0] - max_diff_ns) & (short <= long_[-1] + max_diff_ns)
    upper = np.minimum(np.searchsorted(long_, short, side="right"), len(long_) - 1)
    diff_upper = long_[upper] - short
    lower = np.maximum(upper - 1, 0)
    diff_lower = np.where(upper > 0, short - long_[lower], np.iinfo(np.int64).max)
    take_upper = (diff_upper <= max_diff_ns) & (diff_upper < diff_lower)
    take_lower = ~take_upper & (diff_lower <= max_diff_ns) & (diff_lower <= diff_upper)
    matched = in_range & (take_upper | take_lower)
    short_idx = np.nonzero(matched)[0]
    long_idx = np.where(take_upper, upper, lower)[matched]
    return (short_idx, long_idx) if second_longer else (long_idx, short_idx)


def absolute_trajectory_error(reference: Trajectory, estimate: Trajectory,
                              options: AteOptions = AteOptions()) -> AteResult:
    """ATE of ``estimate`` against ``reference`` on positions (metres)."""
    ref_idx, est_idx = associate(reference.stamps_ns, estimate.stamps_ns, options.max_diff_s)
    n = len(ref_idx)
    if n == 0:
        raise EvaluationError(
            f"no stamps of the two trajectories lie within {options.max_diff_s} s of each "
            "other; check that both use the same clock, or raise --max-diff")
    ref_positions = reference.positions_m[ref_idx]
    est_positions = estimate.positions_m[est_idx]
    if options.align == "none":
        alignment = Sim3(np.eye(3), np.zeros(3), 1.0)
    else:
        if n < 3:
            raise EvaluationError(f"only {n} associated poses: alignment needs at least 3 "
                                  "(or use --align none)")
        try:
            alignment = umeyama_alignment(est_positions, ref_positions,
                                          with_scale=options.align == "sim3")
        except GeometryError as exc:
            raise EvaluationError(f"{exc}; use --align none for such trajectories") from None
    errors = np.linalg.norm(ref_positions - alignment.transform_points(est_positions), axis=1)
    return AteResult(rmse=float(np.sqrt(np.mean(errors**2))), mean=float(np.mean(errors)),
                     median=float(np.median(errors)), std=float(np.std(errors)),
                     min=float(np.min(errors)), max=float(np.max(errors)), n=int(n),
                     alignment=alignment, errors_m=errors)

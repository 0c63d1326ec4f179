"""The ``CusfmError`` hierarchy.

Every error a user can fix (bad input, missing calibration, bad options) is a subclass of
``CusfmError``. Its message names the problem *and* the fix; the CLI prints it on one line and
exits with status 1. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


def one_line(text: str) -> str:
    """Whitespace folded: a library's multi-line text (a message definition, a YAML excerpt)
    quoted in an error stays on one line."""
    return " ".join(text.split())


class CusfmError(Exception):
    """Base class of all user-facing errors; printed on one line wherever it is printed (the
    CLI, the ROS nodes, the mapper worker)."""

    def __str__(self) -> str:
        return one_line(super().__str__())


class ConfigError(CusfmError):
    """Invalid options, unknown configuration keys, bad command-line values."""


class GeometryError(CusfmError):
    """Invalid geometric input: NaN/inf poses, non-unit quaternions, degenerate alignment."""


class CalibrationError(CusfmError):
    """Missing or invalid camera calibration (unknown model, missing parameters, bad size)."""


class FormatError(CusfmError):
    """A file does not follow its format. The message names the file and the line or field."""

    def __init__(self, path: object, where: str | None, problem: str, fix: str | None = None):
        location = f"{path}" if where is None else f"{path}:{where}"
        message = f"{location}: {problem}"
        if fix:
            message += f" ({fix})"
        super().__init__(message)
        self.path = path
        self.where = where
        self.problem = problem


class BagError(CusfmError):
    """A bag cannot be read or lacks what the mapper needs (topics, calibration, poses)."""


class BadFrameError(BagError):
    """One image message cannot be decoded (corrupt or truncated data)."""


class EvaluationError(CusfmError):
    """Trajectories cannot be compared (no associated stamps, degenerate alignment)."""


class MappingError(CusfmError):
    """Mapping failed (too few matches, disconnected view graph, diverging optimization)."""


class LocalizationError(CusfmError):
    """A query cannot be localized (unusable map, wrong camera, too few correspondences)."""

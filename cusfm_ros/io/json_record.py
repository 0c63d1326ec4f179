"""Reading the project's versioned JSON records (``{"format": "cusfm_xxx/N", ...}``) with one
clear error for a missing, unreadable or foreign file."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from cusfm_ros.errors import FormatError


def read_json_record(path: str | os.PathLike, format_name: str, stage: str) -> dict[str, Any]:
    """The parsed record; ``stage`` names the stage that writes it (for the fix)."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, None, "no such file", f"run the {stage} stage")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FormatError(path, None, f"invalid JSON ({exc})",
                          f"rerun the {stage} stage with --overwrite") from None
    if not isinstance(data, dict) or data.get("format") != format_name:
        raise FormatError(path, "format", f"expected {format_name!r}",
                          f"rerun the {stage} stage with --overwrite")
    return data

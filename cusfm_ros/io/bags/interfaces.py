"""The ``cusfm_ros_interfaces`` definitions (``MapInfo``, ``LocalizeImage``) for the rosbags
typestore, read from the same ``msg_schemas/`` files colcon builds the package from.

rosbags' ``.msg`` parser does not take ``/srv/`` names, so a service's request and response
are parsed under ``/msg/`` names and registered under ``/srv/Name_Request`` and
``/srv/Name_Response`` — the names and RIHS01 hashes rosidl gives them.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

PACKAGE = "cusfm_ros_interfaces"


def schema_dirs() -> list[Path]:
    """Where the definitions are: the source tree, a pip install (share/cusfm_ros), a colcon
    install of either package (AMENT_PREFIX_PATH)."""
    here = Path(__file__).resolve()
    dirs = [here.parents[3] / "msg_schemas",
            Path(sys.prefix) / "share" / "cusfm_ros" / "msg_schemas"]
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            dirs += [Path(prefix) / "share" / PACKAGE,
                     Path(prefix) / "share" / "cusfm_ros" / "msg_schemas"]
    return dirs


def _find(kind: str, name: str) -> Path | None:
    for folder in schema_dirs():
        path = folder / kind / f"{name}.{kind}"
        if path.is_file():
            return path
    return None


def interface_types() -> dict:
    """rosbags type definitions of every interface whose file is found (an install without
    the files registers none; using such a type then fails with rosbags' unknown-type
    error)."""
    from rosbags.typesys import get_types_from_msg

    types: dict = {}
    message = _find("msg", "MapInfo")
    if message is not None:
        types.update(get_types_from_msg(message.read_text(), f"{PACKAGE}/msg/MapInfo"))
    service = _find("srv", "LocalizeImage")
    if service is not None:
        request, _, response = service.read_text().partition("\n---")
        for part, text in (("Request", request), ("Response", response)):
            parsed = get_types_from_msg(text, f"{PACKAGE}/msg/LocalizeImage_{part}")
            for key, value in parsed.items():
                types[key.replace(f"{PACKAGE}/msg/LocalizeImage_",
                                  f"{PACKAGE}/srv/LocalizeImage_")] = value
    return types

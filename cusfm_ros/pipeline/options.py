"""``MapperOptions`` and the one option resolver every command and node uses.

``MapperOptions`` has four top-level values set once and handed down to every component
that needs them — ``seed`` (every random choice), ``device`` (auto | cpu | cuda),
``frame_type`` (rig | camera: pose graph and bundle adjustment variables) and
``cpu_threads`` (threads for the per-pair work; 0: every core; no result depends on it) —
and one section
per option dataclass that a registered stage owns (``keyframes``, ``features``, ...): the
fields come from the registry, so a new stage's options need no edit here.

``resolve_options(preset, overrides)``: preset (YAML file or mapping) < overrides (dotted keys
from the command line or ROS parameters). ``SWITCHES`` names the command-line switches and
node parameters and the option each one sets, so the CLI and the node cannot disagree.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

from cusfm_ros.errors import ConfigError
from cusfm_ros.pipeline.components import DEVICES
from cusfm_ros.pipeline.config import load_config, merge, options_from_dict
from cusfm_ros.pipeline.registry import STAGES

FRAME_TYPES = ("rig", "camera")
HANDED_DOWN = {
    "seed": "set `seed` once at the top level of the options; it is handed down to every "
            "component",
    "device": "set `device` once at the top level of the options (auto | cpu | cuda)",
    "frame_type": "set `frame_type` once at the top level of the options (rig | camera)",
    "cpu_threads": "set `cpu_threads` once at the top level of the options (0: every core)",
}


def _sections() -> dict[str, type]:
    sections: dict[str, type] = {}
    for stage in STAGES:
        for name, cls in stage.sections.items():
            if name in sections and sections[name] is not cls:
                raise RuntimeError(f"option section {name} is declared by two stages")
            sections[name] = cls
    return sections


SECTIONS = _sections()


def _validate(self) -> None:
    if self.frame_type not in FRAME_TYPES:
        raise ConfigError(f"frame_type must be rig or camera, got {self.frame_type!r}")
    if self.device not in DEVICES:
        raise ConfigError(f"device must be one of {', '.join(DEVICES)}, got {self.device!r}")
    if self.seed < 0:
        raise ConfigError(f"seed must be >= 0, got {self.seed}")
    if self.cpu_threads < 0:
        raise ConfigError(f"cpu_threads must be >= 0 (0: every core), got {self.cpu_threads}")
    if self.mapping.optimize_extrinsics and self.frame_type != "rig":
        raise ConfigError("--optimize-extrinsics needs --frame-type rig (extrinsics are the "
                          "rig's)")


MapperOptions = dataclasses.make_dataclass(
    "MapperOptions",
    [("seed", int, dataclasses.field(default=0)),
     ("device", str, dataclasses.field(default="auto")),
     ("frame_type", str, dataclasses.field(default="rig")),
     ("cpu_threads", int, dataclasses.field(default=0))]
    + [(name, cls, dataclasses.field(default_factory=cls)) for name, cls in SECTIONS.items()],
    frozen=True, namespace={"__post_init__": _validate, "__module__": __name__,
                            "__doc__": "Every option of the mapper (see the module doc)."})

SWITCHES: dict[str, tuple[str, ...]] = {
    # name (CLI dest / node parameter): option paths it sets
    "seed": ("seed",), "device": ("device",), "frame_type": ("frame_type",),
    "cpu_threads": ("cpu_threads",),
    "image_topics": ("keyframes.image_topics",), "pose_source": ("keyframes.pose_source",),
    "odom_topic": ("keyframes.odom_topic",), "world_frame": ("keyframes.world_frame",),
    "base_frame": ("keyframes.base_frame",), "extrinsics": ("keyframes.extrinsics_file",),
    "sync_tolerance_ms": ("keyframes.sync_tolerance_ms",),
    "skip_bad_frames": ("keyframes.skip_bad_frames",),
    "min_translation_m": ("keyframes.min_translation_m",),
    "min_rotation_deg": ("keyframes.min_rotation_deg",),
    "features": ("features.extractor.name",), "matcher": ("features.matcher.name",),
    "max_keypoints": ("features.extractor.aliked.max_keypoints",
                      "features.extractor.sift.max_keypoints",
                      "features.extractor.xfeat.max_keypoints"),
    "resize_max_px": ("features.extractor.aliked.resize_max_px",
                      "features.extractor.sift.resize_max_px"),
    "matcher_depth_confidence": ("features.matcher.lightglue.depth_confidence",
                                 "features.matcher.lighterglue.depth_confidence"),
    "matcher_width_confidence": ("features.matcher.lightglue.width_confidence",
                                 "features.matcher.lighterglue.width_confidence"),
    "backend": ("features.backend",), "model_dir": ("features.model_dir",),
    "vocab_method": ("vocabulary.method",), "retrieval": ("pairs.mode",),
    "optimize_extrinsics": ("mapping.optimize_extrinsics",),
    "rolling_shutter_line_delay_s": ("mapping.rolling_shutter_line_delay_s",),
    "colmap_binary": ("export.colmap_binary",), "rgb": ("export.rgb",),
}


def switch_overrides(values: dict[str, Any]) -> dict[str, Any]:
    """Dotted option overrides from switch values; None means "not given"."""
    out = {}
    for name, value in values.items():
        if value is None:
            continue
        if name not in SWITCHES:
            raise ConfigError(f"unknown switch {name!r} (known: {', '.join(SWITCHES)})")
        for path in SWITCHES[name]:
            out[path] = list(value) if isinstance(value, tuple) else value
    return out


def set_overrides(pairs: list[str], what: str = "--set") -> dict[str, Any]:
    """Dotted overrides from ``KEY=VALUE`` items, the value in YAML (``loops.top_k=10``)."""
    import yaml

    out = {}
    for item in pairs:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"{what} {item!r}: expected KEY=VALUE (e.g. loops.top_k=10)")
        try:
            out[key.strip()] = yaml.safe_load(value)
        except yaml.YAMLError:
            raise ConfigError(f"{what} {item!r}: the value is not valid YAML") from None
    return out


def _check_reserved(data: dict[str, Any]) -> None:
    """Raise for a handed-down key inside a section (``loops.seed``)."""
    def walk(node: Any, path: str) -> None:
        if not isinstance(node, dict):
            return
        for key, value in node.items():
            if key in HANDED_DOWN:
                raise ConfigError(f"{path}.{key}: {HANDED_DOWN[key]}")
            walk(value, f"{path}.{key}")
    for name, section in data.items():
        if name in SECTIONS:
            walk(section, name)


def _build(data: dict[str, Any], where: str):
    try:
        top = ("seed", "device", "frame_type", "cpu_threads")
        unknown = sorted(set(data) - {*top, *SECTIONS})
        if unknown:
            raise ConfigError(f"unknown section(s) {unknown} (known: {', '.join(top)}, "
                              f"{', '.join(SECTIONS)})")
        _check_reserved(data)
        return options_from_dict(MapperOptions, data, "")
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


DEFAULT_MATCHER = {"aliked": "lightglue", "sift": "knn", "xfeat": "lighterglue"}


def _matcher_default(data: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """An extractor chosen without a matcher gets its own (LightGlue's weights are ALIKED's,
    LighterGlue's XFeat's):
    one named in ``overrides`` replaces the preset's matcher; one in the preset alone fills
    in a missing matcher name."""
    name = overrides.get("features.extractor.name")
    if name in DEFAULT_MATCHER and "features.matcher.name" not in overrides:
        return merge(data, {"features.matcher.name": DEFAULT_MATCHER[name]})
    features = data.get("features")
    extractor = features.get("extractor") if isinstance(features, dict) else None
    matcher = features.get("matcher") if isinstance(features, dict) else None
    if isinstance(extractor, dict) and extractor.get("name") in DEFAULT_MATCHER and not (
            isinstance(matcher, dict) and "name" in matcher):
        return merge(data, {"features.matcher.name": DEFAULT_MATCHER[extractor["name"]]})
    return data


def resolve_options(preset: str | os.PathLike | dict | None = None,
                    overrides: dict[str, Any] | None = None,
                    overrides_source: str = "command line"):
    """``MapperOptions`` from a preset (YAML path or mapping) and dotted-key overrides.
    Errors name where the bad value came from (the preset file, or ``overrides_source``)."""
    if preset is None:
        data, where = {}, "defaults"
    elif isinstance(preset, dict):
        data, where = preset, "options"
    else:
        data, where = load_config(preset), str(preset)
    overrides = dict(overrides or {})
    _build(_matcher_default(data, {}), where)  # the preset alone must be valid
    merged = _matcher_default(merge(data, overrides), overrides)
    return _build(merged, overrides_source if overrides else where)


def preset_path(name: str) -> Path:
    """A shipped preset (``av.yaml``...) from the source tree, a pip install (share/) or a
    colcon install (share/cusfm_ros/config)."""
    import sys

    here = Path(__file__).resolve()
    candidates = [here.parents[2] / "config" / name,
                  Path(sys.prefix) / "share" / "cusfm_ros" / "config" / name]
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            candidates.append(Path(prefix) / "share" / "cusfm_ros" / "config" / name)
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise ConfigError(f"preset {name} not found (looked in {', '.join(map(str, candidates))})")

"""ROS parameters of the nodes, as data (no rclpy): name, type, default, description, read-only.

The mapper's switch parameters are ``pipeline.options.SWITCHES`` — the same table the ``cusfm``
command line uses — typed from the option each one sets; a switch left unset keeps the
preset's value. ``parameter_error`` turns rclpy's type complaint into one line naming the
parameter, the type it wants and how to write it.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass
from typing import Any

from cusfm_ros.errors import ConfigError

KINDS = ("bool", "integer", "double", "string", "string_array", "integer_array",
         "double_array")
_EXAMPLES = {"bool": "true", "integer": "3", "double": "0.0", "string": "text",
             "string_array": "'[a, b]'", "integer_array": "'[1, 2]'",
             "double_array": "'[0.5, 1.0]'"}
_NAMES = {"bool": "true or false", "integer": "an integer", "double": "a floating-point "
          "number (write 0.0, not 0)", "string": "a string", "string_array": "a list of "
          "strings", "integer_array": "a list of integers", "double_array": "a list of numbers"}


@dataclass(frozen=True)
class ParameterSpec:
    name: str
    kind: str
    description: str
    default: Any = None
    """None: declared without a value (unset unless given)."""
    read_only: bool = True

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"parameter {self.name}: unknown kind {self.kind}")

    @property
    def example(self) -> str:
        return f"-p {self.name}:={_EXAMPLES[self.kind]}"


def kind_of(hint: Any) -> str:
    """The ROS parameter type of an option's type hint."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        hint = next(a for a in args if a is not type(None))
        origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is tuple:
        inner = kind_of(args[0]) if args else "string"
        return f"{inner}_array"
    return {bool: "bool", int: "integer", float: "double", str: "string"}[hint]


def option_hint(cls: type, path: str) -> Any:
    """The type hint of a dotted option path under an options dataclass."""
    hint: Any = cls
    for part in path.split("."):
        hints = typing.get_type_hints(hint)
        if part not in hints:
            raise KeyError(path)
        hint = hints[part]
    return hint


def switch_specs() -> list[ParameterSpec]:
    """One parameter per command-line switch, typed from the option it sets."""
    from cusfm_ros.pipeline.options import SWITCHES, MapperOptions

    specs = []
    for name, paths in SWITCHES.items():
        kind = kind_of(option_hint(MapperOptions, paths[0]))
        specs.append(ParameterSpec(name, kind, f"sets {', '.join(paths)} (unset: the preset's "
                                   "value, then the default)"))
    return specs


def mapper_specs() -> list[ParameterSpec]:
    from cusfm_ros.pipeline.mapper import STAGE_NAMES

    return [
        ParameterSpec("bag", "string", "rosbag2 directory or .mcap file to map (required)",
                      ""),
        ParameterSpec("out", "string", "run directory of the outputs (required; a rerun "
                      "resumes it)", ""),
        ParameterSpec("config", "string", "options preset (YAML, e.g. share/cusfm_ros/"
                      "config/av.yaml); empty: the defaults", ""),
        ParameterSpec("steps", "string_array", f"stages to run ({', '.join(STAGE_NAMES)})",
                      list(STAGE_NAMES)),
        ParameterSpec("set", "string_array", "any option as KEY=VALUE, value in YAML (e.g. "
                      "'[loops.top_k=10]'), like `cusfm map --set`"),
        ParameterSpec("overwrite", "bool", "redo the stages even when up to date", False),
        ParameterSpec("map_frame", "string", "frame of the published path and cloud", "map"),
        ParameterSpec("linger_s", "double", "after the map is published, stay up this long "
                      "serving the latched results (negative: until shut down)", -1.0),
        *switch_specs(),
    ]


def parameter_error(spec: ParameterSpec, given: Any = None) -> ConfigError:
    got = "" if given is None else f", got {given!r}"
    return ConfigError(f"parameter {spec.name}: expected {_NAMES[spec.kind]}{got} "
                       f"(e.g. {spec.example})")


def mapper_switches(values: dict[str, Any]) -> dict[str, Any]:
    """Switch values (None: unset) from the node's parameter values."""
    from cusfm_ros.pipeline.options import SWITCHES

    return {name: (tuple(values[name]) if isinstance(values.get(name), list)
                   else values.get(name)) for name in SWITCHES}


def specs_by_name(specs: list[ParameterSpec]) -> dict[str, ParameterSpec]:
    return {spec.name: spec for spec in specs}


def as_dict(spec: ParameterSpec) -> dict:
    return dataclasses.asdict(spec)


@dataclass(frozen=True)
class MapperRequest:
    """What the mapper node was asked to do, resolved and checked before anything runs."""

    options: Any
    bag: str
    run_dir: str
    steps: list[str]
    overwrite: bool


def localizer_specs() -> list[ParameterSpec]:
    return [
        ParameterSpec("map_dir", "string", "run directory of `cusfm map` or its map/ "
                      "(required)", ""),
        ParameterSpec("map_frame", "string", "frame of the map and of every pose", "map"),
        ParameterSpec("device", "string", "auto | cpu | cuda", "auto"),
        ParameterSpec("model_dir", "string", "ONNX model folder (empty: the default)", ""),
        ParameterSpec("image_topics", "string_array", "sensor_msgs/Image topics to localize "
                      "continuously (unset: none)"),
        ParameterSpec("camera_names", "string_array", "the map camera of each image topic"),
        ParameterSpec("odom_topic", "string", "nav_msgs/Odometry for map -> odom on /tf "
                      "(empty: none)", ""),
        ParameterSpec("odom_frame", "string", "child frame of map -> odom (empty: the "
                      "odometry's frame_id)", ""),
    ]


def calibration_specs() -> list[ParameterSpec]:
    """The extrinsic_calibration node's: the mapper's less ``steps`` (it runs up to export)
    and less the switches calibration sets itself."""
    fixed = {"steps", "optimize_extrinsics", "frame_type", "rolling_shutter_line_delay_s"}
    return [spec for spec in mapper_specs() if spec.name not in fixed]


def mapper_request(values: dict[str, Any], calibrate: bool = False) -> MapperRequest:
    """The mapper's (or the calibration's) job from its parameter values, through the
    command line's resolver."""
    from cusfm_ros.pipeline.mapper import STAGE_NAMES
    from cusfm_ros.pipeline.options import resolve_options, set_overrides, switch_overrides

    if calibrate:
        from cusfm_ros.pipeline.calibration import CALIBRATION_STEPS
        values = {**values, "steps": list(CALIBRATION_STEPS)}

    if not values.get("bag") or not values.get("out"):
        raise ConfigError("parameters bag and out are required (ros2 run cusfm_ros mapper "
                          "--ros-args -p bag:=BAG -p out:=RUN_DIR)")
    steps = list(values.get("steps") or [])
    unknown = [s for s in steps if s not in STAGE_NAMES]
    if unknown or not steps:
        raise ConfigError(f"parameter steps: unknown stage(s) {unknown} (stages: "
                          f"{', '.join(STAGE_NAMES)}; e.g. -p steps:='[keyframes, features]')"
                          if unknown else "parameter steps: no stage to run")
    overrides = switch_overrides(mapper_switches(values))
    overrides.update(set_overrides(list(values.get("set") or []), "parameter set:"))
    options = resolve_options(values.get("config") or None, overrides,
                              overrides_source="parameters")
    if calibrate:
        from cusfm_ros.pipeline.calibration import calibration_options
        options = calibration_options(options)
    return MapperRequest(options, str(values["bag"]), str(values["out"]),
                         [s for s in STAGE_NAMES if s in steps], bool(values.get("overwrite")))

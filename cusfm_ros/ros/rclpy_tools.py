"""The little rclpy glue the nodes share: typed parameter declaration from ``ParameterSpec``s,
message classes by type name, latched QoS, logging with one severity per call site, the
static-TF publisher, and a spin loop that ends on SIGINT or SIGTERM.

Imported only by the node modules (it imports rclpy).
"""

from __future__ import annotations

import importlib
import logging
import os
import signal
from collections.abc import Callable
from typing import Any

import rclpy
import rclpy.executors
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException, ParameterUninitializedException
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from cusfm_ros.errors import ConfigError
from cusfm_ros.ros.parameters import ParameterSpec, parameter_error

_TYPES = {"bool": Parameter.Type.BOOL, "integer": Parameter.Type.INTEGER,
          "double": Parameter.Type.DOUBLE, "string": Parameter.Type.STRING,
          "string_array": Parameter.Type.STRING_ARRAY,
          "integer_array": Parameter.Type.INTEGER_ARRAY,
          "double_array": Parameter.Type.DOUBLE_ARRAY}

LATCHED = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def init(args, **kwargs) -> None:
    """``rclpy.init``; a bad ``--ros-args`` (a malformed params file, a bad remap) is one
    ``ConfigError`` line instead of rcl's traceback."""
    try:
        rclpy.init(args=args, **kwargs)
    except Exception as exc:  # rcl raises RCLError / RuntimeError with a multi-line text
        text = " ".join(str(exc).split())
        raise ConfigError(f"cannot parse the ROS arguments ({text}); check --ros-args, "
                          "-p NAME:=VALUE and the --params-file YAML") from None


def declare(node, specs: list[ParameterSpec]) -> dict[str, Any]:
    """Declare every parameter typed (read-only where the spec says); a value of the wrong
    type is a ``ConfigError`` naming the parameter, its type and an example."""
    values = {}
    for spec in specs:
        descriptor = ParameterDescriptor(name=spec.name, type=_TYPES[spec.kind].value,
                                         description=spec.description,
                                         read_only=spec.read_only)
        default = _TYPES[spec.kind] if spec.default is None else spec.default
        try:
            node.declare_parameter(spec.name, default, descriptor)
        except InvalidParameterTypeException:
            given = getattr(node, "_parameter_overrides", {}).get(spec.name)
            raise parameter_error(spec, given.value if given is not None else None) from None
        try:
            value = node.get_parameter(spec.name).value
        except ParameterUninitializedException:
            value = None
        values[spec.name] = list(value) if isinstance(value, (tuple, list)) or (
            hasattr(value, "tolist") and not isinstance(value, (str, bytes))) else value
    return values


def message_class(msgtype: str):
    """``nav_msgs/msg/Path`` -> ``nav_msgs.msg.Path``; ConfigError when not installed."""
    package, kind, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ImportError, AttributeError):
        raise ConfigError(f"message type {msgtype} is not installed (its package {package} "
                          "is missing from this ROS environment)") from None


def log(node, level: int, text: str) -> None:
    """rclpy fixes a call site's severity on first use: one call per severity."""
    logger = node.get_logger()
    if level >= logging.ERROR:
        logger.error(text)
    elif level >= logging.WARNING:
        logger.warning(text)
    elif level >= logging.INFO:
        logger.info(text)
    else:
        logger.debug(text)


class StaticTransforms:
    """/tf_static through tf2_ros's StaticTransformBroadcaster when installed, else a latched
    tf2_msgs/TFMessage publisher with the same QoS; neither installed: a warning, no TF."""

    def __init__(self, node) -> None:
        self.node, self.broadcaster, self.publisher = node, None, None
        try:
            from tf2_ros.static_transform_broadcaster import StaticTransformBroadcaster
            self.broadcaster = StaticTransformBroadcaster(node)
        except ImportError:
            try:
                self.publisher = node.create_publisher(message_class("tf2_msgs/msg/TFMessage"),
                                                       "/tf_static", LATCHED)
            except ConfigError:
                node.get_logger().warning("tf2_msgs is not installed: no /tf_static published")

    def publish_raw(self, cdr: bytes) -> None:
        """A serialized tf2_msgs/TFMessage (as a results bag holds it)."""
        if self.broadcaster is not None:
            from rclpy.serialization import deserialize_message
            message = deserialize_message(cdr, message_class("tf2_msgs/msg/TFMessage"))
            self.broadcaster.sendTransform(list(message.transforms))
        elif self.publisher is not None:
            self.publisher.publish(cdr)


class Shutdown:
    """SIGTERM (launch, systemd) and SIGINT both end ``spin``; the first one is remembered so
    the node can exit as that signal would have (a second signal sent while the node is
    stopping, e.g. a supervisor's SIGTERM after a Ctrl-C, does not change the exit status)."""

    def __init__(self) -> None:
        self.signal: int | None = None
        signal.signal(signal.SIGTERM, self._note)

    def _note(self, signum, frame) -> None:
        if self.signal is None:
            self.signal = signum

    def spin(self, executor, done: Callable[[], bool] = lambda: False,
             slice_s: float = 0.1) -> None:
        """Spin in short slices (Python's handlers run between them) until a signal, rclpy's
        own shutdown (Ctrl-C) or ``done()``."""
        try:
            while rclpy.ok() and self.signal is None and not done():
                executor.spin_once(timeout_sec=slice_s)
        except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
            if self.signal is None:
                self.signal = signal.SIGINT
        except Exception:
            # rclpy's own handler (SIGINT, SIGTERM) may shut the context down between the
            # check above and the executor's wait set, which then fails with an RCLError
            # ("the given context is not valid") instead of ExternalShutdownException: that
            # is the shutdown too. Anything while rclpy still runs is a real error.
            if rclpy.ok():
                raise
        if self.signal is None and not rclpy.ok():
            self.signal = signal.SIGINT

    @staticmethod
    def exit_by(signum: int) -> None:
        """End the process as ``signum`` would (status -signum to the parent)."""
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)

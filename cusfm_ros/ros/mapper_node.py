"""``ros2 run cusfm_ros mapper``: the offline mapper as a ROS 2 node.

Parameters (all read-only, typed; ``ros/parameters.py`` lists them with descriptions): ``bag``
and ``out`` (required), ``config`` (preset YAML), ``steps``, ``set`` (``KEY=VALUE`` like
``cusfm map --set``), ``overwrite``, ``map_frame``, ``linger_s`` and every switch of
``cusfm map`` under its option name (``pipeline.options.SWITCHES``: frame_type,
optimize_extrinsics, rolling_shutter_line_delay_s, rgb, seed, device, ...). Options are
resolved exactly as the command line resolves them.

The pipeline runs in a worker process (``pipeline/worker.py``) while the node spins (its
parameter services answer during a run); the worker's log, progress and per-stage timings go to
the node's logger. When the map is done, the run's ``results.mcap`` is published as it is,
latched (reliable, transient-local, depth 1): ``/cusfm/path``, ``/cusfm/initial_path``,
``/cusfm/map_cloud`` and the refined extrinsics on ``/tf_static``, then a
``cusfm_ros_interfaces/MapInfo`` on ``~/map_info``; the node stays up serving them until shut
down (or ``linger_s``) and exits 0. SIGINT or SIGTERM during the run stops the worker (every
atomic write in progress is dropped, the run directory can be resumed) and the node exits as
that signal would (status -15 / -2). A failed run logs its one-line error and exits 1.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence

from cusfm_ros.errors import CusfmError
from cusfm_ros.ros.runtime import import_ros


def main(args: Sequence[str] | None = None, kind: str = "map") -> int:
    """``kind``: ``map`` (node ``cusfm_mapper``) or ``calibrate`` (node
    ``extrinsic_calibration``: see ``ros/extrinsic_calibration_node.py``)."""
    rclpy = import_ros("rclpy")
    interfaces = import_ros("cusfm_ros_interfaces.msg")
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    from cusfm_ros.io.results_bag import TF_STATIC_TOPIC, read_results_bag
    from cusfm_ros.io.run_dir import RunDir
    from cusfm_ros.pipeline.worker import MapperJob
    from cusfm_ros.ros import rclpy_tools as tools
    from cusfm_ros.ros.parameters import calibration_specs, mapper_request, mapper_specs

    calibrating = kind == "calibrate"
    program = "extrinsic_calibration" if calibrating else "mapper"

    class MapperNode(Node):
        def __init__(self) -> None:
            super().__init__(program if calibrating else "cusfm_mapper")
            values = tools.declare(self, calibration_specs() if calibrating
                                   else mapper_specs())
            self.request = mapper_request(values, calibrating)
            self.linger_s = float(values["linger_s"])
            self.map_frame = values["map_frame"]
            self.outcome: str | None = None  # done | failed
            self.finished_at = 0.0
            self.publishers_: list = []
            self.tf = tools.StaticTransforms(self)
            r = self.request
            self.get_logger().info(f"mapping {r.bag} into {r.run_dir} (stages: "
                                   f"{', '.join(r.steps)})")
            self.job = MapperJob(r.options, r.bag, r.run_dir, r.steps, r.overwrite, kind)
            self.create_timer(0.1, self._poll)

        def _poll(self) -> None:
            for event in self.job.events():
                if event.kind == "log":
                    tools.log(self, int(event.data.get("level", 20)), event.data["message"])
                elif event.kind == "error":
                    self.get_logger().error(event.data["message"])
                    self.outcome = "failed"
                elif event.kind == "done":
                    self._publish_results(event.data["summary"])
                    if event.data.get("calibration"):
                        self._log_calibration(event.data["calibration"])
                    self.outcome, self.finished_at = "done", time.monotonic()
                elif event.kind == "exit" and self.outcome is None:
                    self.get_logger().error(f"the mapper worker ended with status "
                                            f"{event.data['status']} before finishing")
                    self.outcome = "failed"

        def _publish_results(self, summary: dict) -> None:
            run = RunDir(self.request.run_dir)
            if run.results_bag.is_file():
                for topic, msgtype, raw in read_results_bag(run.results_bag):
                    if topic == TF_STATIC_TOPIC:
                        self.tf.publish_raw(raw)
                        continue
                    publisher = self.create_publisher(tools.message_class(msgtype), topic,
                                                      tools.LATCHED)
                    publisher.publish(raw)  # the results bag's CDR, as it is
                    self.publishers_.append(publisher)
            else:
                self.get_logger().warning(f"{run.results_bag} is missing (the export stage "
                                          "did not run): nothing to publish but MapInfo")
            info = interfaces.MapInfo()
            info.header.stamp = self.get_clock().now().to_msg()
            info.header.frame_id = self.map_frame
            info.map_path = str(run.map_dir if run.map_dir.is_dir() else run.root)
            info.num_keyframes = int(summary.get("keyframes") or 0)
            info.num_points = int(summary.get("points") or 0)
            names = _camera_names(run)
            info.num_cameras, info.camera_names = len(names), names
            publisher = self.create_publisher(interfaces.MapInfo, "~/map_info", tools.LATCHED)
            publisher.publish(info)
            self.publishers_.append(publisher)
            linger = ("until shut down" if self.linger_s < 0
                      else f"for {self.linger_s:g} s")
            self.get_logger().info(f"map done: {info.num_keyframes} keyframes, "
                                   f"{info.num_points} points in {run.root}; results "
                                   f"published latched, staying up {linger}")

        def _log_calibration(self, report: dict) -> None:
            from cusfm_ros.cli.calibrate import format_report

            for line in format_report(report):
                if line.startswith("warning:"):
                    self.get_logger().warning(line)
                else:
                    self.get_logger().info(line)

        def finished(self) -> bool:
            if self.outcome == "failed":
                return True
            return (self.outcome == "done" and self.linger_s >= 0
                    and time.monotonic() - self.finished_at >= self.linger_s)

    shutdown = tools.Shutdown()
    node = None
    status = 0
    try:
        tools.init(args, signal_handler_options=SignalHandlerOptions.SIGINT)
        node = MapperNode()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        shutdown.spin(executor, node.finished)
        if node.outcome == "failed":
            status = 1
        elif node.outcome is None:  # stopped by a signal during the run
            code = node.job.cancel()
            print(f"{program}: stopped before the map was complete (worker status {code}); "
                  f"nothing in {node.request.run_dir} looks complete that is not; rerun the "
                  "same command to resume", file=sys.stderr)
        elif node.job.running:
            node.job.cancel()
    except CusfmError as exc:
        print(f"{program}: error: {exc}", file=sys.stderr)
        status = 1
    finally:
        if node is not None:
            if node.outcome is None:
                node.job.cancel()
            node.destroy_node()
        rclpy.try_shutdown()
    if status == 0 and shutdown.signal is not None and (node is None or node.outcome is None):
        tools.Shutdown.exit_by(shutdown.signal)
    return status


def _camera_names(run) -> list[str]:
    from cusfm_ros.io.keyframes_file import read_keyframes

    try:
        return list(read_keyframes(run.keyframes).rig.names)
    except (CusfmError, OSError):
        return []


if __name__ == "__main__":
    sys.exit(main())

"""The mapper in a worker process (what the ROS nodes run) and the nodes' parameter table,
without ROS: a cancelled job stops promptly and leaves nothing that looks complete; parameter
types come from the options; bad values are one-line errors."""

from __future__ import annotations

import json
import signal
import time

import pytest

from cusfm_ros.errors import ConfigError
from cusfm_ros.pipeline.options import resolve_options
from cusfm_ros.pipeline.worker import CANCELLED_STATUS, MapperJob
from cusfm_ros.ros.parameters import (calibration_specs, mapper_request, mapper_specs,
                                      parameter_error, specs_by_name)


def test_cancelled_job_stops_promptly_and_leaves_nothing_complete(tmp_path, models_ready):
    from cusfm_ros.sim.generator import SimulationOptions, Simulator

    sim = Simulator(SimulationOptions(scene="indoor", rig="stereo", frames=30,
                                      image_width=320, image_height=240)).generate(
        tmp_path / "sim")
    run = tmp_path / "run"
    job = MapperJob(resolve_options(None, {"features.extractor.aliked.max_keypoints": 512}),
                    sim / "bag", run)
    deadline = time.monotonic() + 120
    while not (run / "stages" / "features.json").is_file() and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)
    started = time.monotonic()
    status = job.cancel()
    assert time.monotonic() - started < 6.0
    assert status in (CANCELLED_STATUS, -signal.SIGKILL)
    events = list(job.events())
    assert any(e.kind == "log" and "stage keyframes" in e.data["message"] for e in events)
    assert not any(e.kind == "done" for e in events)
    assert events[-1].kind == "exit"
    for name in ("COMPLETE", "poses.tum", "results.mcap", "map", "points.ply"):
        assert not (run / name).exists(), name
    assert not list(run.rglob("*.tmp"))
    report = json.loads((run / "report.json").read_text())
    assert report["status"] == "failed" and "interrupted" in report["error"], report
    record = json.loads((run / "stages" / "features.json").read_text())
    assert record["status"] == "running"  # the next run redoes it (the runner's resume)


def test_job_error_is_an_event_with_the_one_line_message(tmp_path):
    job = MapperJob(resolve_options(None), tmp_path / "missing_bag", tmp_path / "run")
    deadline = time.monotonic() + 60
    events = []
    while time.monotonic() < deadline and not any(e.kind == "exit" for e in events):
        events += list(job.events())
        time.sleep(0.05)
    errors = [e.data["message"] for e in events if e.kind == "error"]
    assert len(errors) == 1 and "no such bag" in errors[0]
    assert events[-1].data["status"] == 1


def test_parameter_types_follow_the_options():
    specs = specs_by_name(mapper_specs())
    assert specs["rolling_shutter_line_delay_s"].kind == "double"
    assert specs["optimize_extrinsics"].kind == "bool"
    assert specs["max_keypoints"].kind == "integer"
    assert specs["image_topics"].kind == "string_array"
    assert specs["steps"].default[0] == "keyframes" and specs["set"].default is None
    assert all(s.read_only and s.description for s in specs.values())
    assert "steps" not in specs_by_name(calibration_specs())
    message = str(parameter_error(specs["rolling_shutter_line_delay_s"], 0))
    assert message == ("parameter rolling_shutter_line_delay_s: expected a floating-point "
                       "number (write 0.0, not 0), got 0 (e.g. -p "
                       "rolling_shutter_line_delay_s:=0.0)")


def _values(**given):
    values = {spec.name: spec.default for spec in mapper_specs()}
    values.update(given)
    return values


def test_mapper_request_resolves_like_the_command_line(tmp_path):
    preset = tmp_path / "preset.yaml"
    preset.write_text("export: {rgb: true, colmap_binary: true}\nloops: {top_k: 7}\n")
    request = mapper_request(_values(bag="b", out="o", config=str(preset),
                                     max_keypoints=300, set=["pairs.mode=radius"],
                                     steps=["features", "keyframes"]))
    o = request.options
    assert o.export.rgb and o.export.colmap_binary and o.loops.top_k == 7  # the preset's
    assert o.features.extractor.aliked.max_keypoints == 300
    assert o.pairs.mode == "radius" and request.steps == ["keyframes", "features"]
    calibration = mapper_request(_values(bag="b", out="o"), calibrate=True)
    assert calibration.options.mapping.optimize_extrinsics
    assert calibration.options.bundle_adjustment.extrinsic_covariance
    assert calibration.steps[-1] == "export"


@pytest.mark.parametrize("given, message", [
    ({"bag": ""}, "parameters bag and out are required"),
    ({"steps": ["keyframes", "nope"]}, "parameter steps: unknown stage(s) ['nope']"),
    ({"steps": []}, "parameter steps: no stage to run"),
    ({"frame_type": "body"}, "parameters: frame_type must be rig or camera, got 'body'"),
    ({"set": ["loops.top_k"]}, "expected KEY=VALUE"),
    ({"seed": -1}, "seed must be >= 0"),
])
def test_bad_mapper_parameters_are_one_line(given, message):
    with pytest.raises(ConfigError) as error:
        mapper_request(_values(**{"bag": "b", "out": "o", **given}))
    assert message in str(error.value) and "\n" not in str(error.value)

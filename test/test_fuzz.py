"""Fuzz: seeded mutations of a small generated bag — truncated at many offsets, bytes flipped
in its chunks, its metadata damaged, a field of every message type broken — through
`cusfm map --steps keyframes`, and kill -9 in each stage of a full run. Whatever the damage:
exit 0 with a complete run, or exit 1 with one line and no traceback; never a result that
looks complete from a failed run; a rerun after a kill reaches the uninterrupted result."""

import json
import shutil

import numpy as np
import pytest
from bagtools import FAST_MAP_ARGS, write_bag

from cusfm_ros.cli.main import main

SEED = 20261202


@pytest.fixture(scope="module")
def clean_bag(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz")
    write_bag(root / "bag", frames=8, compressed=True)
    return root / "bag"


def _mutations(bag, count):
    """(name, function that damages a copy of the bag's storage file)."""
    data = (bag / "bag.mcap").read_bytes() if (bag / "bag.mcap").exists() else None
    assert data is not None, list(bag.iterdir())
    rng = np.random.default_rng(SEED)
    out = []
    for cut in np.sort(rng.integers(8, len(data) - 1, count)):
        out.append((f"truncated at {cut}", lambda d, cut=int(cut): d[:cut]))
    for _ in range(count):
        positions = rng.integers(0, len(data), 8)
        values = rng.integers(0, 256, 8).astype(np.uint8)

        def flip(d, positions=positions, values=values):
            b = bytearray(d)
            for p, v in zip(positions, values):
                b[p] ^= int(v) or 0xFF
            return bytes(b)

        out.append((f"bytes flipped at {positions.tolist()}", flip))
    out.append(("emptied", lambda d: b""))
    out.append(("garbage", lambda d: bytes(rng.integers(0, 256, 4096, dtype=np.uint8))))
    return data, out


def _check(bag, run, capsys, what):
    code = main(["map", str(bag), "--out", str(run), "--steps", "keyframes"])
    err = capsys.readouterr().err
    assert code in (0, 1), (what, code, err)
    assert "Traceback" not in err, (what, err)
    report = json.loads((run / "report.json").read_text()) if (run / "report.json").exists() \
        else None
    if code == 0:
        assert (run / "COMPLETE").is_file() and report["status"] == "complete", what
        assert (run / "keyframes" / "keyframes.json").is_file(), what
    else:
        lines = [line for line in err.strip().splitlines() if line]
        assert len(lines) == 1 and lines[0].startswith("cusfm map: error:"), (what, err)
        assert not (run / "COMPLETE").exists(), what
        assert not (run / "keyframes").exists(), what
        assert report is None or report["status"] == "failed", what
    assert not list(run.rglob("*.tmp")) if run.exists() else True, what
    return code


def test_damaged_bags_end_cleanly(clean_bag, tmp_path, capsys):
    data, mutations = _mutations(clean_bag, 12)
    codes = []
    for index, (what, damage) in enumerate(mutations):
        bag = tmp_path / f"bag{index}"
        shutil.copytree(clean_bag, bag)
        (bag / "bag.mcap").write_bytes(damage(data))
        codes.append(_check(bag, tmp_path / f"run{index}", capsys, what))
    assert codes.count(1) >= len(codes) // 2  # most damage is found, not read past


def test_damaged_metadata_ends_cleanly(clean_bag, tmp_path, capsys):
    for index, text in enumerate(["", "rosbag2_bagfile_information: [", "\x00\x01binary",
                                  "rosbag2_bagfile_information:\n  version: 99\n"]):
        bag = tmp_path / f"meta{index}"
        shutil.copytree(clean_bag, bag)
        (bag / "metadata.yaml").write_text(text)
        _check(bag, tmp_path / f"run{index}", capsys, f"metadata {text!r}")


def _set(path, value):
    """A damage that sets ``message.<path>`` (dotted) to ``value``."""
    def damage(message):
        *parents, name = path.split(".")
        target = message
        for parent in parents:
            target = getattr(target, parent)
        setattr(target, name, value(getattr(target, name)) if callable(value) else value)
    return damage


NAN, INF = float("nan"), float("inf")
# every message type the reader takes, each field it uses broken in the ways a driver breaks it
BROKEN_FIELDS = {
    "sensor_msgs/msg/CompressedImage": {
        "empty data": _set("data", np.zeros(0, np.uint8)),
        "random bytes": _set("data", lambda d: np.random.default_rng(SEED).integers(
            0, 256, len(d), dtype=np.uint8)),
        "png header only": _set("data", np.frombuffer(b"\x89PNG\r\n\x1a\n", np.uint8)),
        "format tiff": _set("format", "tiff"),
        "zero stamp": _set("header.stamp.sec", 0)},
    "sensor_msgs/msg/Image": {
        "data cut in half": _set("data", lambda d: d[:len(d) // 2].copy()),
        "zero width": _set("width", 0),
        "height doubled": _set("height", lambda h: 2 * h),
        "step too small": _set("step", 1),
        "unknown encoding": _set("encoding", "yuv_bogus"),
        "16-bit encoding on 8-bit data": _set("encoding", "mono16")},
    "sensor_msgs/msg/CameraInfo": {
        "zero K": _set("k", np.zeros(9)),
        "NaN focal": _set("k", lambda k: np.r_[NAN, k[1:]]),
        "negative focal": _set("k", lambda k: np.r_[-k[0], k[1:]]),
        "zero size": _set("width", 0),
        "unknown distortion model": _set("distortion_model", "banana"),
        "distortion too short": _set("d", np.zeros(2)),
        "inf distortion": _set("d", lambda d: np.r_[INF, d[1:]])},
    "nav_msgs/msg/Odometry": {
        "NaN position": _set("pose.pose.position.y", NAN),
        "inf position": _set("pose.pose.position.z", INF),
        "zero quaternion": _set("pose.pose.orientation.w", 0.0),
        "stamp from the past": _set("header.stamp.sec", 1),
        "other child frame": _set("child_frame_id", "imu_link")},
    "tf2_msgs/msg/TFMessage": {
        "NaN translation": _set("transforms", lambda t: [_nan_translation(t[0])] + t[1:]),
        "no transforms": _set("transforms", []),
        "camera frame renamed": _set("transforms", lambda t: [_renamed(t[0])] + t[1:])},
}


def _nan_translation(transform):
    transform.transform.translation.x = NAN
    return transform


def _renamed(transform):
    transform.child_frame_id = "nowhere"
    return transform


def _cases():
    """(message type, damage name, which messages: 'one' seeded index or 'all')."""
    rng = np.random.default_rng(SEED)
    return [(msgtype, name, "all" if msgtype == "tf2_msgs/msg/TFMessage" or rng.random() < 0.5
             else int(rng.integers(0, 4)))  # /tf_static has one message
            for msgtype, damages in BROKEN_FIELDS.items() for name in damages]


@pytest.mark.parametrize("msgtype,name,which", _cases())
def test_every_broken_message_type_ends_cleanly(tmp_path, capsys, msgtype, name, which):
    damage = BROKEN_FIELDS[msgtype][name]

    def hook(kind, message, index):
        if kind == msgtype and (which == "all" or index == which):
            damage(message)

    compressed = msgtype == "sensor_msgs/msg/CompressedImage"
    write_bag(tmp_path / "bag", frames=8, compressed=compressed, damage=hook)
    _check(tmp_path / "bag", tmp_path / "run", capsys, f"{msgtype} {name} ({which})")


def _map_command(bag):
    import sys
    return [sys.executable, "-m", "cusfm_ros.cli.main", "map", str(bag / "bag")]


@pytest.fixture(scope="module")
def uninterrupted(small_stereo_bag, tmp_path_factory):
    """The run the killed ones must reach."""
    import subprocess

    reference = tmp_path_factory.mktemp("uninterrupted") / "run"
    subprocess.run(_map_command(small_stereo_bag) + ["--out", str(reference)] + FAST_MAP_ARGS,
                   check=True, capture_output=True)
    return reference


@pytest.mark.parametrize("stage", ["keyframes", "features", "matching", "mapping", "export"])
def test_kill_9_in_a_stage_then_rerun_gives_the_uninterrupted_result(small_stereo_bag,
                                                                      uninterrupted, tmp_path,
                                                                      stage):
    import os
    import signal
    import subprocess
    import time

    command = _map_command(small_stereo_bag)
    run = tmp_path / "run"
    record = run / "stages" / f"{stage}.json"
    # the killed run cannot remove multiprocessing's temporary folder: it goes in tmp_path
    (tmp_path / "tmp").mkdir()
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "TMPDIR": str(tmp_path / "tmp")}
    process = subprocess.Popen(command + ["--out", str(run)] + FAST_MAP_ARGS, env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    killed = False
    while process.poll() is None and time.monotonic() < deadline:
        try:
            if json.loads(record.read_text())["status"] == "running":
                time.sleep(0.02)  # into the stage's work, not its first line
                process.send_signal(signal.SIGKILL)
                killed = True
                break
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.002)
    process.wait(timeout=30)
    assert killed, f"the {stage} stage ended before it could be killed"
    assert not (run / "COMPLETE").exists()
    if (run / "report.json").exists():
        assert json.loads((run / "report.json").read_text())["status"] == "running"
    if stage != "export":  # export publishes poses.tum with the rest, as a unit
        assert not (run / "poses.tum").exists()
    rerun = subprocess.run(command + ["--out", str(run)] + FAST_MAP_ARGS, capture_output=True,
                           text=True)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    assert not list(run.rglob("*.tmp")) and (run / "COMPLETE").is_file()
    for name in ("poses.tum", "points.ply", "extrinsics.yaml"):
        assert (run / name).read_bytes() == (uninterrupted / name).read_bytes(), name
    assert sorted(p.name for p in (run / "sparse").iterdir()) == sorted(
        p.name for p in (uninterrupted / "sparse").iterdir())

"""Fuzz: seeded mutations of a small generated bag — truncated at many offsets, bytes flipped
in its chunks, its metadata damaged — through `cusfm map --steps keyframes`. Whatever the
damage: exit 0 with a complete run, or exit 1 with one line and no traceback; never a
result that looks complete from a failed run."""

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


@pytest.mark.parametrize("stage", ["features", "matching", "mapping"])
def test_kill_9_in_a_stage_then_rerun_gives_the_uninterrupted_result(small_stereo_bag,
                                                                      tmp_path, stage):
    import os
    import signal
    import subprocess
    import sys
    import time

    command = [sys.executable, "-m", "cusfm_ros.cli.main", "map", str(small_stereo_bag / "bag")]
    reference = tmp_path / "reference"
    subprocess.run(command + ["--out", str(reference)] + FAST_MAP_ARGS, check=True,
                   capture_output=True)
    run = tmp_path / "run"
    record = run / "stages" / f"{stage}.json"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    process = subprocess.Popen(command + ["--out", str(run)] + FAST_MAP_ARGS, env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    killed = False
    while process.poll() is None and time.monotonic() < deadline:
        try:
            if json.loads(record.read_text())["status"] == "running":
                time.sleep(0.05)  # into the stage's work, not its first line
                process.send_signal(signal.SIGKILL)
                killed = True
                break
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.005)
    process.wait(timeout=30)
    assert killed, f"the {stage} stage ended before it could be killed"
    assert not (run / "COMPLETE").exists() and not (run / "poses.tum").exists()
    rerun = subprocess.run(command + ["--out", str(run)] + FAST_MAP_ARGS, capture_output=True,
                           text=True)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    assert not list(run.rglob("*.tmp")) and (run / "COMPLETE").is_file()
    assert (run / "poses.tum").read_bytes() == (reference / "poses.tum").read_bytes()

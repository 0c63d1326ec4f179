"""Progress: a tqdm bar on a terminal, log lines with count, rate and ETA elsewhere, nothing
with --quiet; checked on a real pseudo-terminal end to end."""

from __future__ import annotations

import fcntl
import io
import logging
import os
import pty
import struct
import subprocess
import sys
import termios


from cusfm_ros.pipeline.progress import Progress


def test_bar_on_a_terminal_and_lines_elsewhere(monkeypatch, caplog):
    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)
    with caplog.at_level(logging.INFO, logger="cusfm_ros.progress"):
        progress = Progress("features", 4, "images", terminal=True)
        for _ in range(4):
            progress.step()
    assert not caplog.records  # the bar, not log lines
    assert "features: 100%" in stream.getvalue() and "4/4" in stream.getvalue()
    with caplog.at_level(logging.INFO, logger="cusfm_ros.progress"):
        lines = Progress("matching", 3, "pairs", every_s=0.0, terminal=False)
        for _ in range(3):
            lines.step(note="7 matches")
    messages = [r.getMessage() for r in caplog.records]
    assert messages[-1].startswith("matching: 3/3 pairs (") and "ETA 0 s), 7 matches" in \
        messages[-1]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="cusfm_ros"):
        quiet = Progress("loops", 2, "keyframes", every_s=0.0, terminal=False)
        quiet.step(2)
    assert not caplog.records


def _run(command, terminal: bool):
    """Run ``command``; stderr on a pseudo-terminal when ``terminal``."""
    if not terminal:
        return subprocess.run(command, capture_output=True, text=True, timeout=300).stderr
    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                               stderr=follower)
    os.close(follower)
    chunks = []
    while True:
        try:
            chunk = os.read(leader, 65536)
        except OSError:  # the terminal closed with the process
            break
        if not chunk:
            break
        chunks.append(chunk)
    process.wait(timeout=300)
    os.close(leader)
    return b"".join(chunks).decode("utf-8", "replace")


def test_cusfm_shows_a_bar_on_a_terminal_lines_in_a_pipe_and_nothing_quiet(tmp_path,
                                                                           models_ready):
    from cusfm_ros.sim.generator import SimulationOptions, Simulator

    sim = Simulator(SimulationOptions(scene="indoor", rig="stereo", frames=12,
                                      image_width=320, image_height=240)).generate(
        tmp_path / "sim")
    cusfm = [sys.executable, "-m", "cusfm_ros.cli.main"]
    base = ["map", str(sim / "bag"), "--steps", "keyframes", "features", "--max-keypoints",
            "256", "--overwrite", "--out"]
    on_terminal = _run(cusfm + base + [str(tmp_path / "a")], terminal=True)
    assert "features: 100%" in on_terminal and "image/s" in on_terminal, on_terminal[-2000:]
    in_pipe = _run(cusfm + base + [str(tmp_path / "b")], terminal=False)
    assert "100%" not in in_pipe and "images/s, ETA" in in_pipe, in_pipe[-2000:]
    quiet = _run(cusfm + ["--quiet"] + base + [str(tmp_path / "c")], terminal=False)
    assert "ETA" not in quiet and "INFO" not in quiet, quiet[-2000:]
    assert (tmp_path / "c" / "features" / "features.h5").is_file()

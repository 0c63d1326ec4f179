"""Side by side, on the same inputs, on one machine, in one process tree: ours against COLMAP
(pycolmap: incremental and global mapper), one system after the other, each in its own
process (``bench/compare_systems.py``) so that its peak memory is its own.

    python bench/compare.py --out /tmp/compare [--inputs kitti street indoor]
        [--frames 100 300 1000] [--systems ours_view_graph_sift colmap_global ...]
        [--device auto|cpu|cuda] [--max-keypoints 2048] [--time-limit-s 3600]

Writes ``OUT/compare.json`` and ``OUT/compare.md`` after every system (a long run can be
read while it goes):
- Table 3 (the paper's): seconds per 100 frames by stage — ours' vocabulary, loops and pose
  graph shown, not hidden — the total wall time of the system's process, its peak resident
  memory and (ours) peak GPU memory;
- Table 4: ATE RMSE / mean / median / std / min / max of the reference camera's path against
  the ground truth — SE(3)-aligned where the system is metric (ours; COLMAP with the rig's
  extrinsics), Sim(3) for every system — registered images and models (fragments).
A system that fails or does not finish within ``--time-limit-s`` is a row that says so.
``--frames`` sets the simulator inputs' rig samples (the KITTI clip has 51).
Inputs are prepared once under OUT/inputs (``bench/compare_inputs.py``).
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import os
import platform
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

# Only the standard library here: a child's peak resident memory (ru_maxrss) starts at this
# process's size when it forks, so this process stays small and everything else runs in
# children (inputs: compare_inputs.py, systems and their scoring: compare_systems.py).
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from compare_names import COLMAP, INPUTS, OURS, SYSTEMS  # noqa: E402 - the bench folder is no package

logger = logging.getLogger("compare")
DEFAULT_SYSTEMS = ("ours_view_graph_sift", "ours_radius_sift", "colmap_incremental",
                   "colmap_global", "colmap_incremental_priors", "colmap_global_rig")
STAGE_COLUMNS = ("keyframes", "extraction", "vocabulary", "loops", "pose_graph", "matching",
                 "mapping", "export")
OUR_STAGES = {"keyframes": ("keyframes",), "extraction": ("features",),
              "vocabulary": ("vocabulary",), "loops": ("loops",), "pose_graph": ("pose_graph",),
              "matching": ("pairs", "matching"), "mapping": ("mapping",),
              "export": ("export", "map")}


def prepare(name: str, root: Path, frames: int, size: tuple[int, int]) -> tuple[Path, dict]:
    """The input's ``input.json`` (made once, in a child process) and its content."""
    command = [sys.executable, str(HERE / "compare_inputs.py"), name, str(root), str(frames),
               str(size[0]), str(size[1])]
    done = subprocess.run(command, check=True, stdout=subprocess.PIPE, text=True)
    path = Path(done.stdout.strip().splitlines()[-1])
    return path, json.loads(path.read_text())


def save(out: Path, stem: str, form: str, header: str, rows: list[dict], text: str) -> None:
    """``OUT/<stem>.json`` (``form``, header, rows) and ``OUT/<stem>.md``, after every run."""
    (out / f"{stem}.json").write_text(json.dumps({"format": form, "header": header,
                                                  "rows": rows}, indent=1) + "\n")
    (out / f"{stem}.md").write_text(text)


def run_system(system: str, spec_path: Path, work: Path, args, code: Path | None = None
               ) -> dict:
    """The system in a child process; its result, wall time and peak resident memory.
    ``code``: another checkout's root, whose ``bench`` and ``cusfm_ros`` run instead of
    these (``bench/gpu.py --against``)."""
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    bench = HERE if code is None else Path(code).resolve() / "bench"
    extra = (["--threads", str(getattr(args, "colmap_threads", -1))] if system in COLMAP
             else getattr(args, "cusfm_args", []))
    command = [sys.executable, str(bench / "compare_systems.py"), system,
               str(spec_path), str(work), args.device, str(args.max_keypoints), *extra]
    env = None
    if code is not None:  # its package first on the path, run from its root
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(
            [str(bench.parent), *filter(None, [os.environ.get("PYTHONPATH")])])}
    started = time.perf_counter()
    with open(work / "log.txt", "wb") as log:
        child = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT,
                                 start_new_session=True, env=env,
                                 cwd=None if code is None else bench.parent)
        timed_out = False
        while True:
            pid, status, usage = os.wait4(child.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() - started > args.time_limit_s:
                os.killpg(child.pid, signal.SIGKILL)
                _, status, usage = os.wait4(child.pid, 0)
                timed_out = True
                break
            time.sleep(0.2)
    child.returncode = os.waitstatus_to_exitcode(status)
    seconds = time.perf_counter() - started
    result = {"system": system, "seconds": seconds, "peak_rss_mb": usage.ru_maxrss / 1024}
    if timed_out:
        return {**result, "failed": f"did not finish within {args.time_limit_s:.0f} s"}
    if child.returncode != 0 or not (work / "result.json").is_file():
        tail = (work / "log.txt").read_text(errors="replace").strip().splitlines()[-1:]
        return {**result, "failed": f"exit {child.returncode}: {' '.join(tail)[:200]}"}
    return {**result, **json.loads((work / "result.json").read_text())}


def row(result: dict, spec: dict) -> dict:
    frames = spec["frames"]
    per_100 = 100.0 / frames
    stages = result.get("stages_s", {})
    if not stages:  # failed or timed out before reporting its stages
        columns = {}
    elif result["system"] in OURS:
        spans = (result.get("timeline_s") or {}).get("stages") or {}
        columns = {c: _column_seconds(stages, OUR_STAGES[c], spans) for c in STAGE_COLUMNS}
    else:
        columns = {c: stages[c] for c in STAGE_COLUMNS if c in stages}
    return {"input": spec["name"], "frames": frames, "system": result["system"],
            "seconds_per_100_frames": {c: v * per_100 for c, v in columns.items()},
            "total_s": result["seconds"], "total_per_100_frames_s": result["seconds"] * per_100,
            "peak_rss_mb": result["peak_rss_mb"], "gpu_peak_mb": result.get("gpu_peak_mb"),
            "registered": result.get("registered", 0), "models": result.get("models", 0),
            "ate_m": result.get("ate_m", {}), "failed": result.get("failed"),
            "timeline_s": result.get("timeline_s")}


def _column_seconds(stages: dict[str, float], names: tuple[str, ...],
                    spans: dict[str, list]) -> float:
    """A column's seconds: its stages' own seconds, less the time their timeline spans
    overlap (the map store runs on a thread beside the export: the column is their wall
    time, not the sum)."""
    total = sum(stages.get(name, 0.0) for name in names)
    mine = sorted(spans[name] for name in names if name in spans
                  and None not in spans[name] and stages.get(name))
    covered, end = 0.0, None
    for start, stop in mine:  # the union of the spans
        if end is None or start > end:
            covered += stop - start
            end = stop
        elif stop > end:
            covered += stop - end
            end = stop
    return max(0.0, total - (sum(stop - start for start, stop in mine) - covered))


def _cell(value, digits: int = 2) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def markdown(rows: list[dict], header: str) -> str:
    lines = [header, "", "Table 3: seconds per 100 frames (total: the system's whole process)",
             "", "| input | frames | system | " + " | ".join(STAGE_COLUMNS)
             + " | total | peak RSS MB | GPU peak MB |",
             "|---" * (len(STAGE_COLUMNS) + 6) + "|"]
    for r in rows:
        stages = [_cell(r["seconds_per_100_frames"].get(c), 1) for c in STAGE_COLUMNS]
        total = (_cell(r["total_per_100_frames_s"], 1) if not r["failed"]
                 else f"{r['failed']}")
        lines.append(f"| {r['input']} | {r['frames']} | {r['system']} | " + " | ".join(stages)
                     + f" | {total} | {r['peak_rss_mb']:.0f} | {_cell(r['gpu_peak_mb'], 0)} |")
    lines += ["", "Table 4: ATE of the reference camera's path (m); SE(3) for metric systems, "
              "Sim(3) for all", "",
              "| input | frames | system | align | rmse | mean | median | std | min | max | "
              "registered | models |", "|---" * 12 + "|"]
    for r in rows:
        if not r["ate_m"]:
            lines.append(f"| {r['input']} | {r['frames']} | {r['system']} | — | "
                         + "— | " * 6 + f"{r['registered']} of {r['frames']} "
                         f"({r['failed']}) | {r['models']} |")
        for align, stats in r["ate_m"].items():
            values = " | ".join(_cell(stats[k], 3) for k in ("rmse", "mean", "median", "std",
                                                              "min", "max"))
            lines.append(f"| {r['input']} | {r['frames']} | {r['system']} | {align} | {values}"
                         f" | {r['registered']} of {r['frames']} | {r['models']} |")
    return "\n".join(lines) + "\n"


def machine() -> str:
    """CPU cores and GPU name (through nvidia-smi: importing torch here would raise every
    child's peak memory)."""
    try:
        gpu = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=30).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        gpu = ""
    gpu = gpu.splitlines()[0] if gpu else "no GPU"
    return f"{platform.node()}: {os.cpu_count()} CPU cores, {gpu}; {bytecode_note()}"


BYTECODE_PACKAGES = ("torch", "numpy", "cv2", "scipy", "cusfm_ros")


def bytecode_note(packages: tuple[str, ...] = BYTECODE_PACKAGES) -> str:
    """Whether these packages' modules load from compiled bytecode, as a pip install leaves
    them, or are compiled from source at every start: an installation without ``.pyc`` files
    that the interpreter cannot or may not write (``PYTHONDONTWRITEBYTECODE``) pays ~1.5 s more
    for torch's import alone (2.3-2.5 s against 0.85-1.3 s on the 2-core machine), in every
    run's fixed cost. Looks where this interpreter would (``sys.pycache_prefix`` included),
    without importing the packages."""
    from importlib.util import cache_from_source, find_spec

    missing = []
    for name in packages:
        try:
            spec = find_spec(name)
        except (ImportError, ValueError):
            spec = None
        if spec is None or not spec.origin or not spec.origin.endswith(".py"):
            continue
        if not os.path.exists(cache_from_source(spec.origin)):
            missing.append(name)
    if not missing:
        return "modules load from bytecode"
    return f"no bytecode for {', '.join(missing)} (compiled from source at every start)"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--inputs", nargs="+", choices=INPUTS, default=["street"])
    parser.add_argument("--frames", nargs="+", type=int, default=[100])
    parser.add_argument("--systems", nargs="+", choices=SYSTEMS, default=list(DEFAULT_SYSTEMS))
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    parser.add_argument("--max-keypoints", type=int, default=2048)
    parser.add_argument("--time-limit-s", type=float, default=3600.0)
    parser.add_argument("--colmap-threads", type=int, default=-1,
                        help="COLMAP's threads (-1: every core; 1: results that do not vary "
                             "with the machine's load)")
    parser.add_argument("--image-size", type=int, nargs=2, default=(1241, 376),
                        metavar=("WIDTH", "HEIGHT"), help="simulator inputs' image size")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s",
                        datefmt="%H:%M:%S")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    header = (f"{datetime.date.today()}, {machine()}; `python bench/compare.py "
              f"{' '.join(argv if argv is not None else sys.argv[1:])}`")
    rows = []
    for name in args.inputs:
        for frames in ([51] if name == "kitti" else args.frames):
            spec_path, spec = prepare(name, out / "inputs", frames, args.image_size)
            for system in args.systems:
                logger.info("compare: %s on %s (%d frames)", system, name, spec["frames"])
                result = run_system(system, spec_path, out / "runs" / f"{name}_{frames}" /
                                    system, args)
                rows.append(row(result, spec))
                logger.info("compare: %s: %.1f s, %s", system, result["seconds"],
                            result.get("failed") or f"{rows[-1]['registered']} registered")
                save(out, "compare", "cusfm_compare/1", header, rows, markdown(rows, header))
    print(markdown(rows, header))
    return 0


if __name__ == "__main__":
    sys.exit(main())

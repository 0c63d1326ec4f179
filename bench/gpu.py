"""The GPU path against the same machine's CPUs: ``cusfm map`` on the simulated 1241x376
stereo street (2 laps, seed 0) at each frame count, on each device, one process per run
(``bench/compare_systems.py``), seconds per 100 frames by stage, peak resident and GPU
memory, and the ATE, so that speed never hides a worse map.

    python bench/gpu.py --out /tmp/gpu [--frames 100 300 1000] [--devices cuda cpu]
                        [--features sift|aliked|xfeat] [--adaptive] [--time-limit-s 1800]
                        [--set KEY=VALUE ...] [--repeat N] [--against OTHER_CHECKOUT]

``--repeat`` runs each row N times and ``--against`` alternates every run with one of
another checkout (its ``bench`` and ``cusfm_ros``) on the same inputs: the lent GPU
machines differ by up to 2x in CPU speed and some vary between runs, so only alternating
runs on one machine compare two versions.

Before the first timed run on a device, one untimed process (``warm_up``) imports what the
runs import and starts the GPU's libraries: on a fresh lent machine the first process reads
them from disk (its first convolution took 404 ms, the next processes' 65-87 ms), which had
fallen on the first timed run, always "this, 1" of an alternation. ``--no-warm-up`` leaves
it out.

Installs nothing: run it where ``make test`` runs, on a machine with a GPU. Writes
``OUT/gpu.json`` and ``OUT/gpu.md`` after every run. A run past the time limit is a row
that says so.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import compare  # noqa: E402 - the bench folder is not a package


WARM_UP = """
import sys, time
started = time.perf_counter()
import cusfm_ros.cli.main  # noqa: F401 - the CLI's imports (numpy, OpenCV, SciPy, h5py)
device = sys.argv[1]
try:
    import torch
except ImportError:
    torch = None
if torch is not None and device == "cuda" and torch.cuda.is_available():
    with torch.inference_mode():
        images = torch.zeros(2, 3, 64, 64, device="cuda")
        torch.nn.Conv2d(3, 8, 3, padding=1).cuda()(images)
        torch.nn.Linear(64, 64).cuda()(torch.zeros(8, 64, device="cuda"))
        queries = torch.zeros(1, 4, 64, 64, device="cuda", dtype=torch.float16)
        torch.nn.functional.scaled_dot_product_attention(queries, queries, queries)
        torch.cuda.synchronize()
print(f"{time.perf_counter() - started:.1f}")
"""
"""What ``warm_up`` runs in a fresh interpreter: ``python -c WARM_UP DEVICE``."""


def warm_up(device: str, root: Path | None = None) -> float | None:
    """Seconds of one untimed process that imports the CLI and, on ``cuda``, runs a
    convolution, a linear layer and an attention on the GPU, from ``root`` (a checkout;
    None: this one); None where it failed (the timed runs then say why)."""
    root = root or Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-c", WARM_UP, device], cwd=root,
                          capture_output=True, text=True, timeout=300)
    if done.returncode != 0:
        return None
    return float(done.stdout.split()[-1])


class GpuBusy:
    """The mean share of time a kernel ran on GPU 0 while a run goes (nvidia-smi's
    ``utilization.gpu``, sampled every 100 ms): a run fed by a busy host leaves the GPU idle
    (street 300 on an H100, 2026-12-06: 45-56 % while the networks ran, 0 % between), and
    the most GPU memory in use (``memory.used``: the CUDA context and torch's cached blocks
    and CUDA graph pools too, which torch's own peak, of its live tensors, leaves out).
    ``percent`` and ``used_mb`` are None for a CPU run or where there is no nvidia-smi."""

    def __init__(self, device: str) -> None:
        self.active = device == "cuda" and shutil.which("nvidia-smi") is not None
        self.percent: float | None = None
        self.used_mb: float | None = None
        self._sampler = None

    def __enter__(self) -> GpuBusy:
        if self.active:
            self._sampler = subprocess.Popen(
                ["nvidia-smi", "-i", "0", "--query-gpu=utilization.gpu,memory.used",
                 "--format=csv,noheader,nounits", "-lms", "100"],
                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        return self

    def __exit__(self, *exc) -> None:
        if self._sampler is None:
            return
        self._sampler.terminate()
        out, _ = self._sampler.communicate(timeout=10)
        samples = []
        for line in out.splitlines():
            fields = [field.strip() for field in line.split(",")]
            if len(fields) == 2 and all(f.replace(".", "", 1).isdigit() for f in fields):
                samples.append((float(fields[0]), float(fields[1])))
        if samples:
            self.percent = sum(busy for busy, _ in samples) / len(samples)
            self.used_mb = max(used for _, used in samples)


def outside_stages(row: dict) -> float | None:
    """Seconds per 100 frames of the run's process outside its stages (None for a run that
    failed or reported no stages)."""
    stages = row["seconds_per_100_frames"]
    if row["failed"] or not stages:
        return None
    return row["total_per_100_frames_s"] - sum(stages.values())


def outside_parts(row: dict) -> dict[str, float] | None:
    """The time outside the stages (seconds per 100 frames) from the run's timeline: before
    (the process's start to the first stage: the interpreter and the imports), between (in
    the stages' span but not their own work: torch's import waited for beside the first
    stage, the digests, the records, the stages no column shows) and after (the last stage's
    end to the process's end: the report page, the benchmark's scoring, the exit). None
    without a timeline (a failed run, another system, code from before it)."""
    timeline = row.get("timeline_s") or {}
    spans = list((timeline.get("stages") or {}).values())
    outside = outside_stages(row)
    if outside is None or not spans or any(v is None for span in spans for v in span):
        return None
    per_100 = 100.0 / row["frames"]
    before = min(span[0] for span in spans) * per_100
    after = row["total_per_100_frames_s"] - max(span[1] for span in spans) * per_100
    return {"before": before, "between": outside - before - after, "after": after}


def markdown(rows: list[dict], header: str) -> str:
    columns = compare.STAGE_COLUMNS
    labelled = any(r.get("code") != "this" or r.get("run", 1) > 1 for r in rows)
    label = "code, run | " if labelled else ""
    lines = [header, "", "Seconds per 100 frames by stage (total: the whole process; outside: "
             "its time outside the stages, such as the interpreter's and torch's start, CUDA's "
             "initialisation and the report page; before / between / after: where, from the "
             "run's timeline: before the first stage, inside the stages' span but not their "
             "own work, after the last stage)", "",
             f"| {label}frames | device | " + " | ".join(columns) + " | outside | "
             "before / between / after | total | "
             "peak RSS MB | GPU peak MB | GPU used MB | GPU busy % | ATE SE(3) m |",
             "|---" * (len(columns) + 10 + bool(label)) + "|"]
    for r in rows:
        stages = [compare._cell(r["seconds_per_100_frames"].get(c), 1) for c in columns]
        total = r["failed"] or compare._cell(r["total_per_100_frames_s"], 1)
        ate = r["ate_m"].get("se3", {}).get("rmse")
        cell = f"{r['code']}, {r['run']} | " if labelled else ""
        parts = outside_parts(r)
        split = "—" if parts is None else " / ".join(f"{v:.1f}" for v in parts.values())
        lines.append(f"| {cell}{r['frames']} | {r['device']} | " + " | ".join(stages)
                     + f" | {compare._cell(outside_stages(r), 1)} | {split} | {total} | "
                     f"{r['peak_rss_mb']:.0f} | {compare._cell(r['gpu_peak_mb'], 0)} | "
                     f"{compare._cell(r.get('gpu_used_mb'), 0)} | "
                     f"{compare._cell(r.get('gpu_busy_pct'), 0)} | {compare._cell(ate, 4)} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--frames", nargs="+", type=int, default=[100, 300, 1000])
    parser.add_argument("--devices", nargs="+", choices=("cuda", "cpu"), default=["cuda",
                                                                                 "cpu"])
    parser.add_argument("--features", choices=("sift", "aliked", "xfeat"), default="aliked")
    parser.add_argument("--adaptive", action="store_true",
                        help="the matcher's early exit and point pruning (aliked, xfeat)")
    parser.add_argument("--max-keypoints", type=int, default=2048)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a setting passed to `cusfm map --set` (repeatable)")
    parser.add_argument("--time-limit-s", type=float, default=1800.0)
    parser.add_argument("--image-size", type=int, nargs=2, default=(1241, 376),
                        metavar=("WIDTH", "HEIGHT"))
    parser.add_argument("--repeat", type=int, default=1, metavar="N",
                        help="runs of each frame count and device")
    parser.add_argument("--against", type=Path, metavar="OTHER_CHECKOUT",
                        help="another checkout's root: each run is followed by one of it")
    parser.add_argument("--no-warm-up", dest="warm_up", action="store_false",
                        help="no untimed process before a device's first run")
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be >= 1")
    if args.against is not None and not (args.against / "bench" / "compare_systems.py"
                                         ).is_file():
        parser.error(f"--against {args.against}: no bench/compare_systems.py there; give "
                     "the root of a cusfm_ros checkout")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    header = (f"{compare.machine()}; `python bench/gpu.py "
              f"{' '.join(argv if argv is not None else sys.argv[1:])}`")
    system = f"ours_view_graph_{args.features}" + ("_adaptive" if args.adaptive else "")
    if system not in compare.SYSTEMS:
        parser.error(f"{system} is not a system of bench/compare.py")
    rows = []
    warmed: set[str] = set()
    for frames in args.frames:
        spec_path, spec = compare.prepare("street", out / "inputs", frames, args.image_size)
        for device in args.devices:
            run = argparse.Namespace(device=device, max_keypoints=args.max_keypoints,
                                     time_limit_s=args.time_limit_s,
                                     cusfm_args=[a for kv in args.set for a in ("--set", kv)])
            codes = [("this", None)] + ([("against", args.against)] if args.against else [])
            if args.warm_up and device not in warmed:
                warmed.add(device)
                seconds = warm_up(device)
                print(f"warm-up on {device} (untimed): " + (
                    "failed" if seconds is None else f"{seconds:.1f} s"), flush=True)
            for index in range(1, args.repeat + 1):
                for code, root in codes:
                    name = f"{frames}_{device}" + ("" if len(codes) == 1 and args.repeat == 1
                                                   else f"_{code}_{index}")
                    with GpuBusy(device) as busy:
                        result = compare.run_system(system, spec_path, out / "runs" / name,
                                                    run, root)
                    rows.append({**compare.row(result, spec), "device": device,
                                 "code": code, "run": index, "gpu_busy_pct": busy.percent,
                                 "gpu_used_mb": busy.used_mb})
                    compare.save(out, "gpu", "cusfm_gpu_bench/1", header, rows,
                                 markdown(rows, header))
    print(markdown(rows, header))
    return 0


if __name__ == "__main__":
    sys.exit(main())

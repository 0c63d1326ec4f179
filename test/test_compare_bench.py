"""bench/compare.py end to end on a tiny simulated street (ours and COLMAP's global mapper
when pycolmap is installed): the JSON schema, both tables, and a map that scores; and the
peers' BAL adjusters (bench/ba_peers.py) reach gtsam's optimum on a synthetic problem."""

import importlib.util
import json
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"
sys.path.insert(0, str(BENCH))

ROW_KEYS = {"input", "frames", "system", "seconds_per_100_frames", "total_s",
            "total_per_100_frames_s", "peak_rss_mb", "gpu_peak_mb", "registered", "models",
            "ate_m", "failed", "timeline_s"}
STATS = {"rmse", "mean", "median", "std", "min", "max", "n"}


@pytest.fixture(scope="module")
def bench_out(tmp_path_factory):
    """One output folder for both benches: the simulated input is made once."""
    return tmp_path_factory.mktemp("bench")


def test_compare_writes_both_tables_for_ours_and_colmap(bench_out):
    import compare

    tmp_path = bench_out

    systems = ["ours_view_graph_sift"]
    has_colmap = importlib.util.find_spec("pycolmap") is not None
    if has_colmap:
        systems.append("colmap_global")
    # COLMAP on one thread: its multithreaded run once found no model here on a loaded
    # machine
    assert compare.main(["--out", str(tmp_path), "--inputs", "street", "--frames", "30",
                         "--image-size", "640", "240", "--device", "cpu",
                         "--colmap-threads", "1", "--systems", *systems]) == 0
    report = json.loads((tmp_path / "compare.json").read_text())
    assert report["format"] == "cusfm_compare/1"
    assert [r["system"] for r in report["rows"]] == systems
    for r in report["rows"]:
        assert set(r) == ROW_KEYS
        assert r["input"] == "street" and r["frames"] == 30
        assert r["failed"] is None, r["failed"]
        assert r["peak_rss_mb"] > 50 and r["total_s"] > 0
        assert set(r["ate_m"]["sim3"]) == STATS
    ours = report["rows"][0]
    assert ours["registered"] >= 20 and ours["models"] == 1
    assert set(ours["seconds_per_100_frames"]) == set(compare.STAGE_COLUMNS)
    assert ours["ate_m"]["se3"]["rmse"] < 0.1  # metric, from drifting odometry
    if has_colmap:
        assert set(report["rows"][1]["seconds_per_100_frames"]) == {"extraction", "matching",
                                                                    "mapping"}
        assert "se3" not in report["rows"][1]["ate_m"]  # monocular: scale free
    text = (tmp_path / "compare.md").read_text()
    assert "Table 3" in text and "Table 4" in text
    assert text.count("| street | 30 | ours_view_graph_sift |") == 3  # table 3; sim3, se3


def test_gpu_bench_runs_each_device_and_reports_the_stages(bench_out):
    """On CI's CPU-only machine: the CPU row (the cuda row needs a GPU)."""
    import gpu

    assert gpu.main(["--out", str(bench_out), "--frames", "30", "--devices", "cpu",
                     "--features", "sift", "--image-size", "640", "240"]) == 0
    report = json.loads((bench_out / "gpu.json").read_text())
    assert report["format"] == "cusfm_gpu_bench/1"
    (row,) = report["rows"]
    assert row["device"] == "cpu" and row["frames"] == 30 and row["failed"] is None
    assert row["ate_m"]["se3"]["rmse"] < 0.1
    assert row["gpu_peak_mb"] is None  # no GPU was used
    outside = row["total_per_100_frames_s"] - sum(row["seconds_per_100_frames"].values())
    assert 0 < outside == gpu.outside_stages(row)
    line, = [x for x in (bench_out / "gpu.md").read_text().splitlines()
             if x.startswith("| 30 | cpu | ")]
    parts = gpu.outside_parts(row)
    assert set(parts) == {"before", "between", "after"} and min(parts.values()) >= 0
    assert sum(parts.values()) == pytest.approx(outside)
    split = " / ".join(f"{v:.1f}" for v in parts.values())
    assert f" | {outside:.1f} | {split} | {row['total_per_100_frames_s']:.1f} | " in line
    assert gpu.outside_stages({**row, "failed": "exit 1: ..."}) is None
    assert gpu.outside_parts({**row, "timeline_s": None}) is None


def test_the_warm_up_imports_the_cli_in_a_fresh_process_and_says_when_it_cannot(tmp_path):
    """``warm_up`` runs the untimed process from a checkout's root, whose cusfm_ros it
    imports: seconds from this one, None from one whose package does not import."""
    import gpu

    seconds = gpu.warm_up("cpu")
    assert seconds is not None and 0 < seconds < 120
    (tmp_path / "cusfm_ros").mkdir()
    (tmp_path / "cusfm_ros" / "__init__.py").write_text("raise ImportError('broken')\n")
    assert gpu.warm_up("cpu", tmp_path) is None


def test_gpu_busy_is_the_mean_of_nvidia_smis_samples_over_a_run(tmp_path, monkeypatch):
    """The GPU's busy share and most memory in use over a cuda run, from nvidia-smi's samples
    (a stand-in here that prints three and waits to be stopped); none for a CPU run or
    without nvidia-smi."""
    import time

    import gpu

    fake = tmp_path / "nvidia-smi"
    fake.write_text("#!/bin/sh\nprintf '40, 2100\\n50, 2900\\n90, 2500\\n'\nexec sleep 30\n")
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{tmp_path}:{os.environ['PATH']}")
    with gpu.GpuBusy("cuda") as busy:
        time.sleep(0.5)
    assert busy.percent == pytest.approx(60.0) and busy.used_mb == 2900
    with gpu.GpuBusy("cpu") as busy:
        pass
    assert busy.percent is None and busy.used_mb is None
    monkeypatch.setenv("PATH", str(tmp_path / "none"))
    with gpu.GpuBusy("cuda") as busy:
        pass
    assert busy.percent is None


def test_a_column_of_stages_run_side_by_side_is_their_wall_time():
    """The export column holds the export and the map store, which run side by side: their
    own seconds less the overlap of their timeline spans; the time outside the stages
    counts from the first start to the last end."""
    import compare
    import gpu

    spans = {"export": [10.0, 11.0], "map": [10.0, 10.5], "mapping": [8.0, 10.0]}
    stages = {"export": 0.9, "map": 0.45, "mapping": 1.9}
    assert compare._column_seconds(stages, ("export", "map"), spans) == pytest.approx(0.85)
    assert compare._column_seconds(stages, ("mapping",), spans) == pytest.approx(1.9)
    # one after the other: the sum, as before
    apart = {"export": [10.0, 11.0], "map": [11.0, 11.5]}
    assert compare._column_seconds(stages, ("export", "map"), apart) == pytest.approx(1.35)
    assert compare._column_seconds(stages, ("export", "map"), {}) == pytest.approx(1.35)
    row = {"frames": 100, "failed": None, "total_per_100_frames_s": 12.0,
           "seconds_per_100_frames": {"mapping": 1.9, "export": 0.85},
           "timeline_s": {"stages": {"mapping": [8.0, 10.0], "map": [10.0, 10.5],
                                     "export": [10.0, 11.0]}}}
    parts = gpu.outside_parts(row)
    assert parts["before"] == pytest.approx(8.0) and parts["after"] == pytest.approx(1.0)


def test_bytecode_note_names_the_packages_compiled_at_every_start(tmp_path, monkeypatch):
    """The machine line says whether the packages load from bytecode: a package with its
    ``.pyc`` where the interpreter looks is not named, one without is; an absent package is
    skipped."""
    import py_compile

    import compare

    package = tmp_path / "site" / "cachedpkg"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("x = 1\n")
    other = tmp_path / "site" / "plainpkg"
    other.mkdir()
    (other / "__init__.py").write_text("y = 2\n")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    monkeypatch.setattr(sys, "pycache_prefix", str(tmp_path / "prefix"))
    py_compile.compile(str(package / "__init__.py"))  # written under the prefix
    note = compare.bytecode_note(("cachedpkg", "plainpkg", "no_such_package_here"))
    assert note == "no bytecode for plainpkg (compiled from source at every start)"
    py_compile.compile(str(other / "__init__.py"))
    assert compare.bytecode_note(("cachedpkg", "plainpkg")) == "modules load from bytecode"


def test_gpu_bench_alternates_with_another_checkout(bench_out, tmp_path, capsys):
    """``--against`` runs another checkout's code after each run of this one, on the same
    inputs, ``--repeat`` times; the rows say which code ran (the other copy reports its own
    version)."""
    import shutil

    import gpu

    root = BENCH.parent
    other = tmp_path / "other"
    for folder in ("cusfm_ros", "bench", "config"):
        shutil.copytree(root / folder, other / folder,
                        ignore=shutil.ignore_patterns("__pycache__"))
    init = other / "cusfm_ros" / "__init__.py"
    init.write_text(re.sub(r'__version__ = "[^"]*"', '__version__ = "0.0.0+other"',
                           init.read_text()))
    out = tmp_path / "out"
    (out / "inputs").mkdir(parents=True)
    made = bench_out / "inputs"  # the input of the test above, when it ran (else made here)
    for entry in made.iterdir() if made.is_dir() else ():
        (out / "inputs" / entry.name).symlink_to(entry)
    capsys.readouterr()
    assert gpu.main(["--out", str(out), "--frames", "30", "--devices", "cpu", "--features",
                     "sift", "--image-size", "640", "240", "--against", str(other),
                     "--repeat", "2"]) == 0
    assert len(re.findall(r"warm-up on cpu \(untimed\): \d+\.\d s",
                          capsys.readouterr().out)) == 1  # once, before the first run
    rows = json.loads((out / "gpu.json").read_text())["rows"]
    assert [(r["code"], r["run"], r["failed"]) for r in rows] == [
        ("this", 1, None), ("against", 1, None), ("this", 2, None), ("against", 2, None)]
    versions = [json.loads((out / "runs" / f"30_cpu_{code}_1" / "run" / "report.json")
                           .read_text())["version"] for code in ("this", "against")]
    assert versions[1] == "0.0.0+other" and versions[0] != versions[1]
    text = (out / "gpu.md").read_text()
    assert "| this, 1 | 30 | cpu | " in text and "| against, 2 | 30 | cpu | " in text
    with pytest.raises(SystemExit):
        gpu.main(["--out", str(out), "--against", str(tmp_path)])
    assert "no bench/compare_systems.py there" in capsys.readouterr().err


@pytest.mark.parametrize("solver", ["pycolmap", "pyceres"])
def test_peer_bundle_adjusters_reach_gtsams_optimum(solver):
    pytest.importorskip(solver)
    import ba_peers

    from cusfm_ros.core.mapping.bal_gtsam import GtsamBalAdjuster
    from cusfm_ros.sim.bal_problem import street_bal_problem

    problem, _ = street_bal_problem(8, 160)
    problem = problem.in_front()
    reference = GtsamBalAdjuster().solve(problem).problem.cost()
    adjusted, stats = getattr(ba_peers, f"{solver}_adjust")(problem, 100)
    assert problem.cost() > 10 * reference  # the start is off the optimum
    assert adjusted.cost() == pytest.approx(reference, rel=1e-6)
    assert stats["iterations"] >= 1 and np.isfinite(stats["seconds"])


def test_real_bench_row_of_a_peer_model_too_small_to_align():
    """bench/real.py: a peer's model of two images (COLMAP's incremental mapper on the KITTI
    clip, 2026-12-07) is a row that says so; a whole one gets its ATE."""
    from real import row

    from cusfm_ros.core.trajectory import Trajectory

    world_from_body = np.stack([np.eye(4)] * 6)
    world_from_body[:, :3, 3] = [[0, 0, 0], [1, 0, 0], [2, 1, 0], [3, 1, 1], [4, 3, 1],
                                 [5, 2, 2]]
    truth = Trajectory(np.arange(6) * 10**8, world_from_body)
    two = Trajectory(truth.stamps_ns[:2], truth.world_from_body[:2])
    assert row("peer", truth, two, 1.0, "2 of 6, 1 model", False) == (
        "| peer | — | — | — | 2 of 6, 1 model (too few to align) | 1.0 |")
    assert row("ours", truth, truth, 2.0, "6 of 6", True) == (
        "| ours | 0.000 | 0.000 | +0.00 % | 6 of 6 | 2.0 |")

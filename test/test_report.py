"""report.html: written by every `cusfm map` that exports, rebuilt by `cusfm report`, with the
figures the run's data allows; a real headless Chromium (Debian's package; skipped where it
is not installed) loads the page and every figure decodes."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from cusfm_ros.cli.main import main


@pytest.fixture(scope="module")
def mapped(tmp_path_factory, models_ready):
    from cusfm_ros.sim.generator import SimulationOptions, Simulator

    root = tmp_path_factory.mktemp("report")
    sim = Simulator(SimulationOptions(scene="indoor", rig="stereo", frames=30,
                                      image_width=320, image_height=240)).generate(
        root / "sim")
    run = root / "run"
    assert main(["map", str(sim / "bag"), "--out", str(run), "--max-keypoints", "512",
                 "--rgb"]) == 0
    return sim, run


FIGURES = ("trajectory-top", "trajectory-side", "stage-times", "reprojection", "track-length",
           "cloud")


def test_map_writes_the_page_and_report_adds_the_ground_truth(mapped, capsys):
    from cusfm_ros.core.evaluation import AteOptions, absolute_trajectory_error
    from cusfm_ros.io.tum import read_tum

    sim, run = mapped
    page = (run / "report.html").read_text()
    assert all(f'id="{f}"' in page for f in FIGURES) and 'id="ate"' not in page
    assert 'id="extrinsics"' not in page  # nothing was refined: no empty chart
    assert main(["report", str(run), "--ground-truth", str(sim / "ground_truth.tum")]) == 0
    assert capsys.readouterr().out.strip() == str(run / "report.html")
    page = (run / "report.html").read_text()
    assert 'id="ate"' in page and page.count("<figure") == len(FIGURES) + 1
    ate = absolute_trajectory_error(read_tum(sim / "ground_truth.tum"),
                                    read_tum(run / "poses.tum"), AteOptions(align="se3"))
    assert f"RMSE {ate.rmse:.3f} m" in page
    images = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(images) == len(FIGURES) + 1  # self-contained: every figure inlined
    assert "http://" not in page and "https://" not in page


def test_figures_drawn_on_worker_processes_are_the_same_page(mapped, tmp_path):
    """The mapper draws the page's figures on worker processes from 4 cores on: the page
    is byte for byte the one drawn in one process."""
    from cusfm_ros.pipeline.parallel import map_on_processes
    from cusfm_ros.report.page import write_report_page

    _, run = mapped
    shutil.copytree(run, tmp_path / "run")
    here = write_report_page(tmp_path / "run").read_bytes()
    drawn = []

    def on_processes(function, specs):
        specs = list(specs)
        drawn.append(len(specs))
        return map_on_processes(2, fewest=1, chunk=1, minimum=1)(function, specs)

    assert write_report_page(tmp_path / "run", figure_map=on_processes).read_bytes() == here
    assert drawn == [len(FIGURES)]


def test_result_figures_drawn_ahead_on_workers_make_the_same_page(mapped, tmp_path):
    """The mapper's path: the exported results' figures drawn on worker processes while the
    map stage runs (``draw_result_figures``, in parts), the report's own figures (stage
    times) at the end: the same page byte for byte; a figure missing from them is drawn."""
    from cusfm_ros.pipeline.parallel import worker_processes
    from cusfm_ros.report.page import REPORT_FIGURES, draw_result_figures, write_report_page

    _, run = mapped
    shutil.copytree(run, tmp_path / "run")
    here = write_report_page(tmp_path / "run").read_bytes()
    with worker_processes((), 2) as start:
        waits = [start(draw_result_figures, (tmp_path / "run", part, 2)) for part in (0, 1)]
        drawn = {k: v for wait in waits for k, v in wait().items()}
    assert set(drawn) == set(FIGURES) - set(REPORT_FIGURES)
    left = []

    def the_rest(function, specs):
        specs = list(specs)
        left.append(len(specs))
        return map(function, specs)

    assert write_report_page(tmp_path / "run", figure_map=the_rest,
                             drawn=drawn).read_bytes() == here
    assert left == [1]  # stage-times
    del drawn["cloud"]
    assert write_report_page(tmp_path / "run", figure_map=the_rest,
                             drawn=drawn).read_bytes() == here
    assert left == [1, 2]


def test_figures_drawn_from_the_mapping_stages_results_are_the_exported_ones(mapped,
                                                                           tmp_path):
    """The mapper draws the results' figures from the mapping stage's outputs while the
    export writes its copies of them: the same figures, byte for byte; but the colours of
    the cloud are the export's (this run has ``--rgb``: the mapper waits for the export)."""
    from cusfm_ros.io.ply import read_ply, write_ply
    from cusfm_ros.report.page import draw_result_figures
    from cusfm_ros.report.run_data import read_run_data

    _, run = mapped
    exported = draw_result_figures((run, 0, 1))
    mapping = draw_result_figures((run, 0, 1, "mapping"))
    assert set(exported) >= {"trajectory-top", "cloud", "reprojection"}
    assert mapping.pop("cloud") != exported.pop("cloud") and mapping == exported
    shutil.copytree(run, tmp_path / "run")  # as exported without --rgb
    write_ply(tmp_path / "run" / "points.ply", read_ply(run / "points.ply")[0], None)
    assert draw_result_figures((tmp_path / "run", 0, 1, "mapping")) == draw_result_figures(
        (tmp_path / "run", 0, 1))
    with pytest.raises(ValueError, match="results must be one of"):
        read_run_data(run, results="colmap")


def test_report_needs_a_finished_run(tmp_path, capsys):
    assert main(["report", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "no report.json" in err and len(err.strip().splitlines()) == 1


@pytest.mark.skipif(shutil.which("chromium") is None,
                    reason="Chromium (Debian's package) is not installed")
def test_a_real_browser_loads_every_figure(mapped, tmp_path):
    _, run = mapped
    page = run / "report.html"
    result = subprocess.run(
        ["chromium", "--headless", "--no-sandbox", "--disable-gpu",
         "--virtual-time-budget=5000", "--dump-dom", page.as_uri()],
        capture_output=True, text=True, timeout=120)
    body = re.search(r'<body data-figures="(\d+)" data-figures-loaded="(\d+)"', result.stdout)
    assert body is not None, result.stdout[:500] + result.stderr[-500:]
    assert int(body.group(1)) >= len(FIGURES) and body.group(1) == body.group(2)
    for figure in FIGURES:
        assert f'<figure id="{figure}" data-loaded="true"' in result.stdout, figure
    # CUSFM_REPORT_SCREENSHOT=docs/report.png makes README's picture
    screenshot = Path(os.environ.get("CUSFM_REPORT_SCREENSHOT") or tmp_path / "report.png")
    subprocess.run(["chromium", "--headless", "--no-sandbox", "--disable-gpu",
                    "--window-size=1400,1800", f"--screenshot={screenshot}", page.as_uri()],
                   capture_output=True, timeout=120)
    import cv2

    image = cv2.imread(str(screenshot))
    assert image is not None and image.shape[:2] == (1800, 1400)
    assert np.std(image) > 10  # a drawn page, not a blank one


def test_refinement_that_raises_the_ate_is_flagged(tmp_path):
    """With ground truth at hand, a refined path farther from it than the input is listed
    as suspicious (on the page and in read_run_data)."""
    import json

    from cusfm_ros.core.trajectory import Trajectory
    from cusfm_ros.io.tum import write_tum
    from cusfm_ros.report.run_data import read_run_data

    stamps = np.arange(20, dtype=np.int64) * 100_000_000
    truth = np.tile(np.eye(4), (20, 1, 1))
    truth[:, 0, 3] = np.arange(20) * 1.0
    truth[:, 1, 3] = 0.05 * np.arange(20) ** 2  # a curve: SE(3) alignment is defined
    worse = truth.copy()
    worse[:, 2, 3] = np.sin(np.arange(20)) * 0.5  # wiggles the truth has not
    better = truth.copy()
    better[:, 2, 3] = np.sin(np.arange(20)) * 0.1
    run = tmp_path / "run"
    run.mkdir()
    (run / "report.json").write_text(json.dumps({"status": "complete", "stages": {}}))
    write_tum(tmp_path / "gt.tum", Trajectory(stamps, truth))
    for initial, refined, flagged in ((better, worse, True), (worse, better, False)):
        write_tum(run / "initial_poses.tum", Trajectory(stamps, initial))
        write_tum(run / "poses.tum", Trajectory(stamps, refined))
        data = read_run_data(run, tmp_path / "gt.tum")
        raised = [s for s in data.suspicious if "refinement raised the ATE" in s]
        assert bool(raised) == flagged, data.suspicious


def test_loop_edges_are_drawn_as_one_collection_where_the_ate_aligned_them(tmp_path):
    """Every loop edge in the top view, moved by the same alignment as the refined path
    (one artist for all of them: thousands of loops draw in a fraction of a second)."""
    from matplotlib.collections import LineCollection

    from cusfm_ros.core.evaluation import AteOptions, absolute_trajectory_error
    from cusfm_ros.core.geometry import Rigid3
    from cusfm_ros.core.trajectory import Trajectory
    from cusfm_ros.report.page import _trajectories
    from cusfm_ros.report.run_data import RunData

    stamps = np.arange(40, dtype=np.int64) * 100_000_000
    truth = np.repeat(np.eye(4)[None], 40, axis=0)
    truth[:, 0, 3] = 10 * np.cos(stamps * 1e-9)
    truth[:, 1, 3] = 10 * np.sin(stamps * 1e-9)
    offset = Rigid3.from_rotvec(np.array([0, 0, 0.3]), np.array([5.0, -2.0, 0.0])).matrix()
    refined = offset @ truth  # the run's own frame: the page aligns it to the truth
    data = RunData(tmp_path, truth=Trajectory(stamps, truth),
                   refined=Trajectory(stamps, refined))
    data.ate["refined"] = absolute_trajectory_error(data.truth, data.refined,
                                                    AteOptions(align="se3"))
    data.loops_xy = [(refined[i, :3, 3], refined[i + 20, :3, 3]) for i in range(0, 20, 2)]
    figure = _trajectories(data, (0, 1), "top")
    collections = [c for c in figure.axes[0].collections if isinstance(c, LineCollection)]
    assert len(collections) == 1
    segments = np.asarray(collections[0].get_segments())
    assert segments.shape == (10, 2, 2)
    expected = np.stack([[truth[i, :2, 3], truth[i + 20, :2, 3]] for i in range(0, 20, 2)])
    np.testing.assert_allclose(segments, expected, atol=1e-9)
    labels = [t.get_text() for t in figure.axes[0].get_legend().get_texts()]
    assert "loop edges" in labels

"""``report.html``: one self-contained page (figures inlined as PNG) of a run: summary and
accuracy tables, top- and side-view trajectories (initial, refined, ground truth; loop edges
drawn), ATE over time, where the time went per stage, reprojection-error and track-length
histograms, a top view of the point cloud, the extrinsic change per camera and the
``suspicious`` list.

Figures are drawn with matplotlib's object API (``Figure`` + the Agg canvas: no pyplot, no
global state), each by itself from its own arguments (``figure_map`` may draw them on
worker processes: the page of a 300-frame run cost the GPU machine 2 s in one process).
A small script marks each figure once its image has decoded (``data-loaded``) and counts
them on ``<body data-figures-loaded>``, which the browser test reads.
"""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from cusfm_ros.io.atomic import atomic_write
from cusfm_ros.report.run_data import RunData

COLOURS = {"initial": "#d62728", "refined": "#1f77b4", "truth": "#2ca02c", "loop": "#ff7f0e",
           "localized": "#9467bd"}
ATE_KEYS = {"initial": "input", "refined": "refined", "localized": "localized"}
_SCRIPT = """
window.addEventListener('load', function () {
  var loaded = 0;
  document.querySelectorAll('figure img').forEach(function (img) {
    if (img.complete && img.naturalWidth > 0) {
      img.parentNode.setAttribute('data-loaded', 'true'); loaded += 1;
    }
  });
  document.body.setAttribute('data-figures-loaded', String(loaded));
});
"""


def _png(figure) -> str:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(figure)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=90, bbox_inches="tight")
    return base64.b64encode(buffer.getvalue()).decode("ascii")


def _figure(width: float = 6.0, height: float = 4.0):
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width, height))
    return figure, figure.add_subplot()


def _trajectories(data: RunData, axes: tuple[int, int], title: str):
    figure, ax = _figure()
    aligned = {}
    if data.truth is not None:
        aligned["truth"] = data.truth.world_from_body[:, :3, 3]
    for label, trajectory in (("initial", data.initial), ("refined", data.refined),
                              ("localized", data.localized)):
        if trajectory is None:
            continue
        key = ATE_KEYS[label]
        poses = trajectory.world_from_body
        if key in data.ate:  # drawn as the ATE compares them: aligned to the ground truth
            poses = data.ate[key].alignment.transform_poses(poses)
        aligned[label] = poses[:, :3, 3]
    for label, xyz in aligned.items():
        style = {"ls": "none", "marker": "."} if label == "localized" else {}
        ax.plot(xyz[:, axes[0]], xyz[:, axes[1]], color=COLOURS[label], label=label,
                lw=1.2 if label != "truth" else 2.0, alpha=0.9, **style)
    if axes == (0, 1) and data.loops_xy and "refined" in aligned:
        from matplotlib.collections import LineCollection

        transform = data.ate["refined"].alignment if "refined" in data.ate else None
        ends = np.asarray(data.loops_xy, float)  # (loops, 2 ends, 3)
        if transform is not None:
            ends = transform.transform_points(ends.reshape(-1, 3)).reshape(ends.shape)
        # one artist for every loop edge (a line each took seconds to draw at 1,000 loops)
        ax.add_collection(LineCollection(ends[:, :, :2], colors=COLOURS["loop"],
                                         linewidths=0.6, label="loop edges"))
    ax.set_xlabel("xyz"[axes[0]] + " [m]")
    ax.set_ylabel("xyz"[axes[1]] + " [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    return figure


def _ate_over_time(data: RunData):
    figure, ax = _figure(6.0, 3.0)
    for label, key in ATE_KEYS.items():
        result = data.ate.get(key)
        if result is not None:
            ax.plot(np.arange(len(result.errors_m)), result.errors_m, color=COLOURS[label],
                    label=f"{label} (RMSE {result.rmse:.3f} m)")
    ax.set_xlabel("pose (time order)")
    ax.set_ylabel("position error [m]")
    ax.set_title("ATE over time (SE(3)-aligned)")
    ax.legend(fontsize=8)
    return figure


def _stage_times(data: RunData):
    stages = data.report.get("stages", {})
    names = list(stages)
    seconds = [float(stages[n].get("seconds") or 0.0) for n in names]
    figure, ax = _figure(6.0, 0.35 * len(names) + 1.0)
    ax.barh(names[::-1], seconds[::-1], color="#7f7f7f")
    ax.set_xlabel("seconds (this run; reused stages show 0)")
    ax.set_title(f"time per stage (total {sum(seconds):.1f} s)")
    return figure


def _histogram(values: np.ndarray, title: str, xlabel: str, bins):
    figure, ax = _figure(5.0, 3.0)
    ax.hist(values, bins=bins, color="#1f77b4")
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("count")
    return figure


def _cloud(data: RunData):
    figure, ax = _figure()
    points = data.points_m
    step = max(1, len(points) // 50000)
    colours = (data.rgb[::step] / 255.0) if data.rgb is not None else "#1f77b4"
    ax.scatter(points[::step, 0], points[::step, 1], s=0.5, c=colours, linewidths=0)
    if data.refined is not None:
        xyz = data.refined.world_from_body[:, :3, 3]
        ax.plot(xyz[:, 0], xyz[:, 1], color="k", lw=0.8, label="refined path")
        ax.legend(fontsize=8)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"point cloud, top view ({len(points)} points, map frame)")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    return figure


def _extrinsics(data: RunData):
    from matplotlib.figure import Figure

    figure = Figure(figsize=(6.0, 0.4 * len(data.extrinsics) + 1.5))
    left, right = figure.subplots(1, 2)
    names = [d.camera for d in data.extrinsics]
    left.barh(names, [d.translation_mm for d in data.extrinsics], color="#9467bd")
    left.set_xlabel("translation change [mm]")
    right.barh(names, [d.rotation_deg for d in data.extrinsics], color="#8c564b")
    right.set_xlabel("rotation change [deg]")
    right.set_yticklabels([])
    figure.suptitle("extrinsic change per camera (refined vs the bag's)")
    return figure


FigureMap = Callable[[Callable, Iterable], Iterable[str]]
"""``figure_map(_draw, specs)``: each figure's PNG in order (``map``, or on processes)."""


def _draw(spec: tuple[Callable, tuple]) -> str:
    """The base64 PNG of one figure: ``(drawing function, its arguments)``."""
    draw, arguments = spec
    return _png(draw(*arguments))


def figure_specs(data: RunData) -> list[tuple[str, str, tuple[Callable, tuple]]]:
    """(id, caption, (drawing function, its arguments)) for every figure the run's data
    allows: module-level functions and picklable arguments, for worker processes."""
    out = []
    if any(t is not None for t in (data.initial, data.refined, data.localized)):
        out.append(("trajectory-top", "Trajectory, top view", (
            _trajectories, (data, (0, 1), "trajectory, top view (x-y)"))))
        out.append(("trajectory-side", "Trajectory, side view", (
            _trajectories, (data, (0, 2), "trajectory, side view (x-z)"))))
    if data.ate:
        out.append(("ate", "ATE over time", (_ate_over_time, (data,))))
    if data.report.get("stages"):
        out.append(("stage-times", "Time per stage", (_stage_times, (data,))))
    if data.latency_s is not None and len(data.latency_s):
        median_ms = float(np.median(data.latency_s)) * 1e3
        out.append(("latency", "Localization latency", (_histogram, (
            data.latency_s * 1e3, f"latency per query (median {median_ms:.0f} ms)",
            "milliseconds", 30))))
    if data.reprojection_px is not None and len(data.reprojection_px):
        out.append(("reprojection", "Reprojection error", (_histogram, (
            data.reprojection_px, "reprojection error per observation", "pixels",
            np.linspace(0, max(4.0, float(np.percentile(data.reprojection_px, 99))), 50)))))
    if data.track_lengths is not None and len(data.track_lengths):
        top = int(max(data.track_lengths.max(), 2))
        out.append(("track-length", "Track length", (_histogram, (
            data.track_lengths, "observations per point", "track length",
            np.arange(1.5, top + 1.5)))))
    if data.points_m is not None and len(data.points_m):
        out.append(("cloud", "Point cloud", (_cloud, (data,))))
    if any(d.translation_mm > 1e-6 or d.rotation_deg > 1e-6 for d in data.extrinsics):
        out.append(("extrinsics", "Extrinsic change", (_extrinsics, (data,))))
    return out


def _table(rows: list[tuple[str, str]]) -> str:
    body = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>"
                   for k, v in rows)
    return f"<table>{body}</table>"


REPORT_FIGURES = ("stage-times", "latency")
"""Figures drawn from ``report.json`` (the stages' times, the queries), which changes to the
end of a run; the others are drawn from its results."""


def draw_result_figures(arguments: tuple) -> dict[str, str]:
    """(run directory, part, parts[, results]) -> {figure id: base64 PNG} of every
    ``part``-th figure (of ``parts``) that does not come from ``report.json``: module-level
    and one argument, for worker processes that draw them while later stages run (the
    mapper: from the mapping stage's results while the export writes its copies of them,
    ``results="mapping"``; see ``read_run_data``)."""
    from cusfm_ros.report.run_data import read_run_data

    run_dir, part, parts, *results = arguments
    data = read_run_data(run_dir, results=results[0] if results else "export")
    specs = [(figure_id, spec) for figure_id, _, spec in figure_specs(data)
             if figure_id not in REPORT_FIGURES]
    return {figure_id: _draw(spec) for figure_id, spec in specs[part::parts]}


def render(data: RunData, figure_map: FigureMap = map, drawn: dict[str, str] | None = None
           ) -> str:
    """The page; ``drawn``: figures already drawn (``draw_result_figures``), by id."""
    summary = data.report.get("summary") or {k: v for k, v in data.report.items()
                                             if k not in ("queries", "format")}
    rows = [(key.replace("_", " "), f"{value:.3f}" if isinstance(value, float) else str(value))
            for key, value in summary.items()
            if value is not None and not isinstance(value, dict)]
    for key, result in data.ate.items():
        rows.append((f"ATE {key} (SE(3))", f"RMSE {result.rmse:.3f} m, max {result.max:.3f} m"
                                           f" over {result.n} poses"))
    suspicious = ("<p>none</p>" if not data.suspicious else
                  "<ul>" + "".join(f"<li>{html.escape(s)}</li>" for s in data.suspicious)
                  + "</ul>")
    parts = []
    specs = figure_specs(data)
    drawn = {k: v for k, v in (drawn or {}).items() if k not in REPORT_FIGURES}
    todo = [s for s in specs if s[0] not in drawn]
    drawn = {**drawn, **dict(zip((s[0] for s in todo), figure_map(_draw, [s for *_, s in todo])))}
    for figure_id, caption, _ in specs:
        png = drawn[figure_id]
        parts.append(f'<figure id="{figure_id}"><img alt="{html.escape(caption)}" '
                     f'src="data:image/png;base64,{png}"><figcaption>'
                     f"{html.escape(caption)}</figcaption></figure>")
    title = f"cusfm run {data.root.name}"
    status = data.report.get("status")
    banner = ""
    if status in ("failed", "running"):
        what = (f"FAILED in stage {data.report.get('failed_stage')}: "
                f"{data.report.get('error', '')}" if status == "failed"
                else "RUNNING: not finished")
        banner = (f'<p id="status" style="background:#fdd;padding:0.5em">{html.escape(what)}.'
                  " The figures show what the completed stages left; nothing here is the "
                  "result of this run.</p>")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif;margin:1.5em;max-width:1400px}}
figure{{display:inline-block;margin:0.5em;vertical-align:top}}
table{{border-collapse:collapse}}th,td{{border:1px solid #ccc;padding:2px 8px;
text-align:left}}</style></head>
<body data-figures="{len(parts)}">
<h1>{html.escape(title)}</h1>
<p>{html.escape(str(data.root))}</p>{banner}
<h2>Summary</h2>{_table(rows)}
<h2>Suspicious</h2>{suspicious}
<h2>Figures</h2>
{''.join(parts)}
<script>{_SCRIPT}</script>
</body></html>
"""


def write_report_page(run_dir: str | Path, ground_truth: str | Path | None = None,
                      figure_map: FigureMap = map, drawn: dict[str, str] | None = None
                      ) -> Path:
    """Write ``RUN_DIR/report.html`` (atomically) and return its path; ``figure_map`` draws
    the figures not in ``drawn`` (the bytes depend on neither)."""
    from cusfm_ros.report.run_data import read_run_data

    path = Path(run_dir) / "report.html"
    page = render(read_run_data(run_dir, ground_truth), figure_map, drawn)
    with atomic_write(path) as handle:
        handle.write(page)
    return path


def write_page(run_dir: str | Path, ground_truth: str | Path | None = None,
               figure_map: FigureMap = map, drawn: dict[str, str] | None = None
               ) -> Path | None:
    """``write_report_page`` for the end of a run: a failure to draw is a warning, never a
    failed map."""
    import logging

    try:
        path = write_report_page(run_dir, ground_truth, figure_map, drawn)
    except Exception as exc:  # noqa: BLE001 - the run is done; the page is a view of it
        logging.getLogger(__name__).warning("report.html not written (%s: %s)",
                                            type(exc).__name__, exc)
        return None
    logging.getLogger(__name__).info("report: %s", path)
    return path

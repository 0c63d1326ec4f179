"""``cusfm report RUN_DIR [--ground-truth GT.tum]``: (re)build ``RUN_DIR/report.html``."""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("report", help="(re)build a run's report.html")
    parser.add_argument("run_dir")
    parser.add_argument("--ground-truth", default=None, metavar="TUM",
                        help="ground truth (TUM) to draw and to compute the ATE against")
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from cusfm_ros.errors import CusfmError
    from cusfm_ros.report.page import write_report_page

    if not (Path(args.run_dir) / "report.json").is_file():
        raise CusfmError(f"{args.run_dir}: no report.json, so not a finished cusfm run "
                         "directory (run `cusfm map` first)")
    print(write_report_page(args.run_dir, args.ground_truth))
    return 0

"""``cusfm evaluate GT.tum EST.tum``: absolute trajectory error with evo's conventions."""

from __future__ import annotations

import argparse
import json

from cusfm_ros.core.evaluation import ALIGNMENTS, AteOptions, absolute_trajectory_error
from cusfm_ros.io.tum import read_tum


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "evaluate", help="ATE of an estimated trajectory against ground truth (TUM files)",
        description="Associate poses by stamp, align the estimate onto the reference and print "
                    "the absolute trajectory error in metres (same numbers as evo_ape -a/-as).")
    parser.add_argument("reference", help="ground-truth TUM file (world_from_body)")
    parser.add_argument("estimate", help="estimated TUM file (world_from_body)")
    parser.add_argument("--align", choices=ALIGNMENTS, default="se3",
                        help="alignment of the estimate onto the reference (default: se3)")
    parser.add_argument("--max-diff", type=float, default=0.01, metavar="SECONDS",
                        help="largest stamp difference to associate two poses (default: 0.01)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    options = AteOptions(align=args.align, max_diff_s=args.max_diff)
    result = absolute_trajectory_error(read_tum(args.reference), read_tum(args.estimate),
                                       options)
    stats = result.stats()
    if args.json:
        print(json.dumps(stats))
        return 0
    scale = f", scale {result.alignment.scale:.6f}" if args.align == "sim3" else ""
    print(f"ATE ({args.align} alignment{scale}, {stats['n']} associated poses)")
    for key in ("rmse", "mean", "median", "std", "min", "max"):
        print(f"  {key:<7}{stats[key]:.6f} m")
    return 0

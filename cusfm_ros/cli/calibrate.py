"""``cusfm calibrate BAG --out RUN_DIR``: refine every camera's extrinsics from a recorded
drive and report, per camera, the change and how well the data constrains it
(``pipeline/calibration.py``)."""

from __future__ import annotations

import argparse

from cusfm_ros.cli.options import (add_bag_arguments, add_config_arguments,
                                   add_feature_arguments, resolved_options)
from cusfm_ros.io.run_dir import RunDir
from cusfm_ros.pipeline.calibration import ExtrinsicCalibration, calibration_report_path


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "calibrate", help="refine the rig's camera extrinsics from a bag, with a report")
    parser.add_argument("bag")
    parser.add_argument("--out", required=True, metavar="RUN_DIR")
    parser.add_argument("--overwrite", action="store_true",
                        help="redo the stages even if up to date")
    add_config_arguments(parser)
    add_bag_arguments(parser)
    add_feature_arguments(parser)
    parser.set_defaults(run=run)
    return parser


def _row(label: str, entry: dict) -> str:
    sigma_mm = "/".join("?" if v is None else f"{v:.1f}" for v in entry["sigma_mm"])
    sigma_deg = "/".join("?" if v is None else f"{v:.2f}" for v in entry["sigma_deg"])
    return (f"{label:<34} {entry['translation_change_norm_mm']:>9.1f} "
            f"{entry['rotation_change_deg']:>9.3f}  {sigma_mm} / {sigma_deg}")


def format_report(report: dict) -> list[str]:
    base = report["base_frame"]
    lines = [f"{'extrinsic':<34} {'moved mm':>9} {'moved deg':>9}  sigma xyz mm / rpy deg"]
    for name, entry in report["cameras"].items():
        lines.append(_row(f"{base} -> {name}", entry))
        if "relative" in entry:
            lines.append(_row(f"{entry['relative_to']} -> {name}", entry["relative"]))
    for name in report["unconstrained_cameras"]:
        entry = report["cameras"][name]
        axes = ", ".join(entry.get("relative", entry)["weak_axes"])
        lines.append(f"warning: the data does not pin down {name}: {axes} (sigma above half "
                     "the prior's); record more varied motion (turns, slopes) to calibrate it")
    return lines


def run(args: argparse.Namespace) -> int:
    report = ExtrinsicCalibration(resolved_options(args)).solve(args.bag, args.out,
                                                                args.overwrite)
    for line in format_report(report):
        print(line)
    print(f"refined extrinsics: {report['extrinsics']}; report: "
          f"{calibration_report_path(RunDir(args.out))}")
    return 0

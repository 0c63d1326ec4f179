"""``cusfm fleet BAG... --out FLEET_DIR [--ray-address auto|HOST:PORT] [--base-map MAP_DIR]``:
many drives into one map on Ray (``pipeline/fleet.py``)."""

from __future__ import annotations

import argparse
import json

from cusfm_ros.cli.options import (add_bag_arguments, add_config_arguments,
                                   add_feature_arguments, resolved_options)
from cusfm_ros.pipeline.fleet import FleetMapper, FleetOptions


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "fleet", help="map many drives into one map on a Ray cluster (or a local Ray)",
        description="Map every BAG on its own as Ray tasks (resumable; a bag that fails is "
                    "reported and left out), then merge them one by one with the map-update "
                    "path into --base-map or the first drive's map. FLEET_DIR must be "
                    "reachable by every worker.")
    parser.add_argument("bags", nargs="+", metavar="BAG")
    parser.add_argument("--out", required=True, metavar="FLEET_DIR")
    parser.add_argument("--ray-address", default=None,
                        help="a running Ray cluster (auto or HOST:PORT); default: start a "
                             "local Ray instance")
    parser.add_argument("--workers", type=int, default=0,
                        help="CPUs of the local Ray instance (default: all)")
    parser.add_argument("--base-map", default=None, metavar="MAP_DIR",
                        help="merge every drive into this map (never written)")
    parser.add_argument("--mode", choices=("fixed", "adjust"), default=None,
                        help="how drives join the map (default: fixed with --base-map, "
                             "else adjust)")
    parser.add_argument("--max-retries", type=int, default=2,
                        help="reruns of a task whose worker died")
    add_feature_arguments(parser)
    add_config_arguments(parser)
    add_bag_arguments(parser)
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    mode = args.mode or ("fixed" if args.base_map else "adjust")
    fleet = FleetOptions(ray_address=args.ray_address, workers=args.workers, mode=mode,
                         max_retries=args.max_retries)
    report = FleetMapper(resolved_options(args), fleet).solve(args.bags, args.out,
                                                              args.base_map)
    print(json.dumps({"map": report["map"], "drives": len(report["trajectories"]),
                      "dropped": report["dropped"]}))
    print(f"outputs: {args.out}/trajectories/*.tum, merges/, sessions/; map: {report['map']}; "
          f"report: {args.out}/report.json")
    return 0

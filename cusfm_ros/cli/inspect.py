"""``cusfm inspect BAG``: topics, cameras, pose sources and what the mapper would use."""

from __future__ import annotations

import argparse

from cusfm_ros.io.bags.summary import format_summary, summarize


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("inspect", help="describe a bag and what the mapper would use")
    parser.add_argument("bag", help="rosbag2 directory, .mcap/.db3 file or ROS 1 .bag")
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    summary = summarize(args.bag)
    print(format_summary(summary))
    return 1 if summary.problems else 0

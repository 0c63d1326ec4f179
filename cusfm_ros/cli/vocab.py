"""``cusfm vocab build RUN_DIR`` / ``cusfm vocab extend RUN_DIR``: the run's own vocabulary."""

from __future__ import annotations

import argparse

from cusfm_ros.cli.options import add_config_arguments, resolved_options
from cusfm_ros.errors import ConfigError
from cusfm_ros.io.feature_store import FeatureStore
from cusfm_ros.io.run_dir import RunDir
from cusfm_ros.io.vocabulary_file import load_birch, save_birch, save_vocabulary
from cusfm_ros.pipeline.mapper import Mapper


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("vocab", help="build or extend a run's vocabulary")
    parser.add_argument("action", choices=("build", "extend"))
    parser.add_argument("run_dir")
    parser.add_argument("--method", dest="vocab_method", choices=("kmeans", "birch"),
                        default=None)
    parser.add_argument("--branching", type=int, default=None)
    parser.add_argument("--depth", type=int, default=None)
    parser.add_argument("--from", dest="source", default=None, metavar="OTHER_RUN_DIR",
                        help="extend: the run whose features join the vocabulary")
    add_config_arguments(parser)
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    for key, value in (("branching", args.branching), ("depth", args.depth)):
        if value is not None:
            args.set_options.append(f"vocabulary.{key}={value}")
    options = resolved_options(args)
    run_dir = RunDir(args.run_dir)
    if args.action == "build":
        report = Mapper(options).solve(None, run_dir.root, ["vocabulary"], overwrite=True)
        print(f"vocabulary: {report['stages']['vocabulary']['words']} words in "
              f"{report['stages']['vocabulary']['seconds']:.1f} s -> {run_dir.vocabulary}")
        return 0
    # extend: stream another run's descriptors into this run's CF tree (map growth)
    if not args.source:
        raise ConfigError("vocab extend needs --from OTHER_RUN_DIR (the new session's run)")
    builder = load_birch(run_dir.birch_state)
    documents, new = [], []
    for source in (run_dir, RunDir(args.source)):
        with FeatureStore(source.features, {}, read_only=True) as store:
            batch = [store.features(name).descriptors for name in store.feature_names()]
        documents += batch
        if source is not run_dir:
            new = batch
    for descriptors in new:
        builder.insert(descriptors)
    tree = builder.solve(documents)
    save_vocabulary(run_dir.vocabulary, tree)
    save_birch(run_dir.birch_state, builder)
    print(f"vocabulary: {builder.count} descriptors in the CF tree -> {tree.num_words} words")
    return 0

"""``cusfm vocab build RUN_DIR`` / ``cusfm vocab extend RUN_DIR``: the run's own vocabulary."""

from __future__ import annotations

import argparse

from cusfm_ros.cli.match import add_feature_arguments, feature_options
from cusfm_ros.io.vocabulary_file import load_birch, save_birch, save_vocabulary
from cusfm_ros.errors import ConfigError
from cusfm_ros.pipeline.retrieval import (VocabularyStage, VocabularyStageOptions,
                                          open_store, vocabulary_path)


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("vocab", help="build or extend a run's vocabulary")
    parser.add_argument("action", choices=("build", "extend"))
    parser.add_argument("run_dir")
    parser.add_argument("--method", choices=("kmeans", "birch"), default="kmeans")
    parser.add_argument("--branching", type=int, default=10)
    parser.add_argument("--depth", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--from", dest="source", default=None, metavar="OTHER_RUN_DIR",
                        help="extend: the run whose features join the vocabulary")
    add_feature_arguments(parser)
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    features = feature_options(args)
    if args.action == "build":
        options = VocabularyStageOptions(method=args.method, branching=args.branching,
                                         depth=args.depth, seed=args.seed)
        result = VocabularyStage(options, features).solve(args.run_dir, overwrite=True)
        print(f"vocabulary: {result.counts['words']} words in {result.seconds:.1f} s -> "
              f"{vocabulary_path(args.run_dir)}")
        return 0
    # extend: stream another run's descriptors into this run's CF tree (map growth)
    if not args.source:
        raise ConfigError("vocab extend needs --from OTHER_RUN_DIR (the new session's run)")
    out = vocabulary_path(args.run_dir)
    builder = load_birch(out.with_name("birch_state.npz"))
    documents = []
    for run in (args.run_dir, args.source):
        with open_store(run, features) as store:
            documents += [store.features(name).descriptors for name in store.feature_names()]
    with open_store(args.source, features) as store:
        for name in store.feature_names():
            builder.insert(store.features(name).descriptors)
    tree = builder.solve(documents)
    save_vocabulary(out, tree)
    save_birch(out.with_name("birch_state.npz"), builder)
    print(f"vocabulary: {builder.count} descriptors in the CF tree -> {tree.num_words} words")
    return 0

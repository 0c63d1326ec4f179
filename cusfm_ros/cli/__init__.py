"""The ``cusfm`` command line: argument parsing per subcommand, separate from ``run``."""

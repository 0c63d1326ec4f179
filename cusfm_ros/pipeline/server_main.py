"""Imported first by the fork server of the worker processes (``parallel.py`` preloads it):
it loads the parent's main module there once, as ``__mp_main__``, so that every worker forked
from the server finds it loaded instead of running the main script again.

multiprocessing is meant to do this when ``"__main__"`` is preloaded, but before Python 3.13
the path never reaches the server (CPython gh-126631: ``forkserver.ensure_running`` passes
``main_path``, which ``spawn.get_preparation_data`` stopped providing in 3.4). Each worker then
ran the ``cusfm`` script again in ``spawn.prepare``, importing the whole CLI: 0.29-0.36 s of
one core per worker on the 2-core machine, and 16 workers starting beside a GPU stage slowed
it by ~0.75 s on the 16-core GPU machine (street 200). Written by hand: no library fixes the
standard library's server; where Python does it itself the calls below find the main module
loaded and return at once.

The parent names its main module in ``CUSFM_WORKERS_MAIN`` (``path:FILE`` or
``name:MODULE``) before it starts the server, which inherits its environment.
"""

from __future__ import annotations

import os
from multiprocessing import process, spawn

MAIN_VARIABLE = "CUSFM_WORKERS_MAIN"


def main_reference(preparation: dict) -> str | None:
    """``path:FILE`` or ``name:MODULE`` for the main module that ``spawn.prepare`` loads in
    each worker (its ``preparation`` data), or None where it loads none."""
    if "init_main_from_name" in preparation:
        return f"name:{preparation['init_main_from_name']}"
    if "init_main_from_path" in preparation:
        return f"path:{preparation['init_main_from_path']}"
    return None


def load_main(reference: str | None) -> None:
    """What ``spawn.prepare`` does in a worker, done once here; while it runs, a process
    started from the main script's top level is refused, as in a worker."""
    kind, _, value = (reference or "").partition(":")
    if kind not in ("path", "name"):
        return
    process.current_process()._inheriting = True
    try:
        if kind == "path":
            spawn.import_main_path(value)
        else:
            spawn._fixup_main_from_name(value)
    finally:
        del process.current_process()._inheriting


try:
    load_main(os.environ.get(MAIN_VARIABLE))
except Exception:  # noqa: BLE001 - the workers then load it themselves, as before
    pass

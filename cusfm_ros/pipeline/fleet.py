"""Fleet mapping on Ray: many drives into one map.

1. Every bag is mapped on its own as one Ray task (``Mapper`` into
   ``FLEET/sessions/<name>/``: keyframes ... map), the tasks spread over the cluster, a GPU
   requested per task when the cluster has GPUs and the options ask for one. A task is
   idempotent and resumable: the stage runner's fingerprints reuse what is complete and
   redo what a killed worker left half-written, so Ray's retry of a task whose worker died
   continues that drive's work instead of trusting or repeating it.
2. A bag that fails (corrupt, no calibration, no parallax ...) is reported with its reason
   and left out; the others go on.
3. The merge runs the map-update path (``update_map``) once per drive, each a Ray task, in
   bag order: into ``--base-map`` when given (``fixed`` keeps it exactly), else into the first
   drive's own map; each merge reuses the drive's front stages from step 1 and fans the
   localization of the drive's samples against the map (retrieval, matching, pose) out over
   Ray tasks. The last merge is the fleet's map, with every drive's trajectory.

Without ``--base-map`` the drives share one vocabulary: every drive's descriptors streamed
into one BIRCH CF tree (a Ray task; memory follows the tree, not the fleet), refined into
``FLEET/vocabulary/vocabulary.npz``; the first drive's map is re-indexed with it
(``FLEET/base/``) and the merges start from there. With ``--base-map`` its vocabulary stays.

Outputs in ``FLEET``: ``sessions/<name>/`` (each drive alone), ``merges/<name>/`` (the map
after merging that drive), ``trajectories/<name>.tum`` (each drive's refined poses in the merged
map), ``map`` (the path of the final map directory, a text file) and ``report.json``
(written last, ``status``: complete when at least one drive made it into the map).

Artifacts move through the file system: ``FLEET`` must be a path every worker can reach
(a shared volume on a cluster; a local folder on one machine).
"""

from __future__ import annotations

import json
import logging
import os
import resource
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import ConfigError, CusfmError
from cusfm_ros.io.atomic import atomic_write
from cusfm_ros.io.tum import read_tum, write_tum

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FleetOptions:
    ray_address: str | None = None
    """A running cluster (``auto`` or ``HOST:PORT``); None starts a local Ray instance."""
    workers: int = 0
    """CPUs of the local instance (0: all); ignored with ``ray_address``."""
    mode: str = "adjust"
    """How each drive joins the map (``fixed`` | ``adjust``, as ``cusfm map-update``)."""
    max_retries: int = 2
    """Reruns of a task whose worker died (killed, out of memory, lost node)."""

    def __post_init__(self) -> None:
        if self.mode not in ("fixed", "adjust"):
            raise ConfigError(f"fleet mode must be fixed or adjust, got {self.mode!r}")
        if self.workers < 0 or self.max_retries < 0:
            raise ConfigError("fleet workers and max_retries must be >= 0")


def session_names(bags: list[str | os.PathLike]) -> list[str]:
    """One distinct, readable name per bag: ``<k>_<folder name>``."""
    return [f"{k:02d}_{Path(bag).name}" for k, bag in enumerate(bags)]


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def map_session(bag: str, run_dir: str, options) -> dict:
    """A Ray task: one drive mapped alone (resumes a killed run)."""
    from cusfm_ros.pipeline.mapper import Mapper

    started = time.perf_counter()
    report = Mapper(options).solve(bag, run_dir)
    return {"run": run_dir, "seconds": time.perf_counter() - started,
            "keyframes": report.get("summary", {}).get("keyframes"),
            "stages_run": [name for name, stage in report["stages"].items()
                           if not stage.get("reused")],
            "worker_pid": os.getpid(), "worker_peak_rss_mb": _peak_rss_mb()}


def merge_session(map_dir: str, bag: str, session_dir: str, out_dir: str, options,
                  mode: str) -> dict:
    """A Ray task: one drive merged into a map (``update_map``)."""
    import ray

    from cusfm_ros.pipeline.map_update import MapUpdateOptions, localize_samples, update_map

    def fan_out(chunks: list[list[str]]) -> list[dict]:
        """The drive's samples localized against the map in parallel Ray tasks."""
        task = ray.remote(max_retries=2)(localize_samples)
        return ray.get([task.remote(map_dir, session_dir, ids, options) for ids in chunks])

    started = time.perf_counter()
    counts = update_map(map_dir, bag, out_dir, options, MapUpdateOptions(mode=mode),
                        session_dir=session_dir, fan_out=fan_out)
    return {"out": out_dir, "seconds": time.perf_counter() - started,
            "localized": counts["localized"], "new_samples": counts["new_samples"],
            "points": counts["points"], "worker_pid": os.getpid(),
            "worker_peak_rss_mb": _peak_rss_mb()}


def _descriptors(session_dirs: list[str]):
    """Every image's descriptors of these runs, one image at a time."""
    from cusfm_ros.io.feature_store import FeatureStore
    from cusfm_ros.io.run_dir import RunDir

    for session in session_dirs:
        with FeatureStore(RunDir(Path(session)).features, {}, read_only=True) as store:
            for name in store.feature_names():
                yield store.features(name).descriptors


def build_fleet_vocabulary(session_dirs: list[str], path: str, options) -> dict:
    """A Ray task: one vocabulary over every drive, grown incrementally — each drive's
    descriptors streamed into one BIRCH CF tree (memory follows the tree's entries, not the
    fleet's descriptors), refined into the vocabulary tree, IDF from a second stream."""
    from cusfm_ros.io.vocabulary_file import save_vocabulary
    from cusfm_ros.pipeline.stages.vocabulary import birch_builder

    builder = birch_builder(options.vocabulary, options.seed)
    started = time.perf_counter()
    for descriptors in _descriptors(session_dirs):
        builder.insert(descriptors)
    tree = builder.solve(None)
    tree.set_idf(_descriptors(session_dirs))
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    save_vocabulary(path, tree)
    return {"path": path, "descriptors": builder.count, "entries": len(builder
                                                                    .clustering_features()[0]),
            "words": tree.num_words, "seconds": time.perf_counter() - started,
            "worker_peak_rss_mb": _peak_rss_mb()}


def reindex_map(map_dir: str, session_dir: str, vocabulary_path: str, out_dir: str) -> str:
    """A copy of a drive's map whose retrieval uses the fleet's vocabulary: every keyframe's
    TF-IDF vector recomputed from all its keypoints (the drive's feature store)."""
    import scipy.sparse as sp

    from cusfm_ros.core.retrieval.database import ImageDatabase
    from cusfm_ros.io.feature_store import FeatureStore
    from cusfm_ros.io.map_store import map_poses_text, read_map_store, write_map_store
    from cusfm_ros.io.run_dir import RunDir
    from cusfm_ros.io.vocabulary_file import load_vocabulary

    prior = read_map_store(map_dir, mmap=False)
    vocabulary = load_vocabulary(vocabulary_path)
    database = ImageDatabase(vocabulary)
    with FeatureStore(RunDir(Path(session_dir)).features, {}, read_only=True) as store:
        rows = database.bows(store.features(k.image_name).descriptors
                             for k in prior.keyframes.keyframes)
    out = Path(out_dir) / "map"
    write_map_store(out, replace(prior, vocabulary=vocabulary, bow=sp.vstack(rows).tocsr()),
                    map_poses_text(map_dir))
    return str(out)


def _reason(error: BaseException) -> str:
    """The one-line reason of a failed task (the CusfmError inside Ray's wrapper)."""
    cause = getattr(error, "cause", None) or error
    return str(cause).strip().splitlines()[0] if str(cause).strip() else type(cause).__name__


class FleetMapper:
    def __init__(self, options, fleet: FleetOptions = FleetOptions()) -> None:
        self.options = options
        self.fleet = fleet

    def _start_ray(self, scratch: str):
        """``scratch``: the local workers' temporary folder (``TMPDIR``), removed after the
        run: Ray ends its workers without their exit handlers, which left each one's
        multiprocessing folder (``pymp-*``) in /tmp."""
        import ray

        env = {k: v for k, v in os.environ.items() if k.startswith("CUSFM_")}
        if self.fleet.ray_address:
            ray.init(address=self.fleet.ray_address, runtime_env={"env_vars": env},
                     log_to_driver=False)
        else:
            # a local instance listens on the loopback only
            ray.init(num_cpus=self.fleet.workers or os.cpu_count(), include_dashboard=False,
                     runtime_env={"env_vars": {**env, "TMPDIR": scratch}},
                     log_to_driver=False, _node_ip_address="127.0.0.1")
        gpus = ray.cluster_resources().get("GPU", 0)
        logger.info("fleet: Ray %s, %d CPUs, %d GPUs", ray.__version__,
                    int(ray.cluster_resources().get("CPU", 0)), int(gpus))
        return ray, (1 if gpus and self.options.device != "cpu" else 0)

    def solve(self, bags: list[str | os.PathLike], out_dir: str | os.PathLike,
              base_map: str | os.PathLike | None = None) -> dict:
        if not bags:
            raise ConfigError("fleet: no bags given")
        out = Path(out_dir)
        if out.exists() and not out.is_dir():
            raise ConfigError(f"--out {out} is a file; give a directory for the fleet")
        if out.is_dir() and any(out.iterdir()) and not (out / "sessions").is_dir():
            raise ConfigError(f"--out {out} is not empty and not a fleet directory; choose a "
                              "new or empty directory (nothing in it is deleted)")
        out.mkdir(parents=True, exist_ok=True)
        (out / "report.json").unlink(missing_ok=True)
        started = time.perf_counter()
        names = session_names(bags)
        bag_of = dict(zip(names, (str(Path(b).resolve()) for b in bags)))
        with tempfile.TemporaryDirectory(prefix="cusfm-fleet-",
                                         ignore_cleanup_errors=True) as scratch:
            ray, gpus = self._start_ray(scratch)
            try:
                sessions, dropped = self._map_sessions(ray, gpus, out, names, bag_of)
                vocabulary, start = None, base_map
                if base_map is None and sessions:
                    vocabulary, start = self._vocabulary(ray, out, names, sessions)
                merges, final = self._merge(ray, gpus, out, names, bag_of, sessions, dropped,
                                            start, base_map is not None)
            finally:
                ray.shutdown()
        trajectories = self._trajectories(out, final, names, sessions, dropped)
        report = {"format": "cusfm_fleet_report/1",
                  "status": "complete" if final is not None else "failed",
                  "bags": bag_of, "base_map": None if base_map is None else str(base_map),
                  "mode": self.fleet.mode, "sessions": sessions, "vocabulary": vocabulary,
                  "merges": merges,
                  "dropped": dropped, "map": None if final is None else str(final),
                  "trajectories": trajectories, "seconds": time.perf_counter() - started}
        if final is not None:
            with atomic_write(out / "map") as handle:
                handle.write(f"{final}\n")
        with atomic_write(out / "report.json") as handle:
            json.dump(report, handle, indent=1)
        if final is None:
            raise CusfmError(f"fleet: no drive could be mapped ({len(dropped)} dropped: "
                             f"{'; '.join(d['bag'] + ': ' + d['reason'] for d in dropped)})")
        logger.info("fleet: %d drives in one map (%d dropped) -> %s in %.1f s",
                    len(trajectories), len(dropped), final, report["seconds"])
        return report

    # ------------------------------------------------------------------------ per drive
    def _map_sessions(self, ray, gpus: int, out: Path, names: list[str],
                      bag_of: dict[str, str]) -> tuple[dict, list]:
        task = ray.remote(num_gpus=gpus, max_retries=self.fleet.max_retries)(map_session)
        pending = {task.remote(bag_of[n], str(out / "sessions" / n), self.options): n
                   for n in names}
        sessions, dropped, tick = {}, [], time.perf_counter()
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            name = pending.pop(done[0])
            try:
                sessions[name] = ray.get(done[0])
            except Exception as error:  # noqa: BLE001 - any task failure drops that bag only
                dropped.append({"session": name, "bag": bag_of[name],
                                "reason": _reason(error)})
                logger.warning("fleet: %s dropped: %s", bag_of[name], dropped[-1]["reason"])
            finished = len(sessions) + len(dropped)
            rate = finished / (time.perf_counter() - tick)
            logger.info("fleet: %d/%d drives mapped (%d dropped), %.2f drives/min, ETA %.0f s",
                        finished, len(names), len(dropped), 60 * rate,
                        len(pending) / max(rate, 1e-9))
        return sessions, dropped

    # ----------------------------------------------------------------------- vocabulary
    def _vocabulary(self, ray, out: Path, names: list[str], sessions: dict
                    ) -> tuple[dict, Path]:
        """The fleet's vocabulary (every drive), and the first drive's map re-indexed with
        it: the merges start from there, so the merged map retrieves with it."""
        runs = [sessions[n]["run"] for n in names if n in sessions]
        build = ray.remote(max_retries=self.fleet.max_retries)(build_fleet_vocabulary)
        try:
            vocabulary = ray.get(build.remote(runs, str(out / "vocabulary" / "vocabulary.npz"),
                                              self.options))
        except Exception as error:  # noqa: BLE001 - Ray wraps the task's error
            raise CusfmError(f"fleet: the shared vocabulary failed: {_reason(error)}") from None
        logger.info("fleet: vocabulary of %d words from %d descriptors of %d drives "
                    "(%d CF entries) in %.1f s", vocabulary["words"],
                    vocabulary["descriptors"], len(runs), vocabulary["entries"],
                    vocabulary["seconds"])
        reindex = ray.remote(max_retries=self.fleet.max_retries)(reindex_map)
        first = runs[0]
        try:
            ray.get(reindex.remote(first, first, vocabulary["path"], str(out / "base")))
        except Exception as error:  # noqa: BLE001 - Ray wraps the task's error
            raise CusfmError(f"fleet: re-indexing the first drive's map failed: "
                             f"{_reason(error)}") from None
        return vocabulary, out / "base"

    # ---------------------------------------------------------------------------- merge
    def _merge(self, ray, gpus: int, out: Path, names: list[str], bag_of: dict[str, str],
               sessions: dict, dropped: list, start, external: bool
               ) -> tuple[list, Path | None]:
        """Each drive merged in turn into ``start`` (the base map, or the first drive's map
        re-indexed); with an ``external`` base map every drive joins it."""
        order = [n for n in names if n in sessions]
        if not order:
            return [], None
        current = Path(start)
        todo = order if external else order[1:]
        task = ray.remote(num_gpus=gpus, max_retries=self.fleet.max_retries)(merge_session)
        merges = []
        for k, name in enumerate(todo, start=1):
            target = out / "merges" / name
            try:
                result = ray.get(task.remote(str(current), bag_of[name], sessions[name]["run"],
                                             str(target), self.options, self.fleet.mode))
            except Exception as error:  # noqa: BLE001 - a drive that cannot join is dropped
                dropped.append({"session": name, "bag": bag_of[name],
                                "reason": "merge: " + _reason(error)})
                logger.warning("fleet: %s left out of the merge: %s", bag_of[name],
                               dropped[-1]["reason"])
                continue
            merges.append({"session": name, **result})
            current = target
            logger.info("fleet: merged %d/%d (%s): %d of %d samples localized, %d points",
                        k, len(todo), name, result["localized"], result["new_samples"],
                        result["points"])
        if not merges and not external:  # one drive: its own map is the fleet's
            return merges, Path(sessions[order[0]]["run"])
        return merges, current

    def _trajectories(self, out: Path, final: Path | None, names: list[str], sessions: dict,
                      dropped: list) -> dict[str, str]:
        """Each drive's poses in the final map: its stamps picked out of the map's poses
        (drives never share stamps: map update refuses overlapping ones)."""
        if final is None:
            return {}
        merged = read_tum(final / "poses.tum")
        left_out = {d["session"] for d in dropped}
        written = {}
        for name in names:
            if name not in sessions or name in left_out:
                continue
            own = read_tum(Path(sessions[name]["run"]) / "poses.tum")
            keep = (merged.stamps_ns >= own.stamps_ns[0]) & (merged.stamps_ns <=
                                                             own.stamps_ns[-1])
            if not keep.any():
                continue
            path = out / "trajectories" / f"{name}.tum"
            path.parent.mkdir(parents=True, exist_ok=True)
            write_tum(path, Trajectory(merged.stamps_ns[keep], merged.world_from_body[keep]))
            written[name] = str(path)
        return written

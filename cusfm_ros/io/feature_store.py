"""Features per keyframe and matches per pair in one HDF5 file of the run directory.

Layout (h5py):
    /                      attrs: format, config (JSON of the extractor/matcher options)
    /features/<image>      keypoints_px (N, 2), scores (N,), descriptors (N, D);
                           attrs: image_size, complete
    /match_blocks/<n>      the pairs matched in one flush interval, in bulk: pairs (UTF-8
                           JSON of [image0, image1, count] per pair), indices (K, 2) int32 and
                           confidences (K,) of all of them, one pair after the other; attrs:
                           complete. A later block's pair replaces an earlier one's.
    /matches/<pair key>    indices (K, 2), confidences (K,); attrs: image0, image1, complete
                           (one group per pair: the layout before format 2, still read)

Image names may contain "/" (camera sub-folders); they are escaped so every entry is one group.
An entry counts only once its ``complete`` flag is set (written last), so a run killed mid-write
is resumed by redoing just the incomplete entry. Writes reach the file at least every
``flush_interval_s`` (and when the store closes, which an exception or Ctrl-C also does): an
HDF5 flush per entry cost 2.5 ms, three times the write itself (2048 ALIKED features), so a
kill -9 now loses at most that interval's entries. Matches wait in memory until then and go
out as one block: a group and two datasets per pair cost the stages' main thread 1.5-2.5 ms
each on the GPU machine (a third of the matching stage's main thread at 300 frames), where
the pairs are many and their matches small. A block read once stays in memory while the store
is open. Opening a store made with another
configuration raises, unless ``overwrite`` starts it afresh; a cache (``reset_on_mismatch``)
starts afresh by itself, and ``recover`` replaces a file HDF5 cannot open (a kill mid-write).
"""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import numpy as np

from cusfm_ros.core.features.types import Features, Matches
from cusfm_ros.errors import CusfmError, FormatError

FORMAT = "cusfm_features/2"
READABLE_FORMATS = ("cusfm_features/1", FORMAT)
"""Format 1 kept one group per pair of matches; its files are read and appended to (their
new matches go to blocks)."""


def _key(name: str) -> str:
    return name.replace("%", "%25").replace("/", "%2F")


def _unkey(key: str) -> str:
    return key.replace("%2F", "/").replace("%25", "%")


_MEMO_LOCK = threading.Lock()
_memo: tuple[tuple, dict[str, Features]] = ((), {})


def _features_read_before(path: Path) -> dict[str, Features]:
    """The features already read (read-only) from the store at ``path`` in this process, while
    its file is unchanged (same device, inode, size and modification time); a store of
    features in another file, or this one changed, starts afresh (so a long-lived process
    holds one store's features at most; stores of matches alone keep none). Every stage
    after extraction reads the features of most images again: from HDF5 that cost the GPU
    machine's main thread 0.6-1.6 s per stage at 300 frames, where other threads wanted the
    interpreter too."""
    global _memo
    identity = _identity(path)
    with _MEMO_LOCK:
        if _memo[0] != identity:
            _memo = (identity, {})
        return _memo[1]


def _remember_written(path: Path, written: dict[str, Features]) -> None:
    """The features a store just wrote (and closed), as the memo of its file as it is now:
    the stage after extraction (the vocabulary's) then reads them from memory too."""
    global _memo
    identity = _identity(path)
    with _MEMO_LOCK:
        _memo = (identity, {name: _frozen(f) for name, f in written.items()})


def _identity(path: Path) -> tuple:
    info = path.stat()
    return (str(path.resolve()), info.st_dev, info.st_ino, info.st_size, info.st_mtime_ns)


def _frozen(features: Features) -> Features:
    """The features with read-only arrays: what is shared between stages cannot be changed
    by one of them."""
    for array in (features.keypoints_px, features.scores, features.descriptors):
        array.flags.writeable = False
    return features


class FeatureStore:
    """``with FeatureStore(path, config) as store: store.put_features(name, f) ...``

    A read-only store remembers the features it reads for the next read-only store of the
    same unchanged file in this process (``_features_read_before``), and a store that wrote
    features remembers those it wrote."""

    def __init__(self, path: str | os.PathLike, config: dict, overwrite: bool = False,
                 recover: bool = False, reset_on_mismatch: bool = False,
                 read_only: bool = False, flush_interval_s: float = 1.0) -> None:
        self.path = Path(path)
        self.flush_interval_s = flush_interval_s
        self._flushed_at = time.monotonic()
        self.config = json.dumps(config, sort_keys=True, default=str)
        self.overwrite = overwrite
        self.recover = recover
        self.reset_on_mismatch = reset_on_mismatch
        self.read_only = read_only
        self._file = None
        self._index: dict[tuple[str, str], tuple[str, int, int]] = {}
        """(image0, image1) -> (block name, first row, rows), or (group name, 0, -1) for a
        format 1 group of one pair."""
        self._pending: dict[tuple[str, str], Matches] = {}
        self._blocks: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._read: dict[str, Features] | None = None
        self._put: dict[str, Features] = {}

    def _open(self):
        import h5py

        if self.read_only:
            if not self.path.is_file():
                raise FormatError(self.path, None, "no such store", "run the stage that "
                                  "writes it")
            return h5py.File(self.path, "r")
        return h5py.File(self.path, "a")

    def __enter__(self) -> FeatureStore:
        if not self.read_only:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if self.overwrite and self.path.exists():
                self.path.unlink()
        try:
            self._file = self._open()
        except OSError as exc:
            if not (self.recover or self.reset_on_mismatch) or self.read_only:
                raise FormatError(self.path, None, f"cannot open the store ({exc})",
                                  "rerun the stage that writes it with --overwrite") from None
            self.path.unlink()
            self._file = self._open()
        attrs = self._file.attrs
        if self.read_only:  # the runner's fingerprints tie a reader to its producer
            if attrs.get("format") not in READABLE_FORMATS:
                self._file.close()
                raise FormatError(self.path, None, "not a cusfm feature store",
                                  "rerun the stage that writes it with --overwrite")
            self._load_index()
            features = self._file.get("features")
            if features is not None and len(features):  # not a store of matches alone
                self._read = _features_read_before(self.path)
            return self
        if "format" not in attrs:
            attrs["format"], attrs["config"] = FORMAT, self.config
        elif attrs.get("format") not in READABLE_FORMATS or attrs.get("config") != self.config:
            stored = attrs.get("config")
            self._file.close()
            if self.reset_on_mismatch:
                self.path.unlink()
                return self.__enter__()
            raise CusfmError(f"{self.path} holds data of another configuration ({stored});"
                             " rerun the stage that writes it (--overwrite)")
        self._file.require_group("features")
        self._file.require_group("matches")
        self._file.require_group("match_blocks")
        self._load_index()
        return self

    def __exit__(self, *exc_info) -> None:
        if self._file is not None:
            try:
                if not self.read_only:
                    self._write_block()
            finally:
                self._file.close()
                self._file = None
                self._blocks.clear()
            if self._put and exc_info[0] is None:
                _remember_written(self.path, self._put)
            self._put = {}

    def _written(self) -> None:
        """An entry is complete: flush it to the file once the interval has passed."""
        now = time.monotonic()
        if now - self._flushed_at >= self.flush_interval_s:
            self._write_block()
            self._file.flush()
            self._flushed_at = now

    def _load_index(self) -> None:
        """Where each complete pair's matches are: format 1's groups, then the blocks in the
        order they were written (a later one replaces a pair)."""
        self._index.clear()
        legacy = self._file.get("matches")
        for key, group in (legacy.items() if legacy is not None else ()):
            if group.attrs.get("complete", False):
                self._index[(group.attrs["image0"], group.attrs["image1"])] = (key, 0, -1)
        blocks = self._file.get("match_blocks")
        for name in sorted(blocks, key=int) if blocks is not None else ():
            block = blocks[name]
            if not block.attrs.get("complete", False):
                continue
            start = 0
            for image0, image1, count in json.loads(bytes(block["pairs"][()]).decode()):
                self._index[(image0, image1)] = (name, start, count)
                start += count

    def _write_block(self) -> None:
        """The matches put since the last block, as one more block."""
        if not self._pending:
            return
        blocks = self._file["match_blocks"]
        name = str(max((int(n) for n in blocks), default=-1) + 1)
        items = list(self._pending.items())
        group = blocks.create_group(name)
        pairs = [[a, b, len(m)] for (a, b), m in items]
        group.create_dataset("pairs", data=np.frombuffer(json.dumps(pairs).encode(), np.uint8))
        group.create_dataset("indices", data=np.concatenate(
            [m.indices.reshape(-1, 2) for _, m in items]).astype(np.int32))
        group.create_dataset("confidences", data=np.concatenate(
            [m.confidences for _, m in items]).astype(np.float32))
        group.attrs["complete"] = True
        self._file.attrs["format"] = FORMAT
        start = 0
        for (pair, _), (_, _, count) in zip(items, pairs):
            self._index[pair] = (name, start, count)
            start += count
        self._pending.clear()

    # ---------------------------------------------------------------------------- features
    def has_features(self, name: str) -> bool:
        root = self._file.get("features")
        group = root.get(_key(name)) if root is not None else None
        return group is not None and bool(group.attrs.get("complete", False))

    def put_features(self, name: str, features: Features) -> None:
        root = self._file["features"]
        if _key(name) in root:
            del root[_key(name)]
        group = root.create_group(_key(name))
        # what a reader gets back, kept for the readers of this process
        written = Features(features.keypoints_px.astype(np.float32),
                           features.scores.astype(np.float32),
                           features.descriptors.astype(np.float32),
                           tuple(int(v) for v in features.image_size))
        group.create_dataset("keypoints_px", data=written.keypoints_px)
        group.create_dataset("scores", data=written.scores)
        group.create_dataset("descriptors", data=written.descriptors)
        group.attrs["image_size"] = np.asarray(written.image_size, np.int64)
        group.attrs["complete"] = True
        self._put[name] = written
        self._written()

    def _features_group(self, name: str):
        if not self.has_features(name):
            raise CusfmError(f"{self.path}: no features for {name}; run the features stage")
        return self._file["features"][_key(name)]

    def features(self, name: str) -> Features:
        if self._read is not None and name in self._read:
            return self._read[name]
        group = self._features_group(name)
        features = Features(group["keypoints_px"][()], group["scores"][()],
                            group["descriptors"][()],
                            tuple(int(v) for v in group.attrs["image_size"]))
        if self._read is not None:
            self._read[name] = _frozen(features)
        return features

    def keypoints(self, name: str) -> np.ndarray:
        """(N, 2) keypoint pixels of an image, without its descriptors (98 % of its bytes:
        the export and the mapping stage read every image's keypoints only)."""
        if self._read is not None and name in self._read:
            return self._read[name].keypoints_px
        return self._features_group(name)["keypoints_px"][()]

    def feature_names(self) -> list[str]:
        return [_unkey(k) for k, g in self._file["features"].items()
                if g.attrs.get("complete", False)]

    # ----------------------------------------------------------------------------- matches
    def has_matches(self, image0: str, image1: str) -> bool:
        return (image0, image1) in self._pending or (image0, image1) in self._index

    def put_matches(self, image0: str, image1: str, matches: Matches) -> None:
        """Keeps the matches until the next flush, then writes them with the others (a pair
        put again replaces its matches)."""
        self._pending.pop((image0, image1), None)  # keeps the put order
        self._pending[(image0, image1)] = Matches(
            np.asarray(matches.indices, np.int64).reshape(-1, 2),
            np.asarray(matches.confidences, np.float32))
        self._written()

    def matches(self, image0: str, image1: str) -> Matches:
        """Matches of a pair; asking for (b, a) after storing (a, b) swaps the columns."""
        pair = (image0, image1)
        if pair in self._pending:
            return self._pending[pair]
        if pair in self._index:
            name, start, count = self._index[pair]
            if count < 0:  # format 1: a group per pair
                group = self._file["matches"][name]
                return Matches(group["indices"][()].astype(np.int64),
                               group["confidences"][()])
            if name not in self._blocks:
                # the block in the readers' dtypes once, read-only, and each pair a view of
                # it: a copy per pair was two numpy calls, each a wait for the GIL in the
                # matching stage's main thread (the thread that feeds the GPU) beside the
                # verification threads (street 300, H100: a fifth of that thread)
                block = self._file["match_blocks"][name]
                arrays = (block["indices"][()].astype(np.int64), block["confidences"][()])
                for array in arrays:
                    array.flags.writeable = False
                self._blocks[name] = arrays
            indices, confidences = self._blocks[name]
            return Matches(indices[start:start + count], confidences[start:start + count])
        if self.has_matches(image1, image0):
            swapped = self.matches(image1, image0)
            return Matches(swapped.indices[:, ::-1].copy(), swapped.confidences)
        raise CusfmError(f"{self.path}: no matches for {image0} - {image1}; run matching")

    def pairs(self) -> list[tuple[str, str]]:
        """Every pair with matches, stored ones first."""
        return list(self._index) + [p for p in self._pending if p not in self._index]

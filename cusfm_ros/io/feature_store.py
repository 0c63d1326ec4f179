"""Features per keyframe and matches per pair in one HDF5 file of the run directory.

Layout (h5py):
    /                      attrs: format, config (JSON of the extractor/matcher options)
    /features/<image>      keypoints_px (N, 2), scores (N,), descriptors (N, D);
                           attrs: image_size, complete
    /matches/<pair key>    indices (K, 2), confidences (K,); attrs: image0, image1, complete

Image names may contain "/" (camera sub-folders); they are escaped so every entry is one group.
An entry counts only once its ``complete`` flag is set (written last), so a run killed mid-write
is resumed by redoing just the incomplete entry. Writes reach the file at least every
``flush_interval_s`` (and when the store closes, which an exception or Ctrl-C also does): an
HDF5 flush per entry cost 2.5 ms, three times the write itself (2048 ALIKED features), so a
kill -9 now loses at most that interval's entries. Opening a store made with another
configuration raises, unless ``overwrite`` starts it afresh; a cache (``reset_on_mismatch``)
starts afresh by itself, and ``recover`` replaces a file HDF5 cannot open (a kill mid-write).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from cusfm_ros.core.features.types import Features, Matches
from cusfm_ros.errors import CusfmError, FormatError

FORMAT = "cusfm_features/1"


def _key(name: str) -> str:
    return name.replace("%", "%25").replace("/", "%2F")


def _unkey(key: str) -> str:
    return key.replace("%2F", "/").replace("%25", "%")


def pair_key(image0: str, image1: str) -> str:
    return f"{_key(image0)}|{_key(image1)}"


class FeatureStore:
    """``with FeatureStore(path, config) as store: store.put_features(name, f) ...``"""

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
            if attrs.get("format") != FORMAT:
                self._file.close()
                raise FormatError(self.path, None, "not a cusfm feature store",
                                  "rerun the stage that writes it with --overwrite")
            return self
        if "format" not in attrs:
            attrs["format"], attrs["config"] = FORMAT, self.config
        elif attrs.get("format") != FORMAT or attrs.get("config") != self.config:
            stored = attrs.get("config")
            self._file.close()
            if self.reset_on_mismatch:
                self.path.unlink()
                return self.__enter__()
            raise CusfmError(f"{self.path} holds data of another configuration ({stored});"
                             " rerun the stage that writes it (--overwrite)")
        self._file.require_group("features")
        self._file.require_group("matches")
        return self

    def __exit__(self, *exc_info) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def _written(self) -> None:
        """An entry is complete: flush it to the file once the interval has passed."""
        now = time.monotonic()
        if now - self._flushed_at >= self.flush_interval_s:
            self._file.flush()
            self._flushed_at = now

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
        group.create_dataset("keypoints_px", data=features.keypoints_px.astype(np.float32))
        group.create_dataset("scores", data=features.scores.astype(np.float32))
        group.create_dataset("descriptors", data=features.descriptors.astype(np.float32))
        group.attrs["image_size"] = np.asarray(features.image_size, np.int64)
        group.attrs["complete"] = True
        self._written()

    def features(self, name: str) -> Features:
        if not self.has_features(name):
            raise CusfmError(f"{self.path}: no features for {name}; run the features stage")
        group = self._file["features"][_key(name)]
        return Features(group["keypoints_px"][()], group["scores"][()],
                        group["descriptors"][()], tuple(int(v) for v in group.attrs["image_size"]))

    def feature_names(self) -> list[str]:
        return [_unkey(k) for k, g in self._file["features"].items()
                if g.attrs.get("complete", False)]

    # ----------------------------------------------------------------------------- matches
    def has_matches(self, image0: str, image1: str) -> bool:
        root = self._file.get("matches")
        group = root.get(pair_key(image0, image1)) if root is not None else None
        return group is not None and bool(group.attrs.get("complete", False))

    def put_matches(self, image0: str, image1: str, matches: Matches) -> None:
        root = self._file["matches"]
        key = pair_key(image0, image1)
        if key in root:
            del root[key]
        group = root.create_group(key)
        group.create_dataset("indices", data=matches.indices.astype(np.int64).reshape(-1, 2))
        group.create_dataset("confidences", data=matches.confidences.astype(np.float32))
        group.attrs["image0"], group.attrs["image1"] = image0, image1
        group.attrs["complete"] = True
        self._written()

    def matches(self, image0: str, image1: str) -> Matches:
        """Matches of a pair; asking for (b, a) after storing (a, b) swaps the columns."""
        if self.has_matches(image0, image1):
            group = self._file["matches"][pair_key(image0, image1)]
            return Matches(group["indices"][()], group["confidences"][()])
        if self.has_matches(image1, image0):
            swapped = self.matches(image1, image0)
            return Matches(swapped.indices[:, ::-1].copy(), swapped.confidences)
        raise CusfmError(f"{self.path}: no matches for {image0} - {image1}; run matching")

    def pairs(self) -> list[tuple[str, str]]:
        return [(g.attrs["image0"], g.attrs["image1"]) for g in self._file["matches"].values()
                if g.attrs.get("complete", False)]

"""Content digests of run-directory artifacts: what they cover, and the cache."""

import hashlib
import os

from cusfm_ros.io.digest import DigestCache, file_digest


def test_a_folder_digest_covers_names_and_contents_in_order_and_skips_hidden(tmp_path):
    root = tmp_path / "run" / "keyframes"
    files = {"left/1.png": b"a" * 5000, "left/2.png": b"b", "right/1.png": b"c" * 70000,
             "keyframes.json": b"{}"}
    for name, data in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(data)
    (root / ".tmp-partial.png").write_bytes(b"half")  # a temporary file: left out
    cache = DigestCache(tmp_path / "digests.json", tmp_path / "run")
    # by definition: sha256 over (relative path, NUL, file sha256, newline), folders walked
    # top-down in sorted order, each folder's files sorted
    expected = hashlib.sha256()
    for name in ("keyframes.json", "left/1.png", "left/2.png", "right/1.png"):
        expected.update(name.encode() + b"\0" + hashlib.sha256(files[name]).hexdigest().encode()
                        + b"\n")
    assert cache.digest(root) == expected.hexdigest()
    assert cache.digest(root / "left" / "2.png") == file_digest(root / "left" / "2.png")
    assert cache.digest(tmp_path / "absent") is None
    # the cache answers by size and mtime; a changed file is hashed again
    cache.save()
    again = DigestCache(tmp_path / "digests.json", tmp_path / "run")
    assert again.digest(root) == expected.hexdigest() and not again._dirty
    (root / "left" / "2.png").write_bytes(b"B")
    os.utime(root / "left" / "2.png", ns=(1, 1))
    assert again.digest(root) != expected.hexdigest() and again._dirty

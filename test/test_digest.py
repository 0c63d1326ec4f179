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


def test_a_large_file_is_the_digest_of_its_pieces_digests(tmp_path, monkeypatch):
    from cusfm_ros.io import digest

    monkeypatch.setattr(digest, "PIECE_BYTES", 1000)
    data = bytes(range(256)) * 10  # 2560 bytes: pieces of 1000, 1000 and 560
    (tmp_path / "big").write_bytes(data)
    (tmp_path / "small").write_bytes(data[:1000])
    expected = hashlib.sha256()
    for start in (0, 1000, 2000):
        expected.update(hashlib.sha256(data[start:start + 1000]).hexdigest().encode() + b"\n")
    assert file_digest(tmp_path / "big") == expected.hexdigest()
    assert file_digest(tmp_path / "small") == hashlib.sha256(data[:1000]).hexdigest()
    # a forked child hashes in pieces too (its parent's pool threads do not exist there)
    read, write = os.pipe()
    child = os.fork()
    if child == 0:
        os.write(write, file_digest(tmp_path / "big").encode())
        os._exit(0)
    os.waitpid(child, 0)
    assert os.read(read, 100).decode() == expected.hexdigest()

"""File digests (`steering_core.storage.digests`) and checkpoint fingerprints: full content hashes, paid once per file version (path, size, mtime, inode)."""

from __future__ import annotations

import os

import torch
from safetensors.torch import save_file

from steering_core.capture.run_identity import checkpoint_fingerprint
from steering_core.storage import digests
from steering_core.storage.fileio import sha256_file


def test_checkpoint_fingerprint_sees_a_change_anywhere(tmp_path):
    """A fine-tune that moves one weight far from any sampled block still changes the fingerprint."""
    path = tmp_path / "model.safetensors"
    weights = torch.zeros(3 << 20, dtype=torch.uint8)  # 3 MiB: more than a sampled fingerprint reads
    save_file({"w": weights}, path)
    before = checkpoint_fingerprint(path)
    assert before == checkpoint_fingerprint(path)
    # every offset of the data section, tried one at a time, must count
    for offset in (123_457, 1_500_001, (3 << 20) - 70_001):
        changed = weights.clone()
        changed[offset] = 1
        save_file({"w": changed}, path)
        assert checkpoint_fingerprint(path) != before, offset
        assert checkpoint_fingerprint(path) == sha256_file(path)


def test_digest_is_computed_once_per_file_version(tmp_path, monkeypatch):
    calls = []
    real = digests.sha256_file
    monkeypatch.setattr(digests, "sha256_file", lambda p: calls.append(p) or real(p))
    monkeypatch.setenv(digests.DIGEST_CACHE_ENV, str(tmp_path / "digests"))
    monkeypatch.setattr(digests, "STORED_DIGEST_MIN_SIZE", 0)
    path = tmp_path / "a.bin"
    path.write_bytes(b"x" * 100)
    first = digests.file_digest(path)
    assert digests.file_digest(path) == first and len(calls) == 1

    # a new process remembers it too (the digest is stored beside the key, not only in memory)
    digests._DIGESTS.clear()
    assert digests.file_digest(path) == first and len(calls) == 1

    # same size and mtime, other content, written to a new inode and renamed into place: recomputed
    stat = path.stat()
    other = tmp_path / "b.bin"
    other.write_bytes(b"y" * 100)
    os.utime(other, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    os.replace(other, path)
    assert digests.file_digest(path) == sha256_file(path) != first and len(calls) == 2

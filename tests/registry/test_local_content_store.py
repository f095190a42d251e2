"""The embedded content store: Kubo CIDs, verified fetches, tampered files refused."""

from __future__ import annotations

import pytest
from medc_registry import (
    ContentIntegrityError,
    ContentNotFoundError,
    ContentStoreError,
    LocalContentStore,
    compute_cid,
)


def test_add_fetch_pin_round_trip(tmp_path):
    store = LocalContentStore(tmp_path)
    data = b"\x00bundle" * 100_000
    for version in (0, 1):
        cid = store.add(data, version)
        assert cid == compute_cid(data, version)
        assert store.add(data, version) == cid  # idempotent
        assert store.has(cid)
        assert store.fetch(cid) == data
        store.pin(cid)
    # A second store over the same directory sees the content (state survives processes).
    assert LocalContentStore(tmp_path).fetch(compute_cid(data, 0)) == data


def test_tampered_file_on_disk_is_refused(tmp_path):
    store = LocalContentStore(tmp_path)
    cid = store.add(b"honest model weights")
    (tmp_path / "blobs" / cid).write_bytes(b"malicious model weights")
    with pytest.raises(ContentIntegrityError, match=cid):
        store.fetch(cid)


def test_missing_and_malformed_cids_give_clear_errors(tmp_path):
    store = LocalContentStore(tmp_path)
    absent = compute_cid(b"never added")
    with pytest.raises(ContentNotFoundError, match="not in the local content store"):
        store.fetch(absent)
    with pytest.raises(ContentNotFoundError):
        store.pin(absent)
    for bad in ["../etc/passwd", "Qm", ""]:
        with pytest.raises(ContentStoreError, match="invalid CID"):
            store.fetch(bad)

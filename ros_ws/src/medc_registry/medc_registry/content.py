"""Content stores for model files: an embedded local store and a Kubo RPC (``/api/v0``) client.

Both hand out the CID Kubo's ``ipfs add`` gives for the same bytes, and both verify every fetch
against the CID before returning it (:func:`medc_registry.cid.verify`, or block by block with
:func:`medc_registry.cid.assemble` for other DAG layouts): a store that returns tampered bytes
raises :class:`ContentIntegrityError` instead.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Protocol

import httpx

from .cid import Cid, CidError, ContentMismatchError, assemble, compute_cid, parse_cid, verify


class ContentStoreError(RuntimeError):
    """The content store could not add, find or return content."""


class ContentNotFoundError(ContentStoreError):
    """No content under that CID (or the node did not find it within the timeout)."""


class ContentIntegrityError(ContentStoreError):
    """Bytes returned for a CID do not hash to that CID."""


class ContentStore(Protocol):
    """What the registry needs from IPFS."""

    def add(self, data: bytes, cid_version: int = 0) -> str:
        """Store ``data``; return its CID (as ``ipfs add`` prints it)."""
        ...

    def fetch(self, cid: str) -> bytes:
        """Return the bytes of ``cid``, verified against the CID."""
        ...

    def pin(self, cid: str) -> None:
        """Keep ``cid`` from garbage collection."""
        ...

    def has(self, cid: str) -> bool:
        """Whether the store holds ``cid`` locally."""
        ...


def _checked(data: bytes, cid: str) -> bytes:
    try:
        return verify(data, cid)
    except ContentMismatchError as exc:
        raise ContentIntegrityError(str(exc)) from None


def _parsed(cid: str) -> str:
    try:
        parse_cid(cid)
    except CidError as exc:
        raise ContentStoreError(f"invalid CID: {exc}") from None
    return cid


class LocalContentStore:
    """Files under ``root/blobs/<cid>``; CIDs computed locally exactly as Kubo does.

    Pins are recorded under ``root/pins/`` (the local store never garbage-collects; the record is
    there so a later ``ipfs pin add`` can be replayed against a real node).
    """

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)
        (self.root / "blobs").mkdir(parents=True, exist_ok=True)
        (self.root / "pins").mkdir(parents=True, exist_ok=True)

    def __repr__(self) -> str:
        return f"LocalContentStore({str(self.root)!r})"

    def _path(self, cid: str) -> Path:
        return self.root / "blobs" / _parsed(cid)

    def add(self, data: bytes, cid_version: int = 0) -> str:
        """Store ``data`` and return its CID (written atomically; adding twice is a no-op)."""
        cid = compute_cid(bytes(data), cid_version)
        path = self._path(cid)
        if not path.exists():
            fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-")
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
            os.replace(tmp, path)
        return cid

    def fetch(self, cid: str) -> bytes:
        """Verified bytes of ``cid``; ContentNotFoundError / ContentIntegrityError otherwise."""
        path = self._path(cid)
        if not path.is_file():
            raise ContentNotFoundError(f"CID {cid} is not in the local content store {self.root}")
        return _checked(path.read_bytes(), cid)

    def pin(self, cid: str) -> None:
        """Record a pin for ``cid`` (which must be stored)."""
        if not self._path(cid).is_file():
            raise ContentNotFoundError(f"cannot pin {cid}: not in the local content store {self.root}")
        (self.root / "pins" / cid).touch()

    def has(self, cid: str) -> bool:
        """Whether ``cid`` is stored here."""
        return self._path(cid).is_file()


class KuboContentStore:
    """A Kubo-compatible RPC endpoint (``http://127.0.0.1:5001``): add, cat, pin.

    ``timeout`` bounds every request; it matters for ``cat`` of a CID no peer has, which an IPFS
    node otherwise waits on forever.
    """

    def __init__(self, api_url: str = "http://127.0.0.1:5001", timeout: float = 30.0) -> None:
        self.api_url = api_url.rstrip("/")
        self.timeout = timeout
        self._http = httpx.Client(base_url=self.api_url + "/api/v0", timeout=timeout)

    def __repr__(self) -> str:
        return f"KuboContentStore({self.api_url!r})"

    def close(self) -> None:
        """Close the HTTP connection pool."""
        self._http.close()

    def _post(self, path: str, **kwargs) -> httpx.Response:
        try:
            resp = self._http.post(path, **kwargs)
        except httpx.TimeoutException:
            raise ContentNotFoundError(
                f"IPFS node at {self.api_url} did not answer {path} within {self.timeout} s"
            ) from None
        except httpx.HTTPError as exc:
            raise ContentStoreError(f"IPFS node at {self.api_url} unreachable: {exc}") from None
        if resp.status_code != 200:
            raise ContentStoreError(f"IPFS {path} failed ({resp.status_code}): {resp.text.strip()[:300]}")
        return resp

    def version(self) -> str:
        """The node's version string."""
        return self._post("/version").json()["Version"]

    def add(self, data: bytes, cid_version: int = 0) -> str:
        """``ipfs add`` (pinned); checks the node's CID equals the locally computed one."""
        if cid_version not in (0, 1):
            raise ValueError(f"cid_version must be 0 or 1, got {cid_version!r}")
        params = {"cid-version": str(cid_version), "pin": "true", "quieter": "true"}
        if cid_version == 1:
            params["cid-base"] = "base32"
        resp = self._post("/add", params=params, files={"file": ("model.bin", bytes(data))})
        lines = [line for line in resp.text.splitlines() if line.strip()]
        cid = httpx.Response(200, content=lines[-1]).json()["Hash"]
        expected = compute_cid(bytes(data), cid_version)
        if cid != expected:
            raise ContentStoreError(
                f"IPFS node returned CID {cid} but the Kubo default layout gives {expected}; "
                "the node must use Kubo's defaults (262144-byte chunks, balanced DAG)"
            )
        return cid

    def fetch(self, cid: str) -> bytes:
        """The file's bytes, verified against the CID.

        Fast path: ``cat`` and recompute the CID with Kubo's default layout. Content added with
        another layout (chunker, raw-leaves setting) is then read block by block with
        ``block/get``, each block checked against the CID linking to it.
        """
        resp = self._post("/cat", params={"arg": _parsed(cid)})
        try:
            return verify(resp.content, cid)
        except ContentMismatchError:
            pass
        try:
            return assemble(cid, self._block)
        except ContentMismatchError as exc:
            raise ContentIntegrityError(str(exc)) from None
        except CidError as exc:
            raise ContentStoreError(f"cannot read {cid} as a file: {exc}") from None

    def _block(self, cid: Cid) -> bytes:
        return self._post("/block/get", params={"arg": cid.encode()}).content

    def pin(self, cid: str) -> None:
        """``ipfs pin add``."""
        self._post("/pin/add", params={"arg": _parsed(cid)})

    def has(self, cid: str) -> bool:
        """Whether the node holds the root block of ``cid`` locally (offline check)."""
        try:
            self._post("/block/stat", params={"arg": _parsed(cid), "offline": "true"})
        except ContentStoreError:
            return False
        return True

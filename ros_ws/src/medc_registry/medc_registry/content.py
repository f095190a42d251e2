"""Content stores for model files: an embedded local store and a Kubo RPC (``/api/v0``) client.

Both hand out the CID Kubo's ``ipfs add`` gives for the same bytes, and both verify every fetch
against the CID before returning it (:func:`medc_registry.cid.verify`, or block by block with
:func:`medc_registry.cid.assemble` for other DAG layouts): a store that returns tampered bytes
raises :class:`ContentIntegrityError` instead.

Fetches are bounded: at most ``max_size`` bytes (default :data:`MAX_CONTENT_BYTES`, the bundle
loader's ceiling), checked against what the node or the DAG declares before reading and enforced
while streaming; one total ``deadline`` per fetch (not per read, so a node that drips bytes fails
at the deadline); the CID is computed while the bytes stream in (into a temporary file, never
more than one chunk in memory besides the result); CID texts are length-capped before parsing.
"""

from __future__ import annotations

import http.client
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Protocol
from urllib.parse import urlencode, urlsplit

import httpx

from .cid import (
    MAX_BLOCK_BYTES,
    MAX_CONTENT_BYTES,
    Cid,
    CidBuilder,
    CidError,
    ContentMismatchError,
    ContentTooLargeError,
    assemble,
    check_built,
    compute_cid,
    parse_cid,
)

#: Total seconds one Kubo fetch may take (``cat``, and block by block reading if needed).
FETCH_DEADLINE = 300.0
#: Bytes of a fetch kept in memory before the temporary file spills to disk.
_SPOOL_BYTES = 8 << 20


class ContentStoreError(RuntimeError):
    """The content store could not add, find or return content."""


class ContentNotFoundError(ContentStoreError):
    """No content under that CID (or the node did not find it within the timeout)."""


class ContentIntegrityError(ContentStoreError):
    """Bytes returned for a CID do not hash to that CID."""


class ContentSizeError(ContentStoreError):
    """Content over the store's size limit (declared or received); refused."""


class ContentStore(Protocol):
    """What the registry needs from IPFS."""

    def add(self, data: bytes, cid_version: int = 0) -> str:
        """Store ``data``; return its CID (as ``ipfs add`` prints it)."""
        ...

    def fetch(self, cid: str) -> bytes:
        """Return the bytes of ``cid``, verified against the CID."""
        ...

    def fetch_to(self, cid: str, path: str | os.PathLike[str]) -> int:
        """Write the verified bytes of ``cid`` to ``path``; return their size."""
        ...

    def pin(self, cid: str) -> None:
        """Keep ``cid`` from garbage collection."""
        ...

    def has(self, cid: str) -> bool:
        """Whether the store holds ``cid`` locally."""
        ...


def _too_large(cid: str, size: int, limit: int, when: str) -> ContentSizeError:
    return ContentSizeError(f"content of {cid} is {size} bytes or more, over the {limit} byte limit; {when}")


def _verified_copy(src: IO[bytes], cid: str, out: IO[bytes], max_size: int) -> None:
    """Copy ``src`` to ``out`` in chunks while computing its CID; raise unless it is ``cid``."""
    builder = CidBuilder(parse_cid(cid).version)
    while chunk := src.read(1 << 20):
        if builder.size + len(chunk) > max_size:
            raise _too_large(cid, builder.size + len(chunk), max_size, "refused while reading")
        builder.update(chunk)
        out.write(chunk)
    try:
        check_built(builder, cid)
    except ContentMismatchError as exc:
        raise ContentIntegrityError(str(exc)) from None


def _deliver(spool: IO[bytes], path: str | os.PathLike[str] | None) -> bytes | int:
    """A verified spool's bytes, or (with ``path``) its size after moving it to ``path`` atomically."""
    spool.seek(0)
    if path is None:
        return spool.read()
    target = Path(path)
    fd, tmp = tempfile.mkstemp(dir=target.parent or ".", prefix=".medc-fetch-")
    with os.fdopen(fd, "wb") as fh:
        shutil.copyfileobj(spool, fh, 1 << 20)
        size = fh.tell()
    os.replace(tmp, target)
    return size


def _parsed(cid: str) -> str:
    try:
        parse_cid(cid)
    except CidError as exc:
        raise ContentStoreError(f"invalid CID: {exc}") from None
    return cid


def _spool() -> IO[bytes]:
    return tempfile.SpooledTemporaryFile(max_size=_SPOOL_BYTES, prefix="medc-fetch-")


class LocalContentStore:
    """Files under ``root/blobs/<cid>``; CIDs computed locally exactly as Kubo does.

    Pins are recorded under ``root/pins/`` (the local store never garbage-collects; the record is
    there so a later ``ipfs pin add`` can be replayed against a real node).
    """

    def __init__(self, root: str | os.PathLike[str], max_size: int = MAX_CONTENT_BYTES) -> None:
        self.root = Path(root)
        self.max_size = max_size
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
        """Verified bytes of ``cid``; ContentNotFoundError / ContentIntegrityError / ContentSizeError."""
        return self._fetch(cid, None)  # type: ignore[return-value]

    def fetch_to(self, cid: str, path: str | os.PathLike[str]) -> int:
        """Write the verified bytes of ``cid`` to ``path`` (atomically); returns their size."""
        return self._fetch(cid, path)  # type: ignore[return-value]

    def _fetch(self, cid: str, path: str | os.PathLike[str] | None) -> bytes | int:
        src = self._path(cid)
        if not src.is_file():
            raise ContentNotFoundError(f"CID {cid} is not in the local content store {self.root}")
        size = src.stat().st_size
        if size > self.max_size:
            raise _too_large(cid, size, self.max_size, "refused before reading")
        with open(src, "rb") as fh, _spool() as spool:
            _verified_copy(fh, cid, spool, self.max_size)
            return _deliver(spool, path)

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

    ``timeout`` bounds every request and every read; it matters for ``cat`` of a CID no peer has,
    which an IPFS node otherwise waits on forever. A fetch also has one total ``deadline`` and
    reads at most ``max_size`` bytes.
    """

    def __init__(
        self,
        api_url: str = "http://127.0.0.1:5001",
        timeout: float = 30.0,
        deadline: float = FETCH_DEADLINE,
        max_size: int = MAX_CONTENT_BYTES,
    ) -> None:
        self.api_url = api_url.rstrip("/")
        self.timeout = timeout
        self.deadline = deadline
        self.max_size = max_size
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

        Fast path: stream ``cat`` while computing the CID with Kubo's default layout. Content
        added with another layout (chunker, raw-leaves setting) is then read block by block with
        ``block/get``, each block checked against the CID linking to it. Both together get one
        deadline and the size limit.
        """
        return self._fetch(cid, None)  # type: ignore[return-value]

    def fetch_to(self, cid: str, path: str | os.PathLike[str]) -> int:
        """Write the verified bytes of ``cid`` to ``path`` (atomically); returns their size."""
        return self._fetch(cid, path)  # type: ignore[return-value]

    def _fetch(self, cid: str, path: str | os.PathLike[str] | None) -> bytes | int:
        until = time.monotonic() + self.deadline
        with _spool() as spool:
            builder = CidBuilder(parse_cid(_parsed(cid)).version)
            for chunk in self._stream("/cat", {"arg": cid}, self.max_size, until, cid):
                builder.update(chunk)
                spool.write(chunk)
            try:
                check_built(builder, cid)
                return _deliver(spool, path)
            except ContentMismatchError:
                pass
            spool.seek(0)
            spool.truncate()
            try:
                assemble(cid, lambda c: self._block(c, until, cid), max_size=self.max_size, write=spool.write)
            except ContentMismatchError as exc:
                raise ContentIntegrityError(str(exc)) from None
            except ContentTooLargeError as exc:
                raise ContentSizeError(str(exc)) from None
            except CidError as exc:
                raise ContentStoreError(f"cannot read {cid} as a file: {exc}") from None
            return _deliver(spool, path)

    def _block(self, cid: Cid, until: float, root: str) -> bytes:
        return b"".join(self._stream("/block/get", {"arg": cid.encode()}, MAX_BLOCK_BYTES, until, root))

    def _stream(
        self, path: str, params: dict[str, str], limit: int, until: float, cid: str
    ) -> Iterator[bytes]:
        """POST ``/api/v0{path}`` and yield the body, at most ``limit`` bytes, before ``until``.

        Each socket operation waits at most ``timeout`` and never past ``until``, and the
        deadline is checked after every read, so neither a silent nor a dripping node holds a
        fetch past its deadline.
        """
        url = urlsplit(self.api_url)
        received = 0

        def left() -> float:
            remaining = until - time.monotonic()
            if remaining <= 0:
                raise ContentNotFoundError(
                    f"IPFS node at {self.api_url} did not deliver {cid} within the {self.deadline:g} s "
                    f"fetch deadline ({received} bytes received)"
                )
            return min(self.timeout, remaining)

        conn = http.client.HTTPConnection(url.hostname or "127.0.0.1", url.port or 80, timeout=left())
        try:
            conn.request("POST", f"{url.path.rstrip('/')}/api/v0{path}?{urlencode(params)}")
            sock = conn.sock  # getresponse() drops conn.sock for a body that ends at close
            resp = conn.getresponse()
            if resp.status != 200:
                text = resp.read(300).decode("utf-8", "replace").strip()
                if "not found" in text.lower():
                    raise ContentNotFoundError(f"IPFS {path} {cid}: {text}")
                raise ContentStoreError(f"IPFS {path} failed ({resp.status}): {text}")
            for header in ("X-Content-Length", "Content-Length"):
                declared = resp.getheader(header)
                if declared and declared.isdigit() and int(declared) > limit:
                    raise _too_large(
                        cid, int(declared), limit, "refused before reading (declared by the node)"
                    )
            while True:
                wait = left()
                if sock is not None:
                    sock.settimeout(wait)
                chunk = resp.read1(1 << 16)
                if not chunk:
                    left()  # a body that ended at the deadline is still late
                    return
                received += len(chunk)
                if received > limit:
                    raise _too_large(cid, received, limit, "refused while streaming")
                yield chunk
        except TimeoutError:
            left()
            raise ContentNotFoundError(
                f"IPFS node at {self.api_url} did not answer {path} for {cid} within {self.timeout:g} s"
            ) from None
        except (OSError, http.client.HTTPException) as exc:
            raise ContentStoreError(f"IPFS node at {self.api_url} unreachable: {exc}") from None
        finally:
            conn.close()

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

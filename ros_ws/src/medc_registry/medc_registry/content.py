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

import contextlib
import http.client
import os
import shutil
import stat
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Protocol
from urllib.parse import urlencode, urlsplit

from medc_training.outfiles import check_output_folder
from medc_training.untrusted import UntrustedJSONError, parse_json, printable

from . import bounded_http
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
#: Largest answer read from a Kubo node other than content (``add``, ``version``, pins, errors).
MAX_ANSWER_BYTES = 1 << 20
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

    def fetch_to(self, cid: str, path: str | os.PathLike[str], overwrite: bool = True) -> int:
        """Write the verified bytes of ``cid`` to ``path``; return their size. ``overwrite``: replace
        a file already at ``path`` (else refuse it, before fetching and again when writing)."""
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


def _deliver(spool: IO[bytes], path: str | os.PathLike[str] | None,
             overwrite: bool = True) -> bytes | int:
    """A verified spool's bytes, or (with ``path``) its size after moving it to ``path`` atomically:
    a fresh temporary file beside it (``O_EXCL``), renamed over it (a link at ``path`` is replaced,
    never written through), or with ``overwrite`` False linked to it, which fails if anything,
    a link included, is there by then."""
    spool.seek(0)
    if path is None:
        return spool.read()
    target = _check_target(path, overwrite)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=".medc-fetch-")
    try:
        with os.fdopen(fd, "wb") as fh:
            shutil.copyfileobj(spool, fh, 1 << 20)
            size = fh.tell()
            fh.flush()
            os.fsync(fh.fileno())
        if overwrite:
            os.replace(tmp, target)
        else:
            try:
                os.link(tmp, target, follow_symlinks=False)
            except FileExistsError:
                raise ContentStoreError(_exists(target)) from None
            os.unlink(tmp)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)  # never leave the verified bytes behind in a temporary file
        raise
    return size


def _check_target(path: str | os.PathLike[str], overwrite: bool = True) -> Path:
    """``path`` as a file to write, refused (before anything is fetched) when it is a folder, its
    folder does not exist or cannot be written, something other than a file or link is there (a
    device such as ``/dev/full``), or (unless ``overwrite``) anything, a link included, is there."""
    target = Path(path)
    if target.is_dir():
        raise ContentStoreError(f"{target} is a folder: give the file to write, e.g. {target / 'model.bin'}")
    parent = target.parent
    if not parent.is_dir():
        raise ContentStoreError(f"cannot write {target}: the folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ContentStoreError(f"cannot write {target}: the folder {parent} is not writable")
    if not overwrite and (target.exists() or target.is_symlink()):
        raise ContentStoreError(_exists(target))
    with contextlib.suppress(FileNotFoundError):
        mode = target.lstat().st_mode
        if not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):
            raise ContentStoreError(f"{target} is not a regular file (a device, FIFO or socket): give "
                                    "a file to write")
    return target


def _exists(target: Path) -> str:
    return f"{target} exists: not overwritten (pass overwrite=True, or --overwrite to medc-registry fetch)"


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
        try:  # a file, a device or a name too long there: ContentStoreError, one line
            check_output_folder(self.root)
            (self.root / "blobs").mkdir(parents=True, exist_ok=True)
            (self.root / "pins").mkdir(parents=True, exist_ok=True)
        except ValueError as exc:
            raise ContentStoreError(f"content store: {exc}") from None
        except OSError as exc:
            raise ContentStoreError(f"content store {self.root}: {exc.strerror}") from None

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

    def fetch_to(self, cid: str, path: str | os.PathLike[str], overwrite: bool = True) -> int:
        """Write the verified bytes of ``cid`` to ``path`` (atomically; a file there is refused
        unless ``overwrite``); returns their size."""
        _check_target(path, overwrite)
        return self._fetch(cid, path, overwrite)  # type: ignore[return-value]

    def _fetch(self, cid: str, path: str | os.PathLike[str] | None, overwrite: bool = True) -> bytes | int:
        src = self._path(cid)
        if not src.is_file():
            raise ContentNotFoundError(f"CID {cid} is not in the local content store {self.root}")
        size = src.stat().st_size
        if size > self.max_size:
            raise _too_large(cid, size, self.max_size, "refused before reading")
        with open(src, "rb") as fh, _spool() as spool:
            _verified_copy(fh, cid, spool, self.max_size)
            return _deliver(spool, path, overwrite)

    def pin(self, cid: str) -> None:
        """Record a pin for ``cid`` (which must be stored)."""
        if not self._path(cid).is_file():
            raise ContentNotFoundError(f"cannot pin {cid}: not in the local content store {self.root}")
        (self.root / "pins" / cid).touch()

    def has(self, cid: str) -> bool:
        """Whether ``cid`` is stored here."""
        return self._path(cid).is_file()


def _transport_error(api_url: str, exc: BaseException) -> ContentStoreError:
    """The typed error of an HTTP exchange with an IPFS node that failed: a status, header, chunk
    or trailer line http.client refuses (over-long, malformed) is a malformed answer; a refused or
    broken connection, an unreachable node."""
    if isinstance(exc, http.client.HTTPException) and not isinstance(
            exc, ConnectionError | http.client.IncompleteRead):
        why = f"{type(exc).__name__}: {printable(str(exc), 200)}"
        return ContentStoreError(f"IPFS node at {api_url} answered with a malformed HTTP response ({why})")
    return ContentStoreError(f"IPFS node at {api_url} unreachable: {printable(str(exc), 200)}")


class KuboContentStore:
    """A Kubo-compatible RPC endpoint (``http://127.0.0.1:5001``): add, cat, pin.

    Every request has one total deadline, status line and headers included (a node that drips
    header bytes is cut off like one that drips the body; :mod:`medc_registry.bounded_http`):
    ``deadline`` for a fetch (``cat``, and block by block reading if needed), for ``add`` and for
    ``pin``, ``timeout`` for the small queries; ``timeout`` also bounds every single read, which
    matters for ``cat`` of a CID no peer has. A fetch reads at most ``max_size`` bytes, and every
    other answer at most :data:`MAX_ANSWER_BYTES`.
    """

    def __init__(
        self,
        api_url: str = "http://127.0.0.1:5001",
        timeout: float = 30.0,
        deadline: float = FETCH_DEADLINE,
        max_size: int = MAX_CONTENT_BYTES,
    ) -> None:
        if not api_url.startswith(("http://", "https://")):
            raise ValueError(f"IPFS API URL must start with http:// or https://, got {api_url!r}")
        self.api_url = api_url.rstrip("/")
        self.timeout = timeout
        self.deadline = deadline
        self.max_size = max_size

    def __repr__(self) -> str:
        return f"KuboContentStore({self.api_url!r})"

    def close(self) -> None:
        """Nothing to close: every request has its own connection (kept for callers)."""

    def _target(self, path: str, params: dict[str, str]) -> str:
        base = urlsplit(self.api_url).path.rstrip("/")
        return f"{base}/api/v0{path}" + (f"?{urlencode(params)}" if params else "")

    def _post(
        self,
        path: str,
        params: dict[str, str] | None = None,
        body: bytes = b"",
        content_type: str | None = None,
        total: float | None = None,
    ) -> bytes:
        """The body of one RPC answer (at most :data:`MAX_ANSWER_BYTES`, all of it within
        ``total`` seconds, default ``timeout``); ContentStoreError (ContentNotFoundError when the
        node did not answer in time) otherwise."""
        total = self.timeout if total is None else total
        headers = {"Content-Type": content_type} if content_type else {}
        try:
            status, answer = bounded_http.post(
                self.api_url, self._target(path, params or {}), body, headers,
                until=time.monotonic() + total, timeout=self.timeout, max_body=MAX_ANSWER_BYTES,
                what=f"IPFS {path}",
            )
        except (TimeoutError, bounded_http.DeadlineExceeded):
            raise ContentNotFoundError(
                f"IPFS node at {self.api_url} did not answer {path} in full within {total:g} s"
            ) from None
        except bounded_http.BodyTooLarge as exc:
            raise ContentStoreError(f"IPFS node at {self.api_url}: {exc}") from None
        except (OSError, http.client.HTTPException) as exc:
            raise _transport_error(self.api_url, exc) from None
        if status != 200:
            text = printable(answer[:300].decode("utf-8", "replace").strip(), 300)
            raise ContentStoreError(f"IPFS {path} failed ({status}): {text}")
        return answer

    def _json(self, path: str, answer: bytes) -> dict:
        """The last JSON object line of an RPC answer (``add`` streams one line per entry)."""
        lines = [line for line in answer.splitlines() if line.strip()]
        if not lines:
            raise ContentStoreError(f"IPFS {path} at {self.api_url} answered nothing; expected JSON")
        try:
            value = parse_json(lines[-1].decode("utf-8"), f"the IPFS {path} answer", MAX_ANSWER_BYTES)
        except (UnicodeDecodeError, UntrustedJSONError) as exc:
            raise ContentStoreError(f"IPFS {path} at {self.api_url}: malformed answer ({exc})") from None
        if not isinstance(value, dict):
            raise ContentStoreError(f"IPFS {path} at {self.api_url}: the answer is not a JSON object")
        return value

    def version(self) -> str:
        """The node's version string."""
        version = self._json("/version", self._post("/version")).get("Version")
        if not isinstance(version, str):
            raise ContentStoreError(f"IPFS /version at {self.api_url}: the answer names no version")
        return printable(version, 100)

    def add(self, data: bytes, cid_version: int = 0) -> str:
        """``ipfs add`` (pinned); checks the node's CID equals the locally computed one."""
        if cid_version not in (0, 1):
            raise ValueError(f"cid_version must be 0 or 1, got {cid_version!r}")
        params = {"cid-version": str(cid_version), "pin": "true", "quieter": "true"}
        if cid_version == 1:
            params["cid-base"] = "base32"
        boundary = "medc-" + os.urandom(12).hex()
        body = b"".join((
            f"--{boundary}\r\n".encode(),
            b'Content-Disposition: form-data; name="file"; filename="model.bin"\r\n',
            b"Content-Type: application/octet-stream\r\n\r\n",
            bytes(data),
            f"\r\n--{boundary}--\r\n".encode(),
        ))
        answer = self._post("/add", params, body, f"multipart/form-data; boundary={boundary}", self.deadline)
        cid = self._json("/add", answer).get("Hash")
        if not isinstance(cid, str):
            raise ContentStoreError(f"IPFS /add at {self.api_url}: the answer names no CID (no \"Hash\")")
        expected = compute_cid(bytes(data), cid_version)
        if cid != expected:
            raise ContentStoreError(
                f"IPFS node returned CID {printable(cid, 130)} but the Kubo default layout gives "
                f"{expected}; the node must use Kubo's defaults (262144-byte chunks, balanced DAG)"
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

    def fetch_to(self, cid: str, path: str | os.PathLike[str], overwrite: bool = True) -> int:
        """Write the verified bytes of ``cid`` to ``path`` (atomically; a file there is refused
        unless ``overwrite``); returns their size."""
        _check_target(path, overwrite)
        return self._fetch(cid, path, overwrite)  # type: ignore[return-value]

    def _fetch(self, cid: str, path: str | os.PathLike[str] | None, overwrite: bool = True) -> bytes | int:
        until = time.monotonic() + self.deadline
        with _spool() as spool:
            builder = CidBuilder(parse_cid(_parsed(cid)).version)
            for chunk in self._stream("/cat", {"arg": cid}, self.max_size, until, cid):
                builder.update(chunk)
                spool.write(chunk)
            try:
                check_built(builder, cid)
                return _deliver(spool, path, overwrite)
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
            return _deliver(spool, path, overwrite)

    def _block(self, cid: Cid, until: float, root: str) -> bytes:
        return b"".join(self._stream("/block/get", {"arg": cid.encode()}, MAX_BLOCK_BYTES, until, root))

    def _stream(
        self, path: str, params: dict[str, str], limit: int, until: float, cid: str
    ) -> Iterator[bytes]:
        """POST ``/api/v0{path}`` and yield the body, at most ``limit`` bytes, before ``until``.

        Every receive, from the status line on, waits at most ``timeout`` and never past
        ``until`` (:mod:`medc_registry.bounded_http`), so neither a silent node nor one that
        drips header or body bytes holds a fetch past its deadline.
        """
        received = 0

        def late() -> ContentNotFoundError:
            return ContentNotFoundError(
                f"IPFS node at {self.api_url} did not deliver {cid} within the {self.deadline:g} s "
                f"fetch deadline ({received} bytes received)"
            )

        left = bounded_http.deadline_clock(until, self.timeout, late)
        try:
            with bounded_http.open_post(self.api_url, self._target(path, params), b"", {}, left) as resp:
                if resp.status != 200:
                    text = printable(resp.read(300).decode("utf-8", "replace").strip(), 300)
                    if "not found" in text.lower():
                        raise ContentNotFoundError(f"IPFS {path} {cid}: {text}")
                    raise ContentStoreError(f"IPFS {path} failed ({resp.status}): {text}")
                declared = bounded_http.declared_length(resp)
                if declared is not None and declared > limit:
                    raise _too_large(cid, declared, limit, "refused before reading (declared by the node)")
                while True:
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
            raise _transport_error(self.api_url, exc) from None

    def pin(self, cid: str) -> None:
        """``ipfs pin add``."""
        self._post("/pin/add", {"arg": _parsed(cid)}, total=self.deadline)

    def has(self, cid: str) -> bool:
        """Whether the node holds the root block of ``cid`` locally (offline check)."""
        try:
            self._post("/block/stat", {"arg": _parsed(cid), "offline": "true"})
        except ContentStoreError:
            return False
        return True

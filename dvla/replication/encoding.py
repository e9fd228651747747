"""Versioned weight encodings with error feedback, chunking and verified decoding.

This module owns the replication wire format of policy weights (see docs/replication.md). A
weight version is one :class:`WeightVersion` (the wire's :class:`WeightManifest` plus its
payload) from the encoder to the weights a node holds:

* :class:`WeightEncoder` (actor side) turns successive flat parameter vectors into versions
  encoded as ``full``, ``delta-bf16`` or ``delta-topk`` (a full version of a bfloat16 model
  goes as ``full-bf16``: its values are exact in two bytes). Each delta is measured against
  ``published``, what every replica holds after the versions so far (error feedback), so
  quantisation and sparsification errors never accumulate.
* :class:`ChunkAssembler` reassembles a payload from its chunks, arriving in any order.
* :class:`HeldWeights` is the newest verified version a node holds (the encoder's ``published``
  too): :meth:`HeldWeights.apply` decodes a version into its staging buffer, verifies it bit for
  bit against the manifest's checksum and only then swaps it in. Every reader (a rollout's
  policy, an evaluator, a snapshot server) reads ``active`` under its ``lock``.

Everything here is pure computation on numpy buffers: no I/O, no threads of its own. Payload
bytes are little-endian, as are the hosts the framework runs on.
"""

from __future__ import annotations

import hashlib
import math
import threading
from dataclasses import dataclass
from typing import Any, Callable, Union

import numpy as np
import xxhash
import zstandard

from dvla.config import COMPRESSIONS, ENCODINGS, ReplicationConfig
from dvla.fabric.messages import WeightManifest
from dvla.replication.layout import LayoutMismatch, ParamLayout, ReplicationError

BytesLike = Union[bytes, bytearray, memoryview]

_U16 = np.dtype("<u2")
_U32 = np.dtype("<u4")
_F32 = np.dtype("<f4")


class CorruptPayload(ReplicationError):
    """A payload or manifest is malformed (wrong sizes, out-of-range indices, bad fields)."""


class ChecksumMismatch(CorruptPayload):
    """The decoded parameters do not hash to the manifest checksum; nothing was applied."""


class NeedSnapshot(ReplicationError):
    """A delta cannot be applied because this replica does not hold its base version.

    The holder should fetch a snapshot (a full version) from its parent and resume from it.
    """

    def __init__(self, have: int, base: int, version: int) -> None:
        self.have = have
        self.base = base
        self.version = version
        super().__init__(f"delta to version {version} needs base {base}, replica holds {have}")


class StaleVersion(ReplicationError):
    """A version not newer than the one already held arrived (duplicate or late delivery)."""


def checksum(flat: np.ndarray) -> str:
    """Hex digest (XXH3-128) of the exact bytes of a C-contiguous array, without copying.

    Non-cryptographic on purpose: it catches a replica that differs from what the actor
    published; forgery is stopped earlier by the signed envelope of every manifest and chunk.
    """
    if not flat.flags.c_contiguous:
        raise ValueError("checksum needs a C-contiguous array")
    return xxhash.xxh3_128_hexdigest(memoryview(flat).cast("B"))


def _all_finite(x: np.ndarray) -> bool:
    # Two allocation-free reductions: max propagates NaN and exposes +inf, min exposes -inf.
    return bool(np.isfinite(x.max()) and np.isfinite(x.min()))


def bf16_round_bits(x: np.ndarray, out: np.ndarray | None = None, scratch: np.ndarray | None = None) -> np.ndarray:
    """Round float32 ``x`` to bfloat16 (nearest, ties to even) and return the uint16 bits.

    Adding ``0x7FFF`` plus the lowest kept bit before truncating is exact round-to-nearest-even
    (overflow rounds to infinity); NaNs are fixed to the quiet bfloat16 NaN with their sign (the
    bit trick alone could turn one into an infinity). ``out`` and ``scratch`` avoid allocation.
    """
    bits = x.view(np.uint32)
    s = np.empty(x.shape, dtype=np.uint32) if scratch is None else scratch
    out = np.empty(x.shape, dtype=np.uint16) if out is None else out
    np.right_shift(bits, 16, out=s)
    np.bitwise_and(s, 1, out=s)
    np.add(s, 0x7FFF, out=s)
    np.add(s, bits, out=s)  # wraps only for NaN patterns, which are fixed below
    np.right_shift(s, 16, out=s)
    np.copyto(out, s, casting="unsafe")  # every value is < 2**16 after the shift
    if not _all_finite(x):
        nan = np.isnan(x)
        out[nan] = ((bits[nan] >> 16) & 0x8000) | 0x7FC0
    return out


def bf16_to_float32(q: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Exact float32 values of bfloat16 bits ``q`` (the bits become the upper half)."""
    out = np.empty(q.shape, dtype=np.float32) if out is None else out
    wide = out.view(np.uint32)
    np.copyto(wide, q, casting="safe")
    np.left_shift(wide, 16, out=wide)
    return out


def chunk_count(total_bytes: int, chunk_bytes: int) -> int:
    """Number of chunks a payload of ``total_bytes`` is split into at ``chunk_bytes`` per chunk."""
    return max(1, -(-total_bytes // chunk_bytes))


def chunk_span(index: int, n_chunks: int, total_bytes: int) -> tuple[int, int]:
    """(start, stop) byte range of chunk ``index``: even chunks of ``ceil(total_bytes / n_chunks)``
    bytes but a shorter last one, so offsets follow from the manifest alone."""
    size = -(-total_bytes // n_chunks)
    start = index * size
    return start, min(total_bytes, start + size)


def _spans_valid(n_chunks: int, total_bytes: int) -> bool:
    # With even chunks, the last chunk must still hold at least one byte.
    return 1 <= n_chunks <= total_bytes and (n_chunks - 1) * -(-total_bytes // n_chunks) < total_bytes


def split_chunks(payload: BytesLike, chunk_bytes: int) -> list[memoryview]:
    """Zero-copy split of ``payload`` into even chunks of at most ``chunk_bytes`` bytes."""
    if chunk_bytes < 1:
        raise ValueError(f"chunk_bytes must be >= 1, got {chunk_bytes}")
    view = memoryview(payload).cast("B")
    n = chunk_count(view.nbytes, chunk_bytes)
    return [view[slice(*chunk_span(i, n, view.nbytes))] for i in range(n)]


#: wire encodings of a full version: float32 values, or their upper halves when every value is
#: exactly a bfloat16 (what a bf16 model's weights are); chosen by the encoder, not configured
FULL_ENCODINGS = ("full", "full-bf16")


def _is_full(encoding: str) -> bool:
    return encoding in FULL_ENCODINGS


#: suffix of a manifest's encoding whose payload is zstd-compressed ("delta-bf16+zstd")
ZSTD = "zstd"


def split_encoding(encoding: str) -> tuple[str, str]:
    """("delta-bf16", "zstd") for "delta-bf16+zstd"; ("full", "") for "full"."""
    base, _, comp = encoding.partition("+")
    return base, comp


def _planes(raw: np.ndarray, width: int) -> np.ndarray:
    """Byte planes of an array of `width`-byte words: all first bytes, then all second bytes, ..."""
    return np.ascontiguousarray(raw.view(np.uint8).reshape(-1, width).T)


def _unplanes(planes: np.ndarray, width: int) -> np.ndarray:
    return np.ascontiguousarray(planes.reshape(width, -1).T).reshape(-1)


def deflate_delta(encoding: str, payload: memoryview, level: int = 1) -> bytes:
    """Compress a delta payload losslessly. The words are split into byte planes first (the sign
    and exponent bytes of small deltas are nearly constant), and top-k indices become gaps
    (sorted indices differ by little)."""
    if encoding == "delta-bf16":
        words = np.frombuffer(payload, dtype=_U16)
        planes = _planes(words, 2)
    elif encoding == "delta-topk":
        pay = np.frombuffer(payload, dtype=_U32)
        k = pay.size // 2
        tmp = pay.copy()
        tmp[1:k] = pay[1:k] - pay[: k - 1]  # ascending: gaps never underflow
        planes = _planes(tmp, 4)
    else:
        raise ValueError(f"no compression for encoding {encoding!r}")
    return zstandard.ZstdCompressor(level=level).compress(planes.tobytes())


def inflate_delta(encoding: str, data: memoryview, numel: int) -> memoryview:
    """Inverse of :func:`deflate_delta`; never produces more than a raw payload of `numel` can be.

    Every failure (data that does not decompress, or to a wrong size) is a :class:`CorruptPayload`.
    The frame header's declared size is checked before anything is allocated: ``zstandard``
    sizes its output from it and then ignores ``max_output_size``.
    """
    limit = 2 * numel if encoding == "delta-bf16" else 4 * numel
    try:
        declared = zstandard.frame_content_size(data)
        if declared > limit:  # -1: not declared
            raise CorruptPayload(f"{encoding}+zstd frame header says it inflates to {declared} bytes, over {limit}")
        window = min(1 << 27, 1 << max(10, (limit - 1).bit_length()))  # 128 MiB: zstd's default cap
        dctx = zstandard.ZstdDecompressor(max_window_size=window)
        raw = dctx.decompress(data, max_output_size=limit, allow_extra_data=False)
    except (zstandard.ZstdError, MemoryError, ValueError, TypeError) as err:
        raise CorruptPayload(f"{encoding}+zstd payload does not decompress: {type(err).__name__}: {err}") from None
    if len(raw) > limit:
        raise CorruptPayload(f"{encoding}+zstd payload inflates beyond {limit} bytes")
    planes = np.frombuffer(raw, dtype=np.uint8)
    if encoding == "delta-bf16":
        if planes.size != 2 * numel:
            raise CorruptPayload(f"delta-bf16+zstd payload inflates to {planes.size} bytes, expected {2 * numel}")
        return memoryview(_unplanes(planes, 2)).cast("B")
    if planes.size % 8 or planes.size == 0:
        raise CorruptPayload(f"delta-topk+zstd payload inflates to {planes.size} bytes (not 8*k)")
    pay = _unplanes(planes, 4).view(_U32)
    k = pay.size // 2
    idx = np.cumsum(pay[:k], dtype=np.uint64)
    if idx[-1] >= numel:
        raise CorruptPayload("delta-topk+zstd indices out of range")
    pay[:k] = idx
    return memoryview(pay).cast("B")


@dataclass(frozen=True)
class WeightVersion:
    """One encoded weight version: its manifest and its payload.

    ``payload`` views the encoder's buffers: it stays valid until the next ``encode()`` call
    (copy it with ``bytes()`` to keep it longer).
    """

    manifest: WeightManifest
    #: the whole payload (``manifest.total_bytes`` bytes)
    payload: memoryview
    #: the signed envelope of ``manifest`` (empty when the encoder has no signer)
    proof: bytes = b""

    @property
    def chunks(self) -> list[memoryview]:
        """``payload`` split into the manifest's ``n_chunks`` even chunks (zero-copy)."""
        m = self.manifest
        return [self.payload[slice(*chunk_span(i, m.n_chunks, m.total_bytes))] for i in range(m.n_chunks)]


def _byte_view(data: BytesLike) -> memoryview:
    try:
        return memoryview(data).cast("B")
    except TypeError as exc:  # not a buffer, or not contiguous
        raise CorruptPayload(f"payload must be contiguous bytes: {exc}") from exc


def _decode_into(encoding: str, view: memoryview, base: np.ndarray, out: np.ndarray) -> None:
    """The parameters after a version of `encoding` whose payload is `view`, applied to `base`,
    into `out` (which must not alias `base`). The encoder and every replica run exactly this:
    that is why replicas match the encoder bit for bit."""
    n = base.size
    if encoding == "full":
        np.copyto(out, np.frombuffer(view, dtype=_F32, count=n))
    elif encoding == "full-bf16":
        bf16_to_float32(np.frombuffer(view, dtype=_U16, count=n), out=out)
    elif encoding == "delta-bf16":
        bf16_to_float32(np.frombuffer(view, dtype=_U16, count=n), out=out)
        np.add(base, out, out=out)
    else:
        k = view.nbytes // 8
        idx = np.frombuffer(view, dtype=_U32, count=k)
        vals = np.frombuffer(view, dtype=_F32, count=k, offset=4 * k)
        # Strictly increasing indices are what encoders send; this also rules out
        # duplicates, whose scatter order would otherwise be ambiguous.
        if idx[-1] >= n or (k > 1 and not bool(np.all(idx[1:] > idx[:-1]))):
            raise CorruptPayload("delta-topk indices out of range or not strictly increasing")
        np.copyto(out, base)
        out[idx] = np.add(base[idx], vals)


def topk_count(numel: int, fraction: float) -> int:
    """Entries sent per delta-topk version: ceil(fraction * numel), at least 1."""
    return min(numel, max(1, math.ceil(fraction * numel)))


class WeightEncoder:
    """Actor side: encodes successive parameter vectors as versions, with error feedback.

    ``held`` is what every replica holds after the versions encoded so far (``published``).
    Each delta is ``true - published`` at encoding time, so whatever a version fails to
    transmit (bfloat16 rounding, entries outside the top-k) stays in the next delta instead of
    being lost.

    A version is sent ``full`` when it is the first one, every ``snapshot_every`` versions,
    when ``encode(..., full=True)`` asks, when a delta would not be smaller than a full payload,
    and when the delta or its result is not finite (a full version replicates NaNs faithfully;
    the next finite one clears them). ``seal`` signs each manifest (its envelope is the
    version's ``proof``, kept with the held weights for snapshots).
    """

    def __init__(
        self,
        layout: ParamLayout,
        encoding: str = "full",
        topk_fraction: float = 0.05,
        snapshot_every: int = 10,
        chunk_bytes: int = 1 << 20,
        *,
        start_version: int = 0,
        compression: str = "none",
        sender: str = "",
        base_hash: str = "",
        seal: Callable[[WeightManifest], bytes] | None = None,
    ) -> None:
        # Indices travel as uint32; an empty layout has nothing to replicate.
        for ok, problem in (
            (compression in COMPRESSIONS, f"compression must be one of {COMPRESSIONS}, got {compression!r}"),
            (encoding in ENCODINGS, f"encoding must be one of {ENCODINGS}, got {encoding!r}"),
            (0.0 < topk_fraction <= 1.0, f"topk_fraction must be in (0, 1], got {topk_fraction!r}"),
            (snapshot_every >= 1, f"snapshot_every must be >= 1, got {snapshot_every!r}"),
            (chunk_bytes >= 1, f"chunk_bytes must be >= 1, got {chunk_bytes!r}"),
            (0 < layout.numel < 2**32, f"layout must hold between 1 and 2**32 - 1 elements, has {layout.numel}"),
            (start_version >= 0, f"start_version must be >= 0, got {start_version!r}"),
        ):
            if not ok:
                raise ValueError(problem)
        self.layout = layout
        self.encoding = encoding
        self.topk_fraction = topk_fraction
        self.snapshot_every = snapshot_every
        self.chunk_bytes = chunk_bytes
        #: "zstd": delta payloads travel compressed (when that is smaller); full ones never do
        self.compression = compression
        self.sender, self.base_hash, self.seal = sender, base_hash, seal
        #: last version encoded (0 before the first encode, or ``start_version`` when resuming)
        self.version = start_version
        self.held = HeldWeights(layout)
        n = layout.numel
        # Buffers an encoding does not use are left empty rather than sized for the layout.
        self._delta_buf = np.zeros(n if encoding != "full" else 0, dtype=np.float32)
        self._bf16 = np.zeros(n if encoding == "delta-bf16" else 0, dtype=_U16)
        self._k = topk_count(n, topk_fraction)
        self._topk = np.zeros(2 * self._k if encoding == "delta-topk" else 0, dtype=_U32)
        # A bf16 model's full versions travel as bf16 (half the bytes, exact): its weights are
        # bf16 values, checked at each full version (one pass) before relying on it.
        self._bf16_model = bool(layout.dtypes) and all(d == "bfloat16" for d in layout.dtypes)
        self._full16 = np.zeros(n if self._bf16_model else 0, dtype=_U16)

    @classmethod
    def from_config(cls, layout: ParamLayout, cfg: ReplicationConfig, **kwargs: Any) -> "WeightEncoder":
        """An encoder with the settings of a :class:`ReplicationConfig` (`kwargs`: the
        keyword-only arguments)."""
        return cls(layout, cfg.encoding, topk_fraction=cfg.topk_fraction, snapshot_every=cfg.snapshot_every,
                   chunk_bytes=cfg.chunk_bytes, compression=cfg.compression, **kwargs)

    @property
    def published(self) -> np.ndarray:
        """The flat parameters every up-to-date replica holds (``held.active``, read-only)."""
        return self.held.active

    def _wants_full(self, version: int) -> bool:
        if self.encoding == "full" or self.held.version < 0:
            return True
        if (version - 1) % self.snapshot_every == 0:
            return True
        # A top-k payload (8 bytes per entry) at least as large as a full one buys nothing.
        return self.encoding == "delta-topk" and 2 * self._k >= self.layout.numel

    def encode(self, true_flat: np.ndarray, *, full: bool = False) -> WeightVersion:
        """Encode the next version from the current true parameters (flat float32); it is
        ``published`` (held) once this returns."""
        n = self.layout.numel
        if not isinstance(true_flat, np.ndarray) or true_flat.dtype != np.float32 or true_flat.shape != (n,):
            raise LayoutMismatch(f"expected a float32 vector of {n} elements")
        version = self.version + 1
        payload: memoryview | None = None
        encoding = self.encoding
        new = self.held.staging
        if not (full or self._wants_full(version)) and (payload := self._delta(true_flat, new)) is not None:
            # What every replica will hold, computed by the very function they decode with.
            _decode_into(encoding, payload, self.held.active, new)
            if not _all_finite(new):
                payload = None
        if payload is None:
            encoding = "full"
            np.copyto(new, true_flat)
            payload = memoryview(new).cast("B")
            if self._bf16_model:
                bits = new.view(_U32)
                if not np.any(bits & 0xFFFF):
                    np.right_shift(bits, 16, out=self._full16, casting="unsafe")
                    encoding, payload = "full-bf16", memoryview(self._full16).cast("B")
        base = -1 if _is_full(encoding) else version - 1
        if not _is_full(encoding) and self.compression == ZSTD:
            z = deflate_delta(encoding, payload)
            if len(z) < payload.nbytes:
                payload, encoding = memoryview(z), f"{encoding}+{ZSTD}"
        digest = checksum(new)
        manifest = WeightManifest(
            sender=self.sender, version=version, base_version=base, encoding=encoding, layout_hash=self.layout.hash,
            n_chunks=chunk_count(payload.nbytes, self.chunk_bytes), total_bytes=payload.nbytes, checksum=digest,
            # what a snapshot of this version, served by any relay, must hash to
            digest=hashlib.sha256(memoryview(new).cast("B")).hexdigest(), numel=n, base_hash=self.base_hash,
        )
        proof = self.seal(manifest) if self.seal is not None else b""
        self.version = version
        self.held.publish(version, digest, proof)
        return WeightVersion(manifest, payload, proof)

    def _delta(self, true_flat: np.ndarray, scratch: np.ndarray) -> memoryview | None:
        """The delta payload ``true - published`` (None when it is not finite)."""
        d = self._delta_buf
        np.subtract(true_flat, self.held.active, out=d)
        if not _all_finite(d):
            return None
        if self.encoding == "delta-bf16":
            return memoryview(bf16_round_bits(d, out=self._bf16, scratch=scratch.view(np.uint32))).cast("B")
        n, k = self.layout.numel, self._k
        chosen = np.argpartition(np.abs(d, out=scratch), n - k)[n - k :]
        chosen.sort()  # ascending indices: cache-friendly scatter, and a cheap validity check
        np.copyto(self._topk[:k], chosen, casting="unsafe")  # < numel < 2**32
        np.take(d, self._topk[:k], out=self._topk[k:].view(_F32))
        return memoryview(self._topk).cast("B")


class HeldWeights:
    """The newest verified weights a node holds: ``version``, ``checksum``, the flat float32
    ``active`` vector, and ``proof`` (the actor's signed manifest envelope of that version).

    The one writer (the encoder, or :meth:`apply`) computes the next version in ``staging`` and
    swaps it in under ``lock``; readers hold ``lock`` while they read ``active``, so a reader
    sees one version whole and never waits for a decode.
    """

    def __init__(self, layout: ParamLayout) -> None:
        if layout.numel < 1:
            raise ValueError("layout holds no elements")
        self.layout = layout
        # Written once here so every page is mapped now: np.zeros alone maps them lazily, and
        # the first two versions would pay the page faults mid-transfer.
        self._bufs = (np.empty(layout.numel, dtype=np.float32), np.empty(layout.numel, dtype=np.float32))
        for buf in self._bufs:
            buf.fill(0.0)
        self._cur = 0
        #: held by readers of ``active``, and by the writer while it swaps
        self.lock = threading.Lock()
        #: (version, checksum) of ``active``, assigned together ((-1, ""): nothing yet)
        self.id: tuple[int, str] = (-1, "")
        self.proof = b""
        #: versions made active so far
        self.updates = 0
        #: bumped when a write into staging starts and when it is swapped in: odd while one is
        #: under way
        self.seq = 0

    @property
    def version(self) -> int:
        return self.id[0]

    @property
    def checksum(self) -> str:
        """:func:`checksum` of ``active`` ("" before the first version)."""
        return self.id[1]

    @property
    def active(self) -> np.ndarray:
        """Flat parameters of ``version`` (zeros before the first); read it under ``lock``."""
        return self._bufs[self._cur]

    @property
    def staging(self) -> np.ndarray:
        """The writer's buffer, where the next version is computed."""
        return self._bufs[1 - self._cur]

    def publish(self, version: int, digest: str, proof: bytes = b"") -> None:
        """Make ``staging`` (holding `version`, whose checksum is `digest`) active."""
        with self.lock:
            self._cur = 1 - self._cur
            self.id, self.proof = (version, digest), proof
            self.updates += 1

    def apply(self, m: WeightManifest, payload: BytesLike, proof: bytes = b"") -> None:
        """Decode one version into staging, verify it, and make it active.

        This is where the replicas' promise lives: a version is held only if the decoded
        parameters hash to the manifest's checksum, the actor's, bit for bit.

        Raises :class:`LayoutMismatch`, :class:`CorruptPayload`, :class:`StaleVersion`,
        :class:`NeedSnapshot` or :class:`ChecksumMismatch`; on any error nothing held changes.
        """
        view = _byte_view(payload)
        self._check(m, view.nbytes)
        encoding, comp = split_encoding(m.encoding)
        if comp:
            view = inflate_delta(encoding, view, self.layout.numel)
            self._check_size(encoding, view.nbytes)
        if m.version <= self.version:
            raise StaleVersion(f"version {m.version} is not newer than held version {self.version}")
        if not _is_full(encoding) and m.base_version != self.version:
            raise NeedSnapshot(have=self.version, base=m.base_version, version=m.version)
        staging = self.staging
        self.seq += 1
        try:
            _decode_into(encoding, view, self.active, staging)
            digest = checksum(staging)
            if digest != m.checksum:
                raise ChecksumMismatch(f"version {m.version}: decoded checksum {digest} != manifest {m.checksum}")
            self.publish(m.version, digest, proof)
        finally:
            self.seq += 1

    def _check(self, m: WeightManifest, nbytes: int) -> None:
        if m.layout_hash != self.layout.hash:
            raise LayoutMismatch(f"sender layout {m.layout_hash} != local layout {self.layout.hash}")
        base, comp = split_encoding(m.encoding)
        if (base not in ENCODINGS and base not in FULL_ENCODINGS) or comp not in ("", ZSTD) or (comp and _is_full(base)):
            raise CorruptPayload(f"unknown encoding {m.encoding!r}")
        if m.version < 1:
            raise CorruptPayload(f"version must be >= 1, got {m.version}")
        want_base = -1 if _is_full(base) else m.version - 1
        if m.base_version != want_base:
            raise CorruptPayload(f"{m.encoding} version {m.version} must have base {want_base}, got {m.base_version}")
        if nbytes != m.total_bytes or not _spans_valid(m.n_chunks, m.total_bytes):
            raise CorruptPayload(f"payload of {nbytes} bytes does not match manifest ({m.n_chunks}, {m.total_bytes})")
        if comp:
            if nbytes > 4 * self.layout.numel:
                raise CorruptPayload(f"{m.encoding} payload of {nbytes} bytes is larger than a full one")
            return  # sizes of the inflated payload are checked after inflating
        self._check_size(base, nbytes)

    def _check_size(self, encoding: str, nbytes: int) -> None:
        n = self.layout.numel
        want = {"full": 4 * n, "full-bf16": 2 * n, "delta-bf16": 2 * n}.get(encoding, nbytes)
        if nbytes != want:
            raise CorruptPayload(f"{encoding} payload must be {want} bytes, got {nbytes}")
        if encoding == "delta-topk" and (nbytes % 8 or nbytes > 4 * n):
            # Encoders never send a top-k payload larger than a full one.
            raise CorruptPayload(f"delta-topk payload of {nbytes} bytes is not 8*k with 8*k <= {4 * n}")


class ChunkAssembler:
    """Reassembles one payload from chunks arriving in any order, into a reusable buffer.

    The buffer holds ``max_bytes`` (use ``layout.nbytes``: no encoding produces more) and is
    reused across versions through :meth:`reset`.
    """

    def __init__(self, n_chunks: int, total_bytes: int, max_bytes: int) -> None:
        if max_bytes < 1:
            raise ValueError(f"max_bytes must be >= 1, got {max_bytes}")
        self.max_bytes = max_bytes
        self._view = memoryview(bytearray(max_bytes))
        self.reset(n_chunks, total_bytes)

    def reset(self, n_chunks: int, total_bytes: int) -> None:
        """Start assembling a new payload (the buffer is reused, not reallocated)."""
        if not all(isinstance(x, int) and not isinstance(x, bool) for x in (n_chunks, total_bytes)):
            raise ReplicationError("n_chunks and total_bytes must be integers")
        if not 1 <= total_bytes <= self.max_bytes:
            raise ReplicationError(f"total_bytes {total_bytes} outside [1, {self.max_bytes}]")
        if not _spans_valid(n_chunks, total_bytes):
            raise ReplicationError(f"{n_chunks} chunks cannot split {total_bytes} bytes")
        self.n_chunks = n_chunks
        self.total_bytes = total_bytes
        self._have = bytearray(n_chunks)
        self._received = 0

    @property
    def complete(self) -> bool:
        """Whether every chunk has arrived."""
        return self._received == self.n_chunks

    def add(self, index: int, data: BytesLike) -> bool:
        """Store chunk ``index``; True if it was new, False for a duplicate (ignored).

        An index out of range or a chunk whose size differs from its span raises
        :class:`ReplicationError`.
        """
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < self.n_chunks:
            raise ReplicationError(f"chunk index {index!r} outside [0, {self.n_chunks})")
        if self._have[index]:
            return False
        start, stop = chunk_span(index, self.n_chunks, self.total_bytes)
        src = _byte_view(data)
        if src.nbytes != stop - start:
            raise ReplicationError(f"chunk {index} has {src.nbytes} bytes, expected {stop - start}")
        self._view[start:stop] = src
        self._have[index] = 1
        self._received += 1
        return True

    def payload(self) -> memoryview:
        """The assembled payload (valid until :meth:`reset`); raises if chunks are missing."""
        if not self.complete:
            raise ReplicationError(f"payload incomplete: {self._received}/{self.n_chunks} chunks")
        return self._view[: self.total_bytes]

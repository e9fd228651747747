"""Unit tests of dvla.replication: layout, encodings, chunking, verified decoding, held weights
and catch-up."""

from __future__ import annotations

import dataclasses
import hashlib
import math
import threading

import numpy as np
import pytest
import torch
import zstandard

from dvla.config import ENCODINGS, ReplicationConfig
from dvla.fabric.codec import decode, encode
from dvla.fabric.errors import CodecError
from dvla.replication import (
    ChecksumMismatch,
    ChunkAssembler,
    CorruptPayload,
    HeldWeights,
    LayoutMismatch,
    NeedSnapshot,
    ParamLayout,
    ReplicationError,
    StaleVersion,
    WeightEncoder,
    WeightVersion,
    bf16_round_bits,
    bf16_to_float32,
    checksum,
    chunk_count,
    split_chunks,
    split_encoding,
    flatten,
    unflatten_into,
)

CHUNK_BYTES = 16_384  # small, so every version of the ~50k-param model spans many chunks
TOPK_FRACTION = 0.05
JUMP_VERSIONS = (40, 75, 130, 165)  # one "large jump" pair in each half of the run


def _mlp(hidden: int = 128, seed: int = 0) -> torch.nn.Module:
    """~50k floating parameters plus an integer counter buffer."""
    torch.manual_seed(seed)
    model = torch.nn.Sequential(
        torch.nn.Linear(64, hidden),
        torch.nn.Tanh(),
        torch.nn.Linear(hidden, 256),
        torch.nn.LayerNorm(256),
        torch.nn.Tanh(),
        torch.nn.Linear(256, 32),
    )
    model.register_buffer("steps", torch.zeros((), dtype=torch.int64))
    return model


@pytest.fixture(scope="module")
def layout() -> ParamLayout:
    return ParamLayout.from_state_dict(_mlp())


# --------------------------------------------------------------------------------------------
# Layout


def test_layout_covers_float_tensors_only_and_hash_is_stable(layout: ParamLayout) -> None:
    assert "steps" not in layout.names
    assert layout.numel == 50_080
    assert layout.nbytes == 4 * layout.numel
    assert ParamLayout.from_state_dict(_mlp(seed=7).state_dict()).hash == layout.hash


def test_layout_hash_depends_on_names_shapes_dtypes(layout: ParamLayout) -> None:
    assert ParamLayout.from_state_dict(_mlp(hidden=96)).hash != layout.hash
    renamed = ParamLayout(names=("x",) + layout.names[1:], shapes=layout.shapes, dtypes=layout.dtypes)
    assert renamed.hash != layout.hash
    half = ParamLayout(names=layout.names, shapes=layout.shapes, dtypes=("float16",) + layout.dtypes[1:])
    assert half.hash != layout.hash


def test_flatten_and_unflatten_work_in_place(layout: ParamLayout) -> None:
    src, dst = _mlp(seed=1), _mlp(seed=2)
    dst.steps.fill_(5)
    buf = np.zeros(layout.numel, np.float32)
    assert flatten(src, layout, out=buf) is buf
    assert np.array_equal(buf, flatten(src.state_dict(), layout))
    ptrs = {name: t.data_ptr() for name, t in dst.state_dict().items()}
    unflatten_into(buf, dst, layout)
    assert {name: t.data_ptr() for name, t in dst.state_dict().items()} == ptrs
    for name, tensor in src.state_dict().items():
        if name != "steps":
            assert torch.equal(dst.state_dict()[name], tensor)
    assert int(dst.steps) == 5  # non-float buffers are not replicated
    x = torch.randn(3, 64)
    assert torch.equal(src(x), dst(x))
    # A read-only source (e.g. a received payload) works too.
    unflatten_into(np.frombuffer(buf.tobytes(), dtype=np.float32), dst, layout)


def test_flatten_rejects_mismatches(layout: ParamLayout) -> None:
    with pytest.raises(LayoutMismatch):
        flatten(_mlp(hidden=96), layout)
    sd = dict(_mlp().state_dict())
    del sd["0.bias"]
    with pytest.raises(LayoutMismatch):
        flatten(sd, layout)
    with pytest.raises(LayoutMismatch):
        flatten(_mlp(), layout, out=np.zeros(layout.numel, dtype=np.float64))
    with pytest.raises(LayoutMismatch):
        unflatten_into(np.zeros(layout.numel - 1, dtype=np.float32), _mlp(), layout)


# --------------------------------------------------------------------------------------------
# bfloat16, checksum, chunks


def test_bf16_rounding_matches_torch() -> None:
    rng = np.random.default_rng(3)
    bits = rng.integers(0, 2**32, size=200_000, dtype=np.uint64).astype(np.uint32)
    # Exact ties (low half 0x8000) with both parities of the kept bit, and neighbours.
    bits[:3000] = (bits[:3000] & 0xFFFF0000) | 0x8000
    bits[3000:6000] = (bits[3000:6000] & 0xFFFF0000) | 0x7FFF
    x = bits.view(np.float32)
    x = x[np.isfinite(x)]
    specials = np.array([0.0, -0.0, np.inf, -np.inf, 3.4e38, -3.4e38, 1e-40, -1e-45, 1.0, 1.00390625], np.float32)
    x = np.concatenate([x, specials])
    ours = bf16_round_bits(x)
    ref = torch.from_numpy(x).to(torch.bfloat16).view(torch.int16).numpy().view(np.uint16)
    assert np.array_equal(ours, ref)
    assert np.array_equal(bf16_to_float32(ours), torch.from_numpy(x).to(torch.bfloat16).float().numpy())


def test_bf16_keeps_nan_as_nan() -> None:
    x = np.array([1.5, -2.0], np.float32)
    nan_bits = np.array([0x7F800001, 0xFFFFFFFF, 0x7FC00000], np.uint32)  # would round to inf/wrap
    x = np.concatenate([x, nan_bits.view(np.float32)])
    back = bf16_to_float32(bf16_round_bits(x))
    assert back[0] == 1.5 and back[1] == -2.0
    assert np.isnan(back[2:]).all()
    assert np.signbit(back[3]) and not np.signbit(back[2])


def test_checksum_is_bit_exact() -> None:
    a = np.linspace(-1, 1, 1000, dtype=np.float32)
    b = a.copy()
    assert checksum(a) == checksum(b) and len(checksum(a)) == 32
    b.view(np.uint32)[500] ^= 1
    assert checksum(a) != checksum(b)
    with pytest.raises(ValueError):
        checksum(a[::2])


@pytest.mark.parametrize("total, chunk", [(1, 1), (10, 4), (9, 4), (100, 100), (101, 100), (200_320, 16_384)])
def test_split_chunks_is_even_and_bounded(total: int, chunk: int) -> None:
    payload = bytes(range(256)) * (total // 256 + 1)
    payload = payload[:total]
    chunks = split_chunks(payload, chunk)
    assert len(chunks) == chunk_count(total, chunk) == math.ceil(total / chunk)
    assert all(0 < c.nbytes <= chunk for c in chunks)
    assert b"".join(bytes(c) for c in chunks) == payload
    asm = ChunkAssembler(len(chunks), total, max_bytes=total + 7)
    for i in reversed(range(len(chunks))):
        assert asm.add(i, chunks[i])
    assert bytes(asm.payload()) == payload


def test_chunk_assembler_rules() -> None:
    payload = np.arange(1000, dtype=np.float32).tobytes()
    chunks = split_chunks(payload, 1024)
    asm = ChunkAssembler(len(chunks), len(payload), max_bytes=8000)
    assert asm.add(2, chunks[2]) and not asm.add(2, b"\0" * chunks[2].nbytes)  # duplicate ignored
    assert not asm.complete
    with pytest.raises(ReplicationError):
        asm.payload()
    for bad in (-1, 4, True, 1.0):
        with pytest.raises(ReplicationError):
            asm.add(bad, chunks[0])  # type: ignore[arg-type]
    with pytest.raises(ReplicationError):
        asm.add(0, bytes(chunks[0]) + b"x")  # oversize
    with pytest.raises(ReplicationError):
        asm.add(3, bytes(chunks[3])[:-1])  # undersize
    for i in (0, 1, 3):
        asm.add(i, chunks[i])
    assert asm.complete and bytes(asm.payload()) == payload
    asm.reset(1, 10)  # the next payload, in the same buffer
    assert not asm.complete and asm.add(0, bytes(range(10))) and bytes(asm.payload()) == bytes(range(10))
    with pytest.raises(ReplicationError):
        asm.reset(1, 8001)  # larger than the buffer
    with pytest.raises(ReplicationError):
        asm.reset(4, 9)  # 4 even chunks of 3 bytes cannot make 9 bytes
    with pytest.raises(ReplicationError):
        asm.reset(0, 9)


# --------------------------------------------------------------------------------------------
# End-to-end replication


def _deliver(ev: WeightVersion, asm: ChunkAssembler, rng: np.random.Generator) -> memoryview:
    """Send every chunk in a random order, with a few duplicates, as a network would."""
    n = ev.manifest.n_chunks
    asm.reset(n, ev.manifest.total_bytes)
    order = list(rng.permutation(n)) + list(rng.integers(0, n, size=2))
    for i in order:
        asm.add(int(i), bytes(ev.chunks[i]))
    return asm.payload()


def _step(true: np.ndarray, version: int, rng: np.random.Generator) -> None:
    """Random-walk update of varied scale, with occasional large jumps."""
    scale = 10.0 ** rng.uniform(-4, -2)
    if version in JUMP_VERSIONS:
        scale = 0.05
    true += (scale * rng.standard_normal(true.size)).astype(np.float32)


@pytest.mark.parametrize(
    "encoding, snapshot_every, compression",
    [
        (e, s, c)
        for e in ENCODINGS
        for s in (10, 10**9)
        for c in ("none", "zstd")
        if not (e == "full" and (s > 10 or c != "none"))  # full ignores cadence and compression
    ],
    ids=lambda v: v if isinstance(v, str) else ("snap10" if v == 10 else "nosnap"),
)
def test_replicas_are_bit_exact_and_gap_is_bounded(
    layout: ParamLayout, encoding: str, snapshot_every: int, compression: str
) -> None:
    rng = np.random.default_rng(11)
    enc = WeightEncoder(
        layout, encoding, topk_fraction=TOPK_FRACTION, snapshot_every=snapshot_every, chunk_bytes=CHUNK_BYTES,
        compression=compression,
    )
    replicas = [(HeldWeights(layout), ChunkAssembler(1, 1, layout.nbytes)) for _ in range(2)]
    true = flatten(_mlp(), layout)
    start = true.copy()
    gaps, delta_ratios = [0.0], []
    for version in range(1, 201):
        if version > 1:
            _step(true, version, rng)
        before = float(np.linalg.norm(true - enc.published))
        ev = enc.encode(true)
        m = ev.manifest
        assert (m.version, m.layout_hash, m.checksum) == (version, layout.hash, checksum(enc.published))
        assert m.digest == hashlib.sha256(enc.published.tobytes()).hexdigest() and m.numel == layout.numel
        assert all(c.nbytes <= CHUNK_BYTES for c in ev.chunks) and sum(c.nbytes for c in ev.chunks) == m.total_bytes
        expect_full = encoding == "full" or (version - 1) % snapshot_every == 0
        base, comp = split_encoding(m.encoding)
        assert base == ("full" if expect_full else encoding)
        assert comp == ("zstd" if compression == "zstd" and not expect_full else "")
        assert m.base_version == (-1 if expect_full else version - 1)
        for held, asm in replicas:
            held.apply(decode(encode(m)), _deliver(ev, asm, rng))  # the manifest as it travels
            assert held.id == enc.held.id == (version, m.checksum)
            assert np.array_equal(held.active, enc.published)
        gap = float(np.linalg.norm(true - enc.published))
        gaps.append(gap)
        if base == "delta-bf16":
            # Each element is off by at most half a bfloat16 ulp of its delta (2**-9 relative).
            assert gap <= 2.0**-8 * before
        if base != "full":
            delta_ratios.append(m.total_bytes / layout.nbytes)
        else:
            assert gap == 0.0
    # Error feedback: the gap does not accumulate.
    assert max(gaps[101:201]) <= 2 * max(gaps[20:101])
    if encoding == "delta-topk":
        assert np.median(gaps[150:201]) <= 1.5 * np.median(gaps[50:101])
        # Without error feedback the unsent 95% would pile up to ~0.8x the total drift.
        assert np.median(gaps[150:201]) < 0.25 * float(np.linalg.norm(true - start))
    if encoding == "delta-bf16":
        assert max(delta_ratios) < 0.55
    if encoding == "delta-topk":
        assert max(delta_ratios) < 0.15


@pytest.mark.parametrize("encoding", ["delta-bf16", "delta-topk"])
def test_missed_version_needs_snapshot_then_recovers(layout: ParamLayout, encoding: str) -> None:
    rng = np.random.default_rng(5)
    enc = WeightEncoder(layout, encoding, snapshot_every=1000, chunk_bytes=CHUNK_BYTES)
    relay, late = HeldWeights(layout), HeldWeights(layout)
    asm = ChunkAssembler(1, 1, layout.nbytes)
    true = flatten(_mlp(), layout)
    for version in range(1, 13):
        _step(true, version, rng)
        ev = enc.encode(true)
        payload = _deliver(ev, asm, rng)
        relay.apply(ev.manifest, payload)
        if version == 6:
            continue  # lost on the way to `late`
        if version < 6:
            late.apply(ev.manifest, payload)
            continue
        if version == 7:
            with pytest.raises(NeedSnapshot) as info:
                late.apply(ev.manifest, payload)
            assert (info.value.have, info.value.base, info.value.version) == (5, 6, 7)
            assert late.version == 5
            # Catch up from the relay's held weights, sent whole as a chunked full version.
            assert relay.id == (7, enc.held.checksum)
            whole = WeightVersion(ev.manifest.whole(len(split_chunks(relay.active, CHUNK_BYTES))),
                                  memoryview(relay.active.tobytes()))
            assert whole.manifest.encoding == "full" and whole.manifest.base_version == -1
            assert whole.manifest.checksum == ev.manifest.checksum and whole.manifest.digest == ev.manifest.digest
            late.apply(whole.manifest, _deliver(whole, asm, rng))
        else:
            late.apply(ev.manifest, payload)
        assert np.array_equal(late.active, enc.published) and late.version == version
    # The encoder holds what an up-to-date relay holds.
    assert enc.held.id == relay.id and np.array_equal(enc.published, relay.active)
    fresh = HeldWeights(layout)
    fresh.apply(ev.manifest.whole(1), enc.published.tobytes())
    assert fresh.version == 12 and np.array_equal(fresh.active, enc.published)


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_corrupted_chunk_is_rejected_and_active_kept(layout: ParamLayout, encoding: str) -> None:
    rng = np.random.default_rng(9)
    enc = WeightEncoder(layout, encoding, snapshot_every=1000, chunk_bytes=CHUNK_BYTES)
    dec = HeldWeights(layout)
    true = flatten(_mlp(), layout)
    v1 = enc.encode(true)
    dec.apply(v1.manifest, v1.payload)
    _step(true, 2, rng)
    ev = enc.encode(true)
    m = ev.manifest
    kept, kept_id = dec.active.copy(), dec.id
    payload = bytearray(ev.payload)
    # Flip a bit of a value (for top-k: in the value half, so indices stay valid).
    lo = m.total_bytes // 2 if encoding == "delta-topk" else 0
    pos = int(rng.integers(lo, m.total_bytes))
    payload[pos] ^= 0x10
    chunks = split_chunks(payload, CHUNK_BYTES)
    asm = ChunkAssembler(m.n_chunks, m.total_bytes, layout.nbytes)
    for i in rng.permutation(len(chunks)):
        asm.add(int(i), chunks[i])
    with pytest.raises(ChecksumMismatch):
        dec.apply(m, asm.payload())
    assert dec.id == kept_id and np.array_equal(dec.active, kept)
    dec.apply(m, ev.payload)  # the intact payload still applies
    assert np.array_equal(dec.active, enc.published)


@pytest.mark.parametrize("encoding", ["delta-bf16", "delta-topk"])
def test_compressed_deltas_shrink_and_damage_is_rejected(layout: ParamLayout, encoding: str) -> None:
    rng = np.random.default_rng(3)
    enc = WeightEncoder(layout, encoding, snapshot_every=1000, chunk_bytes=CHUNK_BYTES, compression="zstd")
    raw = WeightEncoder(layout, encoding, snapshot_every=1000, chunk_bytes=CHUNK_BYTES)
    dec = HeldWeights(layout)
    true = flatten(_mlp(), layout)
    v1 = enc.encode(true)
    dec.apply(v1.manifest, v1.payload)
    raw.encode(true)
    true += (1e-3 * rng.standard_normal(true.size)).astype(np.float32)  # an optimiser-sized step
    ev, ev_raw = enc.encode(true), raw.encode(true)
    m = ev.manifest
    assert m.encoding == f"{encoding}+zstd" and m.total_bytes < 0.8 * ev_raw.manifest.total_bytes
    kept = dec.active.copy()
    for pos in (5, m.total_bytes // 2, m.total_bytes - 3):
        bad = bytearray(ev.payload)
        bad[pos] ^= 0x41
        with pytest.raises((CorruptPayload, ChecksumMismatch)):
            dec.apply(m, bytes(bad))
        assert np.array_equal(dec.active, kept) and dec.version == 1
    # A payload that inflates beyond any real delta of this layout is refused before it grows.
    bomb = zstandard.ZstdCompressor().compress(bytes(8 * layout.numel))
    with pytest.raises(CorruptPayload, match="inflate|decompress"):
        dec.apply(dataclasses.replace(m, total_bytes=len(bomb), n_chunks=1), bomb)
    dec.apply(m, ev.payload)
    assert np.array_equal(dec.active, enc.published) and np.array_equal(enc.published, raw.published)


def test_corrupted_topk_index_is_rejected(layout: ParamLayout) -> None:
    enc = WeightEncoder(layout, "delta-topk", snapshot_every=1000)
    dec = HeldWeights(layout)
    true = flatten(_mlp(), layout)
    ev = enc.encode(true)
    dec.apply(ev.manifest, ev.payload)
    true[::3] += 0.01
    ev = enc.encode(true)
    for pos in (3, 4):  # high byte of the first index (out of range); low byte of the second (wrong index)
        payload = bytearray(ev.payload)
        payload[pos] ^= 0xFF
        with pytest.raises(CorruptPayload):
            dec.apply(ev.manifest, payload)
    assert dec.version == 1


def test_layout_mismatch_is_detected(layout: ParamLayout) -> None:
    enc = WeightEncoder(layout, "delta-bf16")
    ev = enc.encode(flatten(_mlp(), layout))
    other = HeldWeights(ParamLayout.from_state_dict(_mlp(hidden=96)))
    with pytest.raises(LayoutMismatch):
        other.apply(ev.manifest, ev.payload)
    forged = dataclasses.replace(ev.manifest, layout_hash="0" * 32)
    with pytest.raises(LayoutMismatch):
        HeldWeights(layout).apply(forged, ev.payload)
    with pytest.raises(LayoutMismatch):
        enc.encode(np.zeros(layout.numel + 1, dtype=np.float32))
    assert issubclass(LayoutMismatch, ReplicationError)


def test_stale_and_malformed_versions(layout: ParamLayout) -> None:
    enc = WeightEncoder(layout, "delta-bf16")
    dec = HeldWeights(layout)
    true = flatten(_mlp(), layout)
    v1 = enc.encode(true)
    dec.apply(v1.manifest, v1.payload)
    with pytest.raises(StaleVersion):
        dec.apply(v1.manifest, v1.payload)
    true += 0.01
    v2 = enc.encode(true)
    m = v2.manifest
    bad = [
        dataclasses.replace(m, version=0),
        dataclasses.replace(m, base_version=0),
        dataclasses.replace(m, encoding="gzip"),
        dataclasses.replace(m, total_bytes=m.total_bytes + 1),
        dataclasses.replace(m, checksum=""),
    ]
    for manifest in bad:
        with pytest.raises(CorruptPayload):
            dec.apply(manifest, v2.payload)
    with pytest.raises(CorruptPayload):
        dec.apply(m, bytes(v2.payload)[:-2])
    assert dec.version == 1
    # A field of the wrong type never reaches a replica: the codec refuses it (bool is no int).
    with pytest.raises(CodecError):
        decode(encode(dataclasses.replace(m, version=True)))
    dec.apply(decode(encode(m)), v2.payload)
    assert dec.version == 2


def test_held_weights_swap_whole_versions_and_readers_never_see_a_mix(layout: ParamLayout) -> None:
    """The writer decodes into staging while readers read active; a version becomes active by a
    reference swap, which waits for a reader holding the lock (never the other way round)."""
    enc = WeightEncoder(layout, "delta-topk", snapshot_every=1000)
    held = HeldWeights(layout)
    assert held.id == (-1, "") and held.updates == 0
    true = flatten(_mlp(), layout)
    v1 = enc.encode(true)
    held.apply(v1.manifest, v1.payload)
    first, spare = held.active, held.staging
    true[:100] += 1.0
    v2 = enc.encode(true)
    held.apply(v2.manifest, v2.payload)
    assert held.active is spare and held.staging is first and held.updates == 2
    assert np.array_equal(held.active, enc.published)
    true[100:200] -= 1.0
    v3 = enc.encode(true)
    with held.lock:  # a reader of v2
        reading = held.active.copy()
        writer = threading.Thread(target=held.apply, args=(v3.manifest, v3.payload))
        writer.start()
        writer.join(0.5)
        assert writer.is_alive() and held.version == 2 and np.array_equal(held.active, reading)
        assert np.array_equal(held.staging, enc.published)  # decoded and verified, waiting to swap
    writer.join(5)
    assert held.id == enc.held.id == (3, v3.manifest.checksum) and np.array_equal(held.active, enc.published)


def test_non_finite_parameters_go_out_as_full(layout: ParamLayout) -> None:
    enc = WeightEncoder(layout, "delta-bf16", snapshot_every=1000)
    dec = HeldWeights(layout)
    true = flatten(_mlp(), layout)
    encodings = []
    for change in (None, "nan", "heal", "small", "huge"):
        if change == "nan":
            true[7] = np.nan
        elif change == "heal":
            true[7] = 0.5
        elif change == "small":
            true += 1e-3
        elif change == "huge":
            true[9] = 3.4e38  # the delta rounds to bfloat16 infinity
        ev = enc.encode(true)
        encodings.append(ev.manifest.encoding)
        dec.apply(ev.manifest, ev.payload)
        assert dec.checksum == checksum(enc.published)
        assert np.array_equal(dec.active, enc.published, equal_nan=True)
    assert encodings == ["full", "full", "full", "delta-bf16", "full"]
    assert enc.published[9] == np.float32(3.4e38)


def test_encoder_configuration(layout: ParamLayout) -> None:
    cfg = ReplicationConfig(encoding="delta-topk", topk_fraction=0.6, snapshot_every=3, chunk_bytes=4096)
    enc = WeightEncoder.from_config(layout, cfg, start_version=41)
    true = flatten(_mlp(), layout)
    # A top-k payload at least as large as a full one is never sent.
    assert [enc.encode(true).manifest.encoding for _ in range(3)] == ["full"] * 3
    assert enc.version == 44 and enc.held.version == 44
    for kwargs in ({"encoding": "zstd"}, {"topk_fraction": 0.0}, {"snapshot_every": 0}, {"chunk_bytes": 0}):
        with pytest.raises(ValueError):
            WeightEncoder(layout, **{"encoding": "full", **kwargs})
    assert WeightEncoder(layout).held.id == (-1, "")  # nothing published before the first encode
    # The manifest names the sender and the frozen base, and the seal signs it (the version's proof).
    sealed = WeightEncoder(layout, sender="actor-0", base_hash="b0", seal=lambda m: encode(m)).encode(true)
    assert (sealed.manifest.sender, sealed.manifest.base_hash) == ("actor-0", "b0")
    assert decode(sealed.proof) == sealed.manifest


def test_decoded_weights_drive_the_policy(layout: ParamLayout) -> None:
    learner, rollout = _mlp(seed=1), _mlp(seed=2)
    enc = WeightEncoder(layout, "delta-bf16", snapshot_every=1000)
    dec = HeldWeights(layout)
    buf = np.zeros(layout.numel, np.float32)
    x = torch.randn(16, 64)
    for _ in range(5):
        with torch.no_grad():  # stands in for a learner step
            for param in learner.parameters():
                param.add_(0.01 * torch.randn_like(param))
        ev = enc.encode(flatten(learner, layout, out=buf))
        dec.apply(ev.manifest, ev.payload)
    unflatten_into(dec.active, rollout, layout)
    published = _mlp(seed=3)
    unflatten_into(enc.published, published, layout)
    assert torch.equal(rollout(x), published(x))
    assert torch.allclose(rollout(x), learner(x), atol=1e-3)


def _declare_content_size(frame: bytes, size: int) -> bytes:
    """A zstd frame written without a content size, its header edited to declare ``size`` bytes."""
    assert frame[4] & 0xE3 == 0  # no content size, not single-segment, no dictionary: window byte next
    return frame[:4] + bytes([frame[4] | 0xC0]) + frame[5:6] + int(size).to_bytes(8, "little") + frame[6:]


@pytest.mark.parametrize("encoding", ["delta-bf16", "delta-topk"])
def test_zstd_frame_declaring_a_huge_size_is_refused_without_allocating(encoding: str) -> None:
    import os
    import tracemalloc

    from dvla.replication.encoding import inflate_delta

    small = zstandard.ZstdCompressor(write_content_size=False).compress(os.urandom(1600))
    bomb = _declare_content_size(small, 2**40)  # ~1.6 KB declaring 1 TiB
    assert zstandard.frame_content_size(bomb) == 2**40 and len(bomb) < 2048
    # What an uncapped decompress does with it: ask for 1 TiB (MemoryError where the kernel refuses
    # that; where it overcommits, the allocation succeeds and the missing data is found afterwards).
    with pytest.raises((MemoryError, zstandard.ZstdError)):
        zstandard.ZstdDecompressor().decompress(bomb, max_output_size=4096)
    tracemalloc.start()
    try:
        with pytest.raises(CorruptPayload, match="inflates to 1099511627776 bytes"):
            inflate_delta(encoding, memoryview(bomb), 1000)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20  # refused from the declared size, before any allocation
    # Frames without a declared size, lying sizes, trailing bytes and junk: all CorruptPayload.
    numel = 400  # delta-bf16 caps output at 800 bytes, delta-topk at 1600
    for data in (
        small,  # 1600 bytes, no declared size: more than delta-bf16's cap, not 8*k for topk
        _declare_content_size(small, 100),  # declares less than it holds
        zstandard.ZstdCompressor().compress(bytes(2 * numel)) + b"xx",
        b"\x28\xb5\x2f\xfd",
        b"not zstd at all",
    ):
        with pytest.raises(CorruptPayload):
            inflate_delta(encoding, memoryview(data), numel)
    good = zstandard.ZstdCompressor().compress(bytes(2 * numel))
    assert inflate_delta(encoding, memoryview(good), numel).nbytes == 2 * numel


def test_a_bf16_models_full_versions_travel_as_bf16_exactly() -> None:
    """A model whose tensors are all bfloat16 sends its full versions as `full-bf16`: half the
    bytes, decoded bit for bit; a vector that is not bf16-exact (never from such a model) falls
    back to float32 `full`, and a float32 model never uses it."""
    model = torch.nn.Sequential(torch.nn.Linear(8, 8), torch.nn.Linear(8, 3)).to(torch.bfloat16)
    layout = ParamLayout.from_state_dict(model)
    flat = flatten(model, layout)
    enc, dec = WeightEncoder(layout, "delta-bf16", snapshot_every=2), HeldWeights(layout)
    v1 = enc.encode(flat)
    m1 = v1.manifest
    assert m1.encoding == "full-bf16" and m1.total_bytes == 2 * layout.numel and m1.base_version == -1
    dec.apply(m1, v1.payload)
    np.testing.assert_array_equal(dec.active, flat)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.01)
    v2 = enc.encode(flatten(model, layout))
    assert v2.manifest.encoding == "delta-bf16"
    dec.apply(v2.manifest, v2.payload)
    np.testing.assert_array_equal(dec.active, enc.published)
    # not bf16-exact: float32 full version
    v3 = WeightEncoder(layout).encode(flat + np.float32(1e-4)).manifest
    assert v3.encoding == "full" and v3.total_bytes == 4 * layout.numel
    f32 = ParamLayout.from_state_dict(torch.nn.Linear(8, 3))
    assert WeightEncoder(f32).encode(np.zeros(f32.numel, np.float32)).manifest.encoding == "full"
    # a full-bf16 payload of the wrong size is refused
    bad = dataclasses.replace(m1, total_bytes=4 * layout.numel)
    with pytest.raises(CorruptPayload):
        HeldWeights(layout).apply(bad, bytes(4 * layout.numel))

"""The codec's layout fast path (dvla/fabric/layout.py) against the full encoder and decoder.

The fast path must be invisible: the same bytes out of `encode_into`, the same messages (or
the same CodecError reason) out of `decode`, for any input. These tests prime the caches with
a real message, then compare both paths on variations and on mutated bytes, and check that the
fast path is really the one taken (the full walkers are patched out).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dvla.fabric import codec
import dvla.fabric.layout as layout_mod
from dvla.fabric.codec import LAYOUT_MIN_BYTES, LAYOUTS, WRITERS, CodecError, decode, encode, encode_into
from dvla.fabric.messages import TrajectoryChunk

from tests.unit.test_codec import assert_same, make_traj

FUZZ = settings(max_examples=150, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture(autouse=True, params=["c-views", "python-views"])
def fresh_caches(request, monkeypatch):
    """Every test runs twice: spans and array views by the C helper, and in Python."""
    if request.param == "python-views":
        monkeypatch.setattr(layout_mod, "_C", None)
    elif layout_mod._C is None:
        pytest.skip("dvla.fabric._views is not built here (test_the_c_helper_is_built says why)")
    LAYOUTS.clear()
    WRITERS.clear()
    yield
    LAYOUTS.clear()
    WRITERS.clear()


def big_traj(**changes) -> TrajectoryChunk:
    msg = make_traj(t=16, n=4, d=12, vision=True)
    return dataclasses.replace(msg, **changes) if changes else msg


def outcome(fn, *args, **kwargs):
    """('ok', message) or ('error', reason)."""
    try:
        return "ok", fn(*args, **kwargs)
    except CodecError as err:
        return "error", err.reason


def assert_bitwise_same(a, b) -> None:
    """Field by field, arrays compared as bytes (a mutated float may be NaN)."""
    assert type(a) is type(b)
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, dict):
            assert list(x) == list(y), f.name
            pairs = [(x[k], y[k]) for k in x]
        else:
            pairs = [(x, y)]
        for u, v in pairs:
            if isinstance(u, np.ndarray):
                assert u.dtype == v.dtype and u.shape == v.shape and u.tobytes() == v.tobytes(), f.name
            else:
                assert type(u) is type(v) and u == v, f.name


def assert_same_outcome(fast, full) -> None:
    assert fast[0] == full[0], (fast, full)
    if fast[0] == "ok":
        assert_bitwise_same(fast[1], full[1])
    else:
        assert fast[1] == full[1]


def no_full_walkers(monkeypatch) -> None:
    """From here on, only the layouts can encode or decode."""

    def refuse(*_a, **_k):
        raise AssertionError("the full codec ran: the fast path was not taken")

    monkeypatch.setattr(codec, "_read_top", refuse)
    monkeypatch.setattr(codec, "_write", refuse)


# ----------------------------------------------------------------------------- decoding

def test_a_primed_layout_decodes_without_the_full_decoder(monkeypatch):
    first = encode(big_traj())
    assert len(first) >= LAYOUT_MIN_BYTES
    decode(first)  # learns the layout
    other = big_traj(seq=99, policy_version=5, rollout="rollout-9", created_ns=1_800_000_000_000_000_000)
    rng = np.random.default_rng(3)
    other.actions[...] = rng.standard_normal(other.actions.shape)
    raw = encode(other)
    assert len(raw) == len(first)
    no_full_walkers(monkeypatch)
    got = decode(raw, expect=TrajectoryChunk)
    assert_same(got, other)
    assert got.rollout == "rollout-9" and got.seq == 99 and got.policy_version == 5
    # zero-copy, as with the full decoder
    assert np.shares_memory(got.actions, np.frombuffer(raw, np.uint8))


def test_the_fast_path_builds_a_frozen_message_like_the_constructor(monkeypatch):
    raw = encode(big_traj(seq=7))
    decode(raw)
    no_full_walkers(monkeypatch)
    got = decode(raw)
    assert type(got) is TrajectoryChunk and got.seq == 7
    assert vars(got).keys() == {f.name for f in dataclasses.fields(TrajectoryChunk)}
    with pytest.raises(dataclasses.FrozenInstanceError):
        got.seq = 8  # type: ignore[misc]


def test_only_a_store_only_init_is_bypassed():
    from dvla.fabric.layout import _plain_fields

    @dataclasses.dataclass(frozen=True)
    class Plain:
        a: int

    @dataclasses.dataclass(frozen=True)
    class Post:
        a: int

        def __post_init__(self) -> None:
            pass

    @dataclasses.dataclass(frozen=True)
    class Computed:
        a: int
        b: int = dataclasses.field(init=False, default=0)

    assert _plain_fields(Plain) == {"a"}
    assert _plain_fields(Post) is None and _plain_fields(Computed) is None
    assert _plain_fields(TrajectoryChunk) == {f.name for f in dataclasses.fields(TrajectoryChunk)}


def test_layouts_of_equal_length_coexist(monkeypatch):
    # seq 200 takes 2 bytes and policy_version 5 one; swapped, the length is the same but the
    # structure differs: two layouts under one length, each decoding its own messages.
    a, b = big_traj(seq=200, policy_version=5), big_traj(seq=5, policy_version=200)
    ra, rb = encode(a), encode(b)
    assert len(ra) == len(rb) and ra != rb
    decode(ra)
    decode(rb)
    no_full_walkers(monkeypatch)
    for _ in range(3):
        assert_same(decode(ra), a)
        assert_same(decode(rb), b)


def test_small_messages_and_other_limits_take_the_full_decoder():
    small = encode(make_traj())
    assert len(small) < LAYOUT_MIN_BYTES
    decode(small)
    assert not LAYOUTS.candidates(len(small))
    raw = encode(big_traj())
    decode(raw, limits=codec.Limits(max_str_len=1000))
    assert not LAYOUTS.candidates(len(raw))
    decode(raw)
    assert LAYOUTS.candidates(len(raw))


def test_value_checks_still_run_on_the_fast_path(monkeypatch):
    # env_steps must equal T*N; a forged value of the same width keeps the layout
    good = big_traj()
    raw = bytearray(encode(good))
    decode(bytes(raw))
    at = raw.index(b"\xa9env_steps") + len(b"\xa9env_steps")
    assert raw[at] == good.env_steps  # a positive fixint
    raw[at] = good.env_steps + 1
    no_full_walkers(monkeypatch)
    with pytest.raises(CodecError) as err:
        decode(bytes(raw))
    assert err.value.reason == "shape"


def test_expect_is_honoured_on_the_fast_path():
    raw = encode(big_traj())
    decode(raw)
    from dvla.fabric.messages import WeightChunk

    with pytest.raises(CodecError) as err:
        decode(raw, expect=WeightChunk)
    assert err.value.reason == "type"


def test_a_receivers_decoder_takes_the_layout_and_decodes_like_decode(monkeypatch):
    """`codec.decoder(cls)`: the receive threads' entry point. With a primed layout it builds
    without the full decoder; it honours the class; other input (a bytearray, a length with no
    layout) goes through `decode` with the same result."""
    from dvla.fabric.messages import WeightChunk

    want = big_traj(seq=41)
    raw = encode(want)
    traj, weights = codec.decoder(TrajectoryChunk), codec.decoder(WeightChunk)
    assert_same(traj(raw), want)  # no layout yet: learned on the way
    assert LAYOUTS.candidates(len(raw))
    assert_same(traj(bytearray(raw)), want)
    with pytest.raises(CodecError) as err:
        weights(raw)
    assert err.value.reason == "type"
    no_full_walkers(monkeypatch)
    got = traj(raw)
    assert_same(got, want)
    assert np.shares_memory(got.actions, np.frombuffer(raw, np.uint8))


BASE = encode(big_traj())


@FUZZ
@given(st.lists(st.tuples(st.integers(0, len(BASE) - 1), st.integers(0, 255)), min_size=1, max_size=6))
def test_mutated_bytes_decode_exactly_as_the_full_decoder_says(edits):
    LAYOUTS.clear()  # per example (the fixture runs once per test)
    decode(BASE)  # primed: every mutation of the same length meets the layout first
    mutated = bytearray(BASE)
    for pos, byte in edits:
        mutated[pos] = byte
    data = bytes(mutated)
    assert_same_outcome(outcome(decode, data), outcome(decode, data, layouts=False))
    full = outcome(decode, data, expect=TrajectoryChunk, layouts=False)
    assert_same_outcome(outcome(codec.decoder(TrajectoryChunk), data), full)


def _slot_offsets() -> list[int]:
    LAYOUTS.clear()
    decode(BASE)
    (layout,) = LAYOUTS.candidates(len(BASE))
    return [off for kind, _name, _key, off, _arg in layout.slots if kind != 6]  # every scalar/str slot


@FUZZ
@given(st.data())
def test_mutated_scalar_slots_decode_exactly_as_the_full_decoder_says(data):
    # Aim at the bytes the fast path reads instead of comparing: type bytes of fixints and
    # bools, integer payloads, string characters (invalid UTF-8 included).
    offsets = _slot_offsets()
    mutated = bytearray(BASE)
    for _ in range(data.draw(st.integers(1, 3))):
        off = data.draw(st.sampled_from(offsets)) + data.draw(st.integers(0, 3))
        mutated[off % len(mutated)] = data.draw(st.sampled_from([0x00, 0x7F, 0x80, 0xC2, 0xC3, 0xE0, 0xFF, 0xCC]))
    raw = bytes(mutated)
    assert_same_outcome(outcome(decode, raw), outcome(decode, raw, layouts=False))
    full = outcome(decode, raw, expect=TrajectoryChunk, layouts=False)
    assert_same_outcome(outcome(codec.decoder(TrajectoryChunk), raw), full)


# ----------------------------------------------------------------------------- encoding

def test_a_primed_layout_encodes_without_the_full_encoder(monkeypatch):
    out = bytearray()
    encode_into(big_traj(), out)
    want = [big_traj(seq=s, policy_version=s // 3, rollout=f"rollout-{s % 10}") for s in (0, 7, 127)]
    expected = [encode(m) for m in want]
    no_full_walkers(monkeypatch)
    for msg, wire in zip(want, expected):
        n = encode_into(msg, out)
        assert n == len(wire) and bytes(out) == wire


@pytest.mark.parametrize(
    "change",
    [
        lambda m: dataclasses.replace(m, seq=np.int64(m.seq)),  # numpy scalar: full encoder normalises
        lambda m: dataclasses.replace(m, seq=300),  # another width
        lambda m: dataclasses.replace(m, rollout="r"),  # another string length
        lambda m: dataclasses.replace(m, actions=m.actions.astype(">f4")),  # big-endian
        lambda m: dataclasses.replace(m, actions=np.asfortranarray(m.actions)),  # not C-contiguous
        lambda m: dataclasses.replace(m, obs=dict(reversed(list(m.obs.items())))),  # key order
        lambda m: dataclasses.replace(m, rewards=m.rewards[:, :2].copy()),  # invalid shape
        lambda m: dataclasses.replace(m, env_steps=m.env_steps + 1),  # invalid value, same width
        lambda m: dataclasses.replace(m, seq=-1),  # invalid value
    ],
    ids=["np-int", "width", "str-len", "big-endian", "fortran", "key-order", "bad-shape", "bad-value", "neg-seq"],
)
def test_anything_else_is_encoded_exactly_as_the_full_encoder_does(change):
    out = bytearray()
    base = big_traj()
    encode_into(base, out)
    assert WRITERS.candidates(TrajectoryChunk)
    msg = change(base)
    full = outcome(encode, msg)
    fast = outcome(lambda: (encode_into(msg, out), bytes(out))[1])
    assert fast[0] == full[0]
    assert fast[1] == full[1]


@FUZZ
@given(
    st.integers(1, 24), st.integers(1, 6), st.integers(1, 40), st.booleans(),
    st.lists(st.tuples(st.integers(0, 2**40), st.integers(0, 2**20), st.text(min_size=1, max_size=12)), min_size=1,
             max_size=4),
)
def test_encode_into_matches_encode_for_any_chunk(t, n, d, vision, variants):
    out = bytearray()
    base = make_traj(t=t, n=n, d=d, vision=vision)
    for seq, version, name in variants:
        msg = dataclasses.replace(base, seq=seq, policy_version=version, rollout=name)
        try:
            wire = encode(msg)
        except CodecError:
            continue
        assert encode_into(msg, out) == len(wire) and bytes(out) == wire
        assert_bitwise_same(decode(bytes(out)), decode(wire, layouts=False))


# --------------------------------------------------------------------------------------------
# The C helper itself (dvla/fabric/_views.c)


def test_the_c_helper_is_built_wherever_a_compiler_is():
    import shutil
    import sysconfig

    if shutil.which(sysconfig.get_config_var("CC").split()[0] or "cc") is None:
        pytest.skip("no C compiler: dvla runs the Python views")
    from dvla.fabric import _views  # noqa: F401  (an ImportError here: the build skipped it)


def _c():
    views = pytest.importorskip("dvla.fabric._views").views
    f4, u1 = np.dtype("<f4"), np.dtype("u1")
    data = b"HEAD" + np.arange(6, dtype=f4).tobytes() + b"MID" + bytes([1, 2, 3])
    spans = ((0, b"HEAD"), (28, b"MID"))
    arrays = ((4, f4, (2, 3)), (31, u1, (3,)))
    return views, data, spans, arrays


def test_c_views_check_spans_and_view_the_arrays_without_copying():
    views, data, spans, arrays = _c()
    a, b = views(data, spans, arrays)
    np.testing.assert_array_equal(a, np.arange(6, dtype="<f4").reshape(2, 3))
    np.testing.assert_array_equal(b, [1, 2, 3])
    assert a.base is data and not a.flags.writeable and a.flags.c_contiguous
    assert views(data[:0] + b"HEAX" + data[4:], spans, arrays) is None  # a span differs
    assert views(data[:30], spans, arrays) is None  # a span runs past the end
    wb = bytearray(data)
    a, _b = views(wb, spans, arrays)
    a[0, 0] = 42.0  # writable views of a writable buffer
    assert np.frombuffer(wb, "<f4", 1, 4)[0] == 42.0
    with pytest.raises(BufferError):
        wb.extend(b"x")  # pinned while a view lives
    del a, _b
    wb.extend(b"x")


@pytest.mark.parametrize("spans, arrays, error", [
    (((0, "HEAD"),), (), TypeError),
    (((0,),), (), TypeError),
    ((), ((4, "f4", (2, 3)),), TypeError),
    ((), ((30, np.dtype("<f4"), (2, 3)),), ValueError),  # beyond the end
    ((), ((-1, np.dtype("u1"), (1,)),), ValueError),
    ((), ((0, np.dtype("u1"), (-1,)),), ValueError),
    ((), ((0, np.dtype("u1"), (2**62, 2**62)),), ValueError),  # size overflows
])
def test_c_views_refuse_bad_specs_with_an_error_not_a_crash(spans, arrays, error):
    views, data, _s, _a = _c()
    with pytest.raises(error):
        views(data, spans, arrays)

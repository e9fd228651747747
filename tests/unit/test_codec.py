"""Tests of dvla.fabric.codec and the message types: round trips, zero-copy, wire
compatibility with a stock msgpack decoder, and rejection of hostile input (only CodecError,
no large allocations)."""

from __future__ import annotations

import dataclasses
import re
import struct
import tracemalloc

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dvla.fabric.codec import (
    ARRAY_ALIGN,
    ARRAY_EXT_CODE,
    DEFAULT_LIMITS,
    DTYPES,
    SCHEMA_VERSION,
    CodecError,
    Limits,
    decode,
    encode,
    encode_into,
)
from dvla.fabric.errors import FabricError
from dvla.fabric.messages import (
    MESSAGE_TYPES,
    Command,
    EvalResult,
    LedgerRecord,
    Receipt,
    ReceiptRequest,
    RoleStatus,
    SnapshotRequest,
    TrajectoryChunk,
    WeightChunk,
    WeightManifest,
    WeightSnapshot,
)

FUZZ = settings(max_examples=150, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])


# ----------------------------------------------------------------------------- builders

def make_traj(t: int = 4, n: int = 3, d: int = 5, a: int = 2, *, seed: int = 0, vision: bool = False) -> TrajectoryChunk:
    rng = np.random.default_rng(seed)
    if vision:
        obs = {
            "rgb": rng.integers(0, 255, (t, n, 8, 6, 3), dtype=np.uint8),
            "tokens": rng.integers(0, 1000, (t, n, 7), dtype=np.int32),
            "state": rng.standard_normal((t, n, d)).astype(np.float32),
        }
    else:
        obs = {"state": rng.standard_normal((t, n, d)).astype(np.float32)}
    done = rng.random((t, n)) < 0.2
    return TrajectoryChunk(
        rollout="rollout-0",
        seq=7,
        policy_version=12,
        env_steps=t * n,
        obs=obs,
        actions=rng.standard_normal((t, n, a)).astype(np.float32),
        logprobs=rng.standard_normal((t, n)).astype(np.float32),
        rewards=rng.standard_normal((t, n)).astype(np.float32),
        terminated=done,
        truncated=rng.random((t, n)) < 0.1,
        success=done & (rng.random((t, n)) < 0.5),
        next_obs={k: v[-1].copy() if t else np.zeros(v.shape[1:], v.dtype) for k, v in obs.items()},
        final_obs={k: np.where(done.reshape(done.shape + (1,) * (v.ndim - 2)), v, 0).astype(v.dtype) for k, v in obs.items()},
        created_ns=1_700_000_000_000_000_000,
    )


def control_messages() -> list:
    return [
        WeightManifest(sender="actor", version=5, base_version=-1, encoding="full", layout_hash="ab12",
                       n_chunks=3, total_bytes=3000, checksum="deadbeef", created_ns=123),
        WeightChunk(sender="actor", version=5, index=2, n_chunks=3, data=bytes(range(256)) * 4),
        Command(target="all", verb="checkpoint", args={"path": "/tmp/x", "n": 3, "nested": {"ok": True, "l": [1, 2.5, None]}},
                issued_ns=99),
        RoleStatus(name="rollout-0", kind="rollout", node="n1", rack="r1", pid=4242, state="running",
                   policy_version=7, env_steps=10_000, steps_per_s=1234.5,
                   lanes={"traj": {"lag_s": 0.25, "mbps": 12.0}}, planes={"data": {"rx": 10, "drop": 0}},
                   extra={"gpu": "A100", "mem_gb": 3.5, "flags": [1, "two"], "deep": {"a": {"b": -1}}}, time_ns=5),
        EvalResult(sender="evaluator-0", policy_version=9, episodes=50, success_once=0.5, success_at_end=0.25,
                   return_mean=-3.25, time_ns=6),
        SnapshotRequest(requester="rollout-3", have_version=-1),
        WeightSnapshot(sender="actor", version=4, manifest=b"\x01" * 40, n_chunks=3, created_ns=7),
        LedgerRecord(role="robot-1", incarnation=2, pid=77,
                     record='{"role":"robot-1","incarnation":2,"pid":77,"kind":"rollout","shipped":5}'),
        ReceiptRequest(rollout="rollout-3", seq=(2 << 32) + 17),
        Receipt(rollout="rollout-3", seq=-1),
    ]


def array_ext(arr: np.ndarray, *, dtype_name: str | None = None, shape: tuple | None = None, pad: int = 0,
              data: bytes | None = None, code: int = ARRAY_EXT_CODE) -> msgpack.ExtType:
    """An array ext built independently of the codec (from the documented layout)."""
    name = (dtype_name or arr.dtype.name).encode()
    shape = arr.shape if shape is None else shape
    header = bytes([len(name)]) + name + bytes([len(shape)]) + struct.pack(f"<{len(shape)}I", *shape)
    raw = arr.astype(arr.dtype.newbyteorder("<")).tobytes() if data is None else data
    return msgpack.ExtType(code, header + bytes([pad]) + bytes(pad) + raw)


def wire(body: dict, tag: str = "snapshot.req", v=SCHEMA_VERSION) -> bytes:
    """A message packed by stock msgpack (independent of the codec's encoder)."""
    return msgpack.packb({"v": v, "t": tag, "b": body}, use_bin_type=True)


def traj_body(msg: TrajectoryChunk) -> dict:
    def conv(value):
        if isinstance(value, np.ndarray):
            return array_ext(value)
        if isinstance(value, dict):
            return {k: conv(v) for k, v in value.items()}
        return value

    return {f.name: conv(getattr(msg, f.name)) for f in dataclasses.fields(msg)}


def reference_decode(buf: bytes) -> dict:
    """Decode with stock msgpack + the documented array header: what a foreign client would do."""
    def ext_hook(code: int, payload: bytes):
        assert code == ARRAY_EXT_CODE
        n = payload[0]
        name = payload[1:1 + n].decode()
        ndim = payload[1 + n]
        p = 2 + n
        shape = struct.unpack_from(f"<{ndim}I", payload, p)
        p += 4 * ndim
        p += 1 + payload[p]
        return np.frombuffer(payload, DTYPES[name], offset=p).reshape(shape)

    return msgpack.unpackb(buf, ext_hook=ext_hook, raw=False)


def assert_same(a, b) -> None:
    assert type(a) is type(b)
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), f.name
        elif isinstance(x, dict) and x and all(isinstance(v, np.ndarray) for v in x.values()):
            assert x.keys() == y.keys(), f.name
            for k in x:
                assert x[k].dtype == y[k].dtype and np.array_equal(x[k], y[k]), (f.name, k)
        else:
            assert x == y, f.name


def arrays_of(msg: TrajectoryChunk):
    for f in dataclasses.fields(msg):
        value = getattr(msg, f.name)
        if isinstance(value, np.ndarray):
            yield f.name, value
        elif isinstance(value, dict):
            for k, v in value.items():
                yield f"{f.name}[{k}]", v


def reasons_only(fn, *args, **kwargs) -> str | None:
    """Run fn; return the CodecError reason, None on success; any other exception fails the test."""
    try:
        fn(*args, **kwargs)
    except CodecError as err:
        assert isinstance(err, ValueError) and isinstance(err, FabricError)
        assert err.reason in {"malformed", "schema", "type", "oversize", "shape"}
        return err.reason
    return None


# Golden vectors: the same bytes are shown in docs/wire-format.md.
GOLDEN_ARRAY_MSG = Command(target="all", verb="pause", args={"x": np.array([1.0, 2.0], np.float32)}, issued_ns=1)
GOLDEN_ARRAY_HEX = (
    "83a17603a174a3636d64a16284a6746172676574a3616c6ca476657262a57061757365a46172677381a178c71a0107666c"
    "6f61743332010200000004000000000000803f00000040a96973737565645f6e7301"
)
GOLDEN_TRAJ = TrajectoryChunk(
    rollout="r0", seq=0, policy_version=1, env_steps=1,
    obs={"state": np.array([[[0.5, -1.0]]], np.float32)},
    actions=np.array([[[0.25]]], np.float32), logprobs=np.array([[-0.5]], np.float32),
    rewards=np.array([[1.0]], np.float32), terminated=np.array([[True]]), truncated=np.array([[False]]),
    success=np.array([[True]]), next_obs={"state": np.array([[0.0, 0.0]], np.float32)},
    final_obs={"state": np.array([[[0.5, -1.0]]], np.float32)}, created_ns=1_700_000_000_000_000_000,
)
GOLDEN_TRAJ_HEX = (
    "83a17603a174a47472616aa1628fa7726f6c6c6f7574a27230a373657100ae706f6c6963795f76657273696f6e01a9656e"
    "765f737465707301a36f627381a57374617465c7210107666c6f6174333203010000000100000002000000030000000000"
    "003f000080bfa7616374696f6e73c7210107666c6f61743332030100000001000000010000000700000000000000000080"
    "3ea86c6f6770726f6273c71c0107666c6f6174333202010000000100000006000000000000000000bfa772657761726473"
    "c71d0107666c6f6174333202010000000100000007000000000000000000803faa7465726d696e61746564c7170104626f"
    "6f6c020100000001000000070000000000000001a97472756e6361746564c7130104626f6f6c0201000000010000000300"
    "000000a773756363657373c7150104626f6f6c02010000000100000005000000000001a86e6578745f6f627381a5737461"
    "7465c71c0107666c6f617433320201000000020000000200000000000000000000a966696e616c5f6f627381a573746174"
    "65c7240107666c6f6174333203010000000100000002000000060000000000000000003f000080bfa665787472617380aa"
    "637265617465645f6e73cf17979cfe362a0000"
)


# ----------------------------------------------------------------------------- round trips

@pytest.mark.parametrize("msg", control_messages(), ids=lambda m: type(m).__name__)
def test_control_messages_round_trip(msg):
    buf = encode(msg)
    out = decode(buf)
    assert out == msg
    assert decode(buf, expect=type(msg)) == msg
    assert isinstance(buf, bytes)


def test_every_message_type_is_covered():
    covered = {type(m) for m in control_messages()} | {TrajectoryChunk}
    assert covered == set(MESSAGE_TYPES.values())


@pytest.mark.parametrize("vision", [False, True])
def test_trajectory_round_trip_is_zero_copy(vision):
    msg = make_traj(vision=vision)
    buf = encode(msg)
    out = decode(buf, expect=TrajectoryChunk)
    assert_same(msg, out)
    whole = np.frombuffer(buf, np.uint8)
    for name, arr in arrays_of(out):
        assert np.shares_memory(arr, whole), name
        assert not arr.flags.writeable, name  # bytes input: read-only views
    assert out.horizon == 4 and out.num_envs == 3


def test_encode_into_reuses_one_buffer_for_messages_of_any_size():
    buf = bytearray(b"stale" * 10_000)
    for msg in (make_traj(vision=True), make_traj(), make_traj(vision=True)):
        n = encode_into(msg, buf)
        assert n == len(buf) and bytes(buf) == encode(msg)
        assert_same(msg, decode(buf, expect=TrajectoryChunk))
    with pytest.raises(CodecError):
        encode_into(make_traj(), buf, Limits(max_message_bytes=64))


def test_array_data_is_aligned_within_message():
    msg = make_traj(vision=True)
    buf = bytearray(encode(msg))  # bytearray: views stay into this object
    base = np.frombuffer(buf, np.uint8).ctypes.data
    out = decode(buf)
    for name, arr in arrays_of(out):
        assert (arr.ctypes.data - base) % ARRAY_ALIGN == 0, name


def test_decode_accepts_memoryview_and_bytearray():
    msg = make_traj()
    buf = encode(msg)
    for form in (memoryview(buf), bytearray(buf), memoryview(bytearray(buf))):
        assert_same(msg, decode(form))
    # Zero-copy into a memoryview of a larger receive buffer.
    rx = bytearray(b"\0" * 3 + buf + b"\0" * 5)
    out = decode(memoryview(rx)[3:3 + len(buf)])
    assert np.shares_memory(out.actions, np.frombuffer(rx, np.uint8))


@pytest.mark.parametrize("dtype", sorted(DTYPES))
def test_every_allowed_dtype_round_trips(dtype):
    arr = (np.arange(24) % 7).astype(dtype).reshape(2, 3, 4)
    msg = RoleStatus(name="x", kind="k", node="n", rack="r", pid=1, state="running", policy_version=0,
                     env_steps=0, steps_per_s=0.0, extra={"a": arr, "scalar": np.array(3, dtype=dtype)}, time_ns=0)
    out = decode(encode(msg))
    assert out.extra["a"].dtype == np.dtype(dtype) and np.array_equal(out.extra["a"], arr)
    scalar = np.array(3, dtype=dtype)
    assert out.extra["scalar"].shape == () and out.extra["scalar"] == scalar


def test_strided_big_endian_and_empty_arrays_encode_correctly():
    base = make_traj(t=4, n=3, d=6)
    strided = np.asfortranarray(base.obs["state"])
    swapped = base.actions.astype(">f4")
    msg = dataclasses.replace(base, actions=swapped, obs={"state": strided})
    out = decode(encode(dataclasses.replace(msg, actions=swapped.astype("<f4"))))
    assert np.array_equal(out.obs["state"], base.obs["state"])
    with pytest.raises(CodecError) as err:  # validate: actions must be float32 (native), >f4 is not
        encode(msg)
    assert err.value.reason == "type"
    fortran_swapped = np.asfortranarray(base.obs["state"]).astype(">f4", order="F")
    out = decode(encode(RoleStatus(name="x", kind="k", node="n", rack="r", pid=1, state="running", policy_version=0,
                                   env_steps=0, steps_per_s=0.0, extra={"a": fortran_swapped}, time_ns=0)))
    assert out.extra["a"].dtype == np.dtype("<f4") and np.array_equal(out.extra["a"], base.obs["state"])
    empty = make_traj(t=0, n=3)
    out = decode(encode(empty))
    assert out.actions.shape == (0, 3, 2) and out.env_steps == 0


def test_numpy_scalars_are_accepted_on_encode():
    msg = EvalResult(sender="e", policy_version=np.int64(3), episodes=np.int32(5), success_once=np.float32(0.5),
                     success_at_end=1, return_mean=np.float64(2.0), time_ns=1)
    out = decode(encode(msg))
    assert out.policy_version == 3 and type(out.policy_version) is int
    assert out.success_once == 0.5 and type(out.success_at_end) is float


def test_stock_msgpack_reads_the_encoding():
    msg = make_traj(vision=True)
    top = reference_decode(encode(msg))
    assert top["v"] == SCHEMA_VERSION and top["t"] == "traj"
    assert np.array_equal(top["b"]["obs"]["rgb"], msg.obs["rgb"])
    assert np.array_equal(top["b"]["success"], msg.success)
    assert top["b"]["rollout"] == "rollout-0"


def test_codec_reads_stock_msgpack_output():
    msg = make_traj(vision=True)
    out = decode(wire(traj_body(msg), tag="traj"))  # unaligned, no padding, minimal msgpack forms
    assert_same(msg, out)


def test_golden_bytes():
    # Pinned wire bytes (also shown in docs/wire-format.md); a change here is a wire break.
    buf = encode(SnapshotRequest(requester="r0", have_version=3))
    assert buf.hex() == ("83a17603a174ac736e617073686f742e726571a16282a9726571756573746572a27230"
                         "ac686176655f76657273696f6e03")
    assert encode(GOLDEN_ARRAY_MSG).hex() == GOLDEN_ARRAY_HEX
    assert encode(GOLDEN_TRAJ).hex() == GOLDEN_TRAJ_HEX
    assert_same(decode(bytes.fromhex(GOLDEN_TRAJ_HEX)), GOLDEN_TRAJ)


# ----------------------------------------------------------------------------- schema errors

def test_wrong_schema_version_and_unknown_tag():
    body = {"requester": "r", "have_version": 1}
    assert decode(wire(body)) == SnapshotRequest(requester="r", have_version=1)
    assert reasons_only(decode, wire(body, v=2)) == "schema"  # the previous schema
    assert reasons_only(decode, wire(body, v=4)) == "schema"
    assert reasons_only(decode, wire(body, v=True)) == "schema"
    assert reasons_only(decode, wire(body, v="1")) == "schema"
    assert reasons_only(decode, wire(body, tag="nope")) == "schema"
    assert reasons_only(decode, wire(body, tag=5)) == "schema"


def test_missing_extra_and_mistyped_fields():
    assert reasons_only(decode, wire({"requester": "r"})) == "schema"
    assert reasons_only(decode, wire({"requester": "r", "have_version": 1, "x": 0})) == "schema"
    assert reasons_only(decode, wire({"requester": 1, "have_version": 1})) == "type"
    assert reasons_only(decode, wire({"requester": "r", "have_version": "1"})) == "type"
    assert reasons_only(decode, wire({"requester": "r", "have_version": True})) == "type"
    assert reasons_only(decode, wire({"requester": "r", "have_version": 1.5})) == "type"
    assert reasons_only(decode, wire({"requester": b"r", "have_version": 1})) == "type"


def test_nested_field_types_are_checked():
    status = control_messages()[3]
    body = {f.name: getattr(status, f.name) for f in dataclasses.fields(status)}
    assert decode(wire(body, tag="status")) == status
    for field, bad in (("lanes", {"a": {"b": "x"}}), ("lanes", {"a": 1.0}), ("planes", {"a": 3}),
                       ("extra", [1]), ("steps_per_s", "fast"), ("pid", None)):
        assert reasons_only(decode, wire({**body, field: bad}, tag="status")) == "type", field
    # float fields accept integers written by other encoders
    assert decode(wire({**body, "steps_per_s": 3}, tag="status")).steps_per_s == 3.0


def test_top_level_shape_errors():
    assert reasons_only(decode, msgpack.packb([1, "traj", {}])) == "schema"
    assert reasons_only(decode, msgpack.packb({"v": 2, "t": "cmd"})) == "schema"
    assert reasons_only(decode, msgpack.packb({"v": 2, "t": "cmd", "b": {}, "x": 1})) == "schema"
    assert reasons_only(decode, msgpack.packb({"v": 2, "t": "cmd", "b": [1]})) == "schema"
    assert reasons_only(decode, msgpack.packb({1: 1})) == "schema"
    assert reasons_only(decode, encode(control_messages()[0]) + b"\x00") == "malformed"
    assert reasons_only(decode, b"") == "malformed"
    assert reasons_only(decode, b"\xc1") == "malformed"


def test_duplicate_keys_are_rejected():
    buf = b"\x84\xa1v\x01\xa1t\xa3cmd\xa1b\x80\xa1v\x01"
    assert reasons_only(decode, buf) == "schema"


def test_expect_filters_types():
    buf = encode(SnapshotRequest(requester="r", have_version=1))
    assert reasons_only(decode, buf, expect=TrajectoryChunk) == "type"
    assert reasons_only(decode, buf, expect=(Command, SnapshotRequest)) is None


@pytest.mark.parametrize("bad", ["text", 12, None, [1, 2], object()])
def test_non_bytes_input(bad):
    assert reasons_only(decode, bad) == "malformed"


def test_value_invariants_are_checked():
    assert reasons_only(decode, wire({"target": "all", "verb": "explode", "args": {}, "issued_ns": 1}, tag="cmd")) == "schema"
    base = control_messages()[1]
    assert reasons_only(encode, dataclasses.replace(base, index=3)) == "schema"
    assert reasons_only(encode, dataclasses.replace(control_messages()[3], state="dancing")) == "schema"


# ----------------------------------------------------------------------------- trajectory validation

@pytest.mark.parametrize(
    "change, reason",
    [
        (lambda m: {"rewards": m.rewards[:-1]}, "shape"),
        (lambda m: {"logprobs": m.logprobs[:, :-1]}, "shape"),
        (lambda m: {"terminated": m.terminated.astype(np.uint8)}, "type"),
        (lambda m: {"actions": m.actions.astype(np.float64)}, "type"),
        (lambda m: {"actions": m.actions[..., 0]}, "shape"),
        (lambda m: {"env_steps": m.env_steps + 1}, "shape"),
        (lambda m: {"seq": -1}, "schema"),
        (lambda m: {"obs": {"state": m.obs["state"][:, :-1]}}, "shape"),
        (lambda m: {"next_obs": {"state": m.next_obs["state"][:-1]}}, "shape"),
        (lambda m: {"next_obs": {}}, "schema"),
        (lambda m: {"final_obs": {"state": m.final_obs["state"], "x": m.final_obs["state"]}}, "schema"),
        (lambda m: {"final_obs": {"state": m.final_obs["state"].astype(np.float16)}}, "type"),
        (lambda m: {"obs": {}, "next_obs": {}, "final_obs": {}}, "schema"),
        (lambda m: {"obs": {"state": m.obs["state"][0, 0]}}, "shape"),
    ],
)
def test_trajectory_inconsistencies_are_rejected_on_both_sides(change, reason):
    good = make_traj()
    bad = dataclasses.replace(good, **change(good))
    assert reasons_only(bad.validate) == reason
    assert reasons_only(encode, bad) == reason
    assert reasons_only(decode, wire(traj_body(bad), tag="traj")) == reason


def test_non_array_fields_are_type_errors():
    good = make_traj()
    assert reasons_only(encode, dataclasses.replace(good, actions=good.actions.tolist())) == "type"
    body = traj_body(good)
    body["actions"] = good.actions.tolist()
    assert reasons_only(decode, wire(body, tag="traj")) == "type"
    body = traj_body(good)
    body["obs"] = {"state": 1.0}
    assert reasons_only(decode, wire(body, tag="traj")) == "type"


def test_disallowed_dtypes():
    good = make_traj()
    for dtype in (np.complex64, np.uint16, np.uint64, "datetime64[ns]", object):
        obs = {"state": np.zeros((4, 3, 2), dtype=dtype)}
        msg = dataclasses.replace(good, obs=obs, next_obs={"state": obs["state"][0]}, final_obs=obs)
        assert reasons_only(encode, msg) == "type", dtype
    body = traj_body(good)
    body["obs"] = {"state": array_ext(good.obs["state"], dtype_name="uint16")}
    assert reasons_only(decode, wire(body, tag="traj")) == "type"
    body["obs"] = {"state": array_ext(good.obs["state"], code=2)}
    assert reasons_only(decode, wire(body, tag="traj")) == "type"


def test_declared_shape_must_match_payload():
    good = make_traj()
    body = traj_body(good)
    arr = good.obs["state"]
    body["obs"] = {"state": array_ext(arr, shape=(4, 3, 6))}
    assert reasons_only(decode, wire(body, tag="traj")) == "shape"
    body["obs"] = {"state": array_ext(arr, shape=(2**31, 2**31))}
    assert reasons_only(decode, wire(body, tag="traj")) == "shape"
    body["obs"] = {"state": array_ext(arr, shape=(2**32 - 1,) * 8)}
    assert reasons_only(decode, wire(body, tag="traj")) == "shape"
    body["obs"] = {"state": array_ext(arr, shape=(1,) * 9)}
    assert reasons_only(decode, wire(body, tag="traj")) == "oversize"
    body["obs"] = {"state": array_ext(arr, pad=3)}
    assert reasons_only(decode, wire(body, tag="traj")) is None  # padding is legal
    body["obs"] = {"state": array_ext(arr, pad=64)}
    assert reasons_only(decode, wire(body, tag="traj")) == "malformed"


# ----------------------------------------------------------------------------- limits

def test_limits_are_enforced_on_decode_and_encode():
    msg = make_traj(vision=True)
    buf = encode(msg)
    tight = {
        "max_message_bytes": len(buf) - 1,
        "max_array_bytes": msg.obs["rgb"].nbytes - 1,
        "max_ndim": 4,
        "max_str_len": 5,
        "max_map_len": 2,
        "max_depth": 2,
    }
    for name, value in tight.items():
        limits = Limits(**{name: value})
        assert reasons_only(decode, buf, limits=limits) == "oversize", name
        assert reasons_only(encode, msg, limits=limits) == "oversize", name
    cmd = Command(target="all", verb="stop", args={"l": list(range(10))})
    assert reasons_only(decode, encode(cmd), limits=Limits(max_list_len=9)) == "oversize"
    assert reasons_only(encode, cmd, limits=Limits(max_list_len=9)) == "oversize"
    assert DEFAULT_LIMITS.max_message_bytes == 256 * 2**20 and DEFAULT_LIMITS.max_ndim == 8


def test_deep_nesting_is_refused_without_recursion_error():
    body = {"target": "all", "verb": "stop", "issued_ns": 1}
    prefix = msgpack.packb({"v": 2, "t": "cmd", "b": body})[:-1]
    # rewrite the body map header to 4 entries and append args = [[[[...]]]] 100000 deep
    bomb = bytearray(prefix)
    bomb[bomb.index(b"\xa1b") + 2] = 0x84
    bomb += b"\xa4args" + b"\x91" * 100_000 + b"\xc0"
    assert reasons_only(decode, bytes(bomb)) == "oversize"
    nested: dict = {}
    cur = nested
    for _ in range(40):
        cur["x"] = {}
        cur = cur["x"]
    assert reasons_only(encode, Command(target="all", verb="stop", args=nested)) == "oversize"


def test_encode_rejects_unencodable_values():
    for args in ({"o": object()}, {1: 2}, {"big": 2**70}, {"s": "\ud800"}, {"set": {1}}):
        assert reasons_only(encode, Command(target="all", verb="stop", args=args)) == "type", args
    assert reasons_only(encode, "not a message") == "type"
    assert reasons_only(encode, WeightChunk(sender="a", version=1, index=0, n_chunks=1, data="str")) == "type"


FORGED_HEADERS = [
    b"\xdb\xff\xff\xff\xff",  # str32 of 4 GiB
    b"\xc6\xff\xff\xff\xff",  # bin32 of 4 GiB
    b"\xdd\xff\xff\xff\xff",  # array32 of 4G items
    b"\xdf\xff\xff\xff\xff",  # map32 of 4G entries
    b"\xc9\xff\xff\xff\xff\x01",  # ext32 of 4 GiB
    b"\xc9\x00\x00\x00\x1c\x01\x07float32\x02\x00\x00\x00\x80\x00\x00\x00\x80\x00",  # shape (2^31, 2^31)
    b"\xdd\x00\x10\x00\x00",  # array of 1M items, no data
]


@pytest.mark.parametrize("forged", FORGED_HEADERS, ids=range(len(FORGED_HEADERS)))
def test_forged_lengths_do_not_allocate(forged):
    prefix = b"\x83\xa1v\x01\xa1t\xa3cmd\xa1b\x84\xa6target\xa3all\xa4verb\xa4stop\xa9issued_ns\x01\xa4args"
    buf = prefix + forged + b"\x00" * 64
    tracemalloc.start()
    try:
        reason = reasons_only(decode, buf)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert reason in {"oversize", "malformed", "shape", "type", "schema"}
    assert peak < 64 * 1024, peak


def test_decode_allocates_nothing_per_array_byte():
    big = make_traj(t=16, n=32, d=2048)  # ~8 MiB of observations
    buf = encode(big)
    decode(buf)  # warm caches
    tracemalloc.start()
    try:
        out = decode(buf)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert np.shares_memory(out.obs["state"], np.frombuffer(buf, np.uint8))
    assert peak < 64 * 1024, peak


def test_encode_copies_array_bytes_once():
    big = make_traj(t=16, n=32, d=2048)
    encode(big)
    tracemalloc.start()
    try:
        buf = encode(big)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < len(buf) + 256 * 1024, (peak, len(buf))


# ----------------------------------------------------------------------------- fuzzing

VALID = [encode(make_traj(t=2, n=2, d=3, vision=True)), *[encode(m) for m in control_messages()]]


@FUZZ
@given(st.binary(max_size=512))
def test_fuzz_random_bytes(data):
    reasons_only(decode, data)


@FUZZ
@given(st.sampled_from(VALID), st.data())
def test_fuzz_truncations(buf, data):
    cut = data.draw(st.integers(0, len(buf) - 1))
    assert reasons_only(decode, buf[:cut]) is not None


@FUZZ
@given(st.sampled_from(VALID), st.lists(st.tuples(st.integers(0, 2**16), st.integers(0, 255)), min_size=1, max_size=8))
def test_fuzz_mutations(buf, edits):
    mutated = bytearray(buf)
    for pos, byte in edits:
        mutated[pos % len(mutated)] = byte
    reasons_only(decode, bytes(mutated))


@FUZZ
@given(st.sampled_from(VALID), st.integers(0, 2**16), st.binary(min_size=1, max_size=16))
def test_fuzz_insertions(buf, pos, junk):
    pos %= len(buf)
    reasons_only(decode, buf[:pos] + junk + buf[pos:])


@FUZZ
@given(st.sampled_from(VALID), st.lists(st.tuples(st.integers(0, 2**16), st.sampled_from([0x00, 0x7F, 0xC6, 0xC9, 0xDD,
                                                                                        0xDF, 0xFF])),
                                        min_size=1, max_size=6))
def test_fuzz_allocation_stays_bounded_by_the_input(buf, edits):
    # Mutations biased to length prefixes (bin32, ext32, array32, map32, 0xff bytes): whatever a
    # forged length claims, decoding allocates at most on the order of the input itself.
    mutated = bytearray(buf)
    for pos, byte in edits:
        mutated[pos % len(mutated)] = byte
    data = bytes(mutated)
    tracemalloc.start()
    try:
        reasons_only(decode, data)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 64 * 1024 + 2 * len(data), (peak, len(data))


msgpack_scalars = (st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=8)
                   | st.binary(max_size=8))
# Flat containers only: recursive strategies are slow to generate and add no new decoder paths.
msgpack_values = (msgpack_scalars | st.lists(msgpack_scalars, max_size=3)
                  | st.dictionaries(st.text(max_size=4) | st.integers(-(2**63), 2**63 - 1), msgpack_scalars, max_size=3))


@settings(FUZZ, max_examples=60)
@given(st.sampled_from(sorted(MESSAGE_TYPES)), st.dictionaries(st.text(max_size=12), msgpack_values, max_size=6),
       st.sampled_from([SCHEMA_VERSION, 0, 2, 4, "3", None]))
def test_fuzz_wrong_types(tag, body, version):
    reasons_only(decode, wire(body, tag=tag, v=version))


@FUZZ
@given(st.sampled_from(sorted(MESSAGE_TYPES)), st.sampled_from([m for m in control_messages()]), st.data())
def test_fuzz_field_swaps(tag, template, data):
    # Real field names with values taken from other fields/messages: mostly type errors.
    body = {f.name: getattr(template, f.name) for f in dataclasses.fields(template)}
    keys = list(body)
    a, b = data.draw(st.sampled_from(keys)), data.draw(st.sampled_from(keys))
    body[a], body[b] = body[b], body[a]
    reasons_only(decode, wire(body, tag=tag))


@settings(max_examples=60, deadline=None, database=None)
@given(
    t=st.integers(0, 5), n=st.integers(1, 4), a=st.integers(1, 3),
    obs_dtypes=st.lists(st.sampled_from(sorted(DTYPES)), min_size=1, max_size=3),
    trailing=st.lists(st.integers(0, 4), max_size=3), seed=st.integers(0, 2**16),
)
def test_fuzz_trajectory_round_trip(t, n, a, obs_dtypes, trailing, seed):
    rng = np.random.default_rng(seed)
    base = make_traj(t=t, n=n, a=a, seed=seed)
    obs = {f"o{i}": (rng.standard_normal((t, n, *trailing)) * 50).astype(dt) for i, dt in enumerate(obs_dtypes)}
    msg = dataclasses.replace(base, obs=obs, next_obs={k: v[0] if t else np.zeros((n, *trailing), v.dtype)
                                                        for k, v in obs.items()},
                              final_obs={k: np.zeros_like(v) for k, v in obs.items()})
    assert_same(msg, decode(encode(msg)))


def test_a_snapshot_header_holds_a_version_or_nothing():
    WeightSnapshot(sender="r", version=-1, manifest=b"", n_chunks=0).validate()  # nothing held yet
    WeightSnapshot(sender="r", version=4, manifest=b"", n_chunks=0).validate()  # up to date: header only
    for bad in (dict(version=-1, n_chunks=2), dict(version=-2, n_chunks=0), dict(version=4, n_chunks=-1)):
        with pytest.raises(CodecError):
            WeightSnapshot(sender="r", manifest=b"m", **bad).validate()


@pytest.mark.parametrize("role, record, why", [
    ("../x", '{"kind":"rollout","role":"../x","incarnation":0,"pid":1}', "not a valid key chunk"),
    ("robot-1", "not json", "not JSON"),
    ("robot-1", '{"kind":"actor","role":"robot-1","incarnation":0,"pid":1}', "not a rollout's counter record"),
    ("robot-1", '{"kind":"rollout","role":"robot-2","incarnation":0,"pid":1}', "record's role 'robot-2'"),
    ("robot-1", '{"kind":"rollout","role":"robot-1","incarnation":3,"pid":1}', "record's incarnation 3"),
])
def test_a_ledger_record_names_a_file_and_matches_its_record(role: str, record: str, why: str) -> None:
    with pytest.raises(FabricError, match=re.escape(why)):
        decode(wire({"role": role, "incarnation": 0, "pid": 1, "record": record}, tag="ledger"))

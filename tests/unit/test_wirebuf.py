"""WireBuffer (a message laid out in its wire bytes) and the rollout's ChunkPool."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from dvla.fabric import CodecError, TrajectoryChunk, WireBuffer, decode, encode
from dvla.roles.chunkpool import WIDE_FIELDS, ChunkPool, chunk_template


class _Spec:
    def __init__(self, shape: tuple[int, ...], dtype: type) -> None:
        self.shape, self.dtype = shape, np.dtype(dtype)


SPEC = {"state": _Spec((5,), np.float32), "rgb": _Spec((4, 4, 3), np.uint8)}


def template(T: int = 3, n: int = 2) -> TrajectoryChunk:
    return chunk_template("rollout-0", T, n, SPEC, act_dim=4)


def fill(wb: WireBuffer, seed: int) -> dict[str, np.ndarray]:
    """Write random data into every array of `wb` in place; returns what was written."""
    rng = np.random.default_rng(seed)
    m = wb.msg
    want = {
        "state": rng.standard_normal(m.obs["state"].shape, dtype=np.float32),
        "rgb": rng.integers(0, 256, m.obs["rgb"].shape, dtype=np.uint8),
        "actions": rng.standard_normal(m.actions.shape, dtype=np.float32),
        "success": rng.random(m.success.shape) < 0.5,
        "next_state": rng.standard_normal(m.next_obs["state"].shape, dtype=np.float32),
    }
    for t in range(m.actions.shape[0]):  # step by step, as the sim lane writes
        m.obs["state"][t] = want["state"][t]
        m.obs["rgb"][t] = want["rgb"][t]
        m.actions[t] = want["actions"][t]
        m.success[t] = want["success"][t]
    m.next_obs["state"][...] = want["next_state"]
    return want


@pytest.mark.parametrize("layouts", [False, True], ids=["full-decoder", "layout-decoder"])
@pytest.mark.parametrize("seq", [0, 1, 127, 2**32 + 5, 2**64 - 1])
def test_arrays_written_in_place_and_sealed_scalars_decode(layouts: bool, seq: int) -> None:
    wb = WireBuffer(template(), wide=WIDE_FIELDS)
    want = fill(wb, seed=seq % 1000)
    wb.seal(seq=seq, policy_version=7, created_ns=1_700_000_000_123_456_789)
    got = decode(bytes(wb.buf), expect=TrajectoryChunk, layouts=layouts)
    assert (got.seq, got.policy_version, got.created_ns) == (seq, 7, 1_700_000_000_123_456_789)
    assert got.rollout == "rollout-0" and got.env_steps == 6
    np.testing.assert_array_equal(got.obs["state"], want["state"])
    np.testing.assert_array_equal(got.obs["rgb"], want["rgb"])
    np.testing.assert_array_equal(got.actions, want["actions"])
    np.testing.assert_array_equal(got.success, want["success"])
    np.testing.assert_array_equal(got.next_obs["state"], want["next_state"])
    assert got.obs["rgb"].dtype == np.uint8 and got.success.dtype == np.bool_
    # Same message as the reference encoder's, only the three integers in their 64-bit forms.
    assert len(wb.buf) == wb.nbytes == len(encode(got)) + sum(9 - len(encode_int(v)) for v in (seq, 7, got.created_ns))


def encode_int(v: int) -> bytes:
    import msgpack

    return msgpack.packb(v)


def test_a_reused_buffer_carries_each_new_chunk_and_keeps_its_size() -> None:
    wb = WireBuffer(template(), wide=WIDE_FIELDS)
    n = wb.nbytes
    for i in range(3):
        want = fill(wb, seed=i)
        wb.seal(seq=i, policy_version=i, created_ns=time.time_ns())
        got = decode(bytes(wb.buf), expect=TrajectoryChunk)
        assert got.seq == i and len(wb.buf) == n
        np.testing.assert_array_equal(got.actions, want["actions"])
    assert wb.message().seq == 2  # the receiver's view of the current bytes


@pytest.mark.parametrize("values, what", [
    ({"seq": -1}, "does not fit"),
    ({"seq": 2**64}, "does not fit"),
    ({"policy_version": 1.5}, "expected int"),
    ({"policy_version": True}, "expected int"),
    ({"rollout": 3}, "not a wide field"),
    ({"env_steps": 4}, "not a wide field"),
])
def test_seal_refuses_values_that_do_not_fit_and_fields_that_are_not_wide(values: dict, what: str) -> None:
    wb = WireBuffer(template(), wide=WIDE_FIELDS)
    before = bytes(wb.buf)
    with pytest.raises(CodecError, match=what):
        wb.seal(**values)
    assert bytes(wb.buf) == before


def test_construction_refuses_what_cannot_be_laid_out() -> None:
    with pytest.raises(CodecError, match="must be an int"):
        WireBuffer(template(), wide=("rollout",))
    with pytest.raises(CodecError, match="not a fabric message"):
        WireBuffer(object())  # type: ignore[arg-type]
    bad = TrajectoryChunk(**{**template().__dict__, "env_steps": 5})  # T*N is 6
    with pytest.raises(CodecError):
        WireBuffer(bad, wide=WIDE_FIELDS)


def test_chunk_pool_hands_out_each_buffer_once_and_stops_waiting_on_stop() -> None:
    pool = ChunkPool(template(), size=3)
    stop = threading.Event()
    taken = [pool.take(stop) for _ in range(3)]
    assert len({id(b) for b in taken}) == 3 and pool.free() == 0
    stop_timer = threading.Timer(0.2, stop.set)
    stop_timer.start()
    t0 = time.monotonic()
    assert pool.take(stop) is None  # every buffer is out: waits, then gives up on stop
    assert 0.15 < time.monotonic() - t0 < 2.0
    stop_timer.join()
    pool.give(taken[1])
    assert pool.take(threading.Event()) is taken[1]
    with pytest.raises(ValueError):
        ChunkPool(template(), size=0)

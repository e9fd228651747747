"""dvla.roles.actor.chunk_problem: a trajectory chunk is checked before it reaches the learner
(versions, then the run's ChunkSpec: T, N, observation keys, shapes and dtypes, finite floats,
token ids in the vocabulary)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dvla.fabric.codec import decode, encode
from dvla.fabric.messages import ArraySpec, ChunkSpec, TrajectoryChunk
from dvla.roles.actor import chunk_problem

T, N, A = 4, 2, 3
STATE = {"state": ArraySpec((5,), "float32")}
RGB = {"rgb": ArraySpec((8, 8, 3), "uint8"), "proprio": ArraySpec((4,), "float32"),
       "tokens": ArraySpec((6,), "int32", vocab=100)}


def run(obs=STATE, n: int = N) -> ChunkSpec:
    """The run's spec: chunks of T steps of up to n envs."""
    return ChunkSpec(obs=obs, act_dim=A, T=T, N=n)


def chunk(spec=STATE, version: int = 3, t: int = T, n: int = N, **changes) -> TrajectoryChunk:
    rng = np.random.default_rng(0)

    def arr(shape, s):
        if s.dtype == "float32":
            return rng.standard_normal(shape, dtype=np.float32)
        return rng.integers(0, s.vocab or 256, shape).astype(s.dtype)

    obs = {k: arr((t, n, *s.shape), s) for k, s in spec.items()}
    c = TrajectoryChunk(
        rollout="rollout-0", seq=7, policy_version=version, env_steps=t * n, obs=obs,
        actions=rng.standard_normal((t, n, A), dtype=np.float32),
        logprobs=rng.standard_normal((t, n), dtype=np.float32), rewards=rng.standard_normal((t, n), dtype=np.float32),
        terminated=np.zeros((t, n), bool), truncated=np.zeros((t, n), bool), success=np.zeros((t, n), bool),
        next_obs={k: arr((n, *s.shape), s) for k, s in spec.items()},
        final_obs={k: np.zeros((t, n, *s.shape), s.dtype) for k, s in spec.items()},
    )
    c = decode(encode(c))  # what ingest gets: arrays are read-only views of the received bytes
    return dataclasses.replace(c, **changes) if changes else c


def reason(c: TrajectoryChunk, spec=STATE, newest: int = 5) -> str | None:
    problem = chunk_problem(c, run(spec), newest)
    return None if problem is None else problem[0]


@pytest.mark.parametrize("spec", [STATE, RGB])
def test_a_sound_chunk_passes(spec) -> None:
    assert chunk_problem(chunk(spec), run(spec), 5) is None
    assert chunk_problem(chunk(spec, version=5), run(spec), 5) is None  # the newest released itself
    assert chunk_problem(chunk(spec, version=0), run(spec), 5) is None
    assert chunk_problem(chunk(spec, n=1), run(spec), 5) is None  # fewer envs than the most a chunk holds


def test_versions_no_actor_released_are_rejected() -> None:
    assert reason(chunk(version=6)) == "future_version"
    assert reason(chunk(version=2**62)) == "future_version"
    assert reason(chunk(version=-1)) == "negative_version"
    code, detail = chunk_problem(chunk(version=9), run(), 5)
    assert "9" in detail and "5" in detail


def test_chunks_must_have_the_runs_steps_and_at_most_its_envs() -> None:
    code, detail = chunk_problem(chunk(t=T + 1), run(), 5)
    assert code == "shape" and f"T={T + 1}" in detail and f"T={T}" in detail
    code, detail = chunk_problem(chunk(), run(n=N - 1), 5)
    assert code == "shape" and f"N={N}" in detail and f"N<={N - 1}" in detail


@pytest.mark.parametrize("field", ["rewards", "logprobs", "actions", "obs", "next_obs", "final_obs", "proprio"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_nonfinite_floats_are_rejected(field: str, bad: float) -> None:
    spec = RGB if field == "proprio" else STATE
    c = chunk(spec)
    if field in ("rewards", "logprobs", "actions"):
        arr = getattr(c, field).copy()
        arr.flat[arr.size // 2] = bad
        c = dataclasses.replace(c, **{field: arr})
    else:
        part = "obs" if field == "proprio" else field
        key = "proprio" if field == "proprio" else "state"
        arr = getattr(c, part)[key].copy()
        arr.flat[-1] = bad
        c = dataclasses.replace(c, **{part: {**getattr(c, part), key: arr}})
    code, detail = chunk_problem(c, run(spec), 5)
    assert code == "nonfinite" and (field in detail or "proprio" in detail)


def test_observations_must_match_the_runs_spec() -> None:
    assert reason(chunk(), spec={"state": ArraySpec((6,), "float32")}) == "shape"  # wrong per-env shape
    assert reason(chunk(), spec={"pixels": ArraySpec((5,), "float32")}) == "shape"  # wrong key
    assert reason(chunk(), spec={"state": ArraySpec((5,), "float16")}) == "shape"  # wrong dtype
    c = chunk(RGB)
    as_int = {part: {**getattr(c, part), "rgb": getattr(c, part)["rgb"].astype(np.int32)}
              for part in ("obs", "next_obs", "final_obs")}
    assert reason(decode(encode(dataclasses.replace(c, **as_int))), RGB) == "shape"  # images not uint8
    c = chunk()
    wide = np.zeros((T, N, A + 1), np.float32)
    assert reason(dataclasses.replace(c, actions=wide)) == "shape"
    spec = RGB
    c = chunk(spec)
    tokens = c.obs["tokens"].copy()
    tokens[0, 0, 0] = 100  # == vocab
    assert reason(dataclasses.replace(c, obs={**c.obs, "tokens": tokens}), spec) == "out_of_range"
    tokens[0, 0, 0] = -1
    assert reason(dataclasses.replace(c, obs={**c.obs, "tokens": tokens}), spec) == "out_of_range"
    nxt = c.next_obs["tokens"].copy()
    nxt[0, 0] = 10**6
    assert reason(dataclasses.replace(c, next_obs={**c.next_obs, "tokens": nxt}), spec) == "out_of_range"

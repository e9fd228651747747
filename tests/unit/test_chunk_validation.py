"""dvla.roles.actor.chunk_problem: the values of a trajectory chunk are checked before it reaches
the learner (versions, the run's observation spec, finite floats, token ids in the vocabulary)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dvla.fabric.codec import decode, encode
from dvla.fabric.messages import TrajectoryChunk
from dvla.learn.envs import ArraySpec
from dvla.roles.actor import chunk_problem

T, N, A = 4, 2, 3
STATE = {"state": ArraySpec((5,), "float32")}
RGB = {"rgb": ArraySpec((8, 8, 3), "uint8"), "proprio": ArraySpec((4,), "float32"),
       "tokens": ArraySpec((6,), "int32", vocab=100)}


def chunk(spec=STATE, version: int = 3, **changes) -> TrajectoryChunk:
    rng = np.random.default_rng(0)

    def arr(shape, s):
        if s.dtype == "float32":
            return rng.standard_normal(shape, dtype=np.float32)
        return rng.integers(0, s.vocab or 256, shape).astype(s.dtype)

    obs = {k: arr((T, N, *s.shape), s) for k, s in spec.items()}
    c = TrajectoryChunk(
        rollout="rollout-0", seq=7, policy_version=version, env_steps=T * N, obs=obs,
        actions=rng.standard_normal((T, N, A), dtype=np.float32),
        logprobs=rng.standard_normal((T, N), dtype=np.float32), rewards=rng.standard_normal((T, N), dtype=np.float32),
        terminated=np.zeros((T, N), bool), truncated=np.zeros((T, N), bool), success=np.zeros((T, N), bool),
        next_obs={k: arr((N, *s.shape), s) for k, s in spec.items()},
        final_obs={k: np.zeros((T, N, *s.shape), s.dtype) for k, s in spec.items()},
    )
    c = decode(encode(c))  # what ingest gets: arrays are read-only views of the received bytes
    return dataclasses.replace(c, **changes) if changes else c


def reason(c: TrajectoryChunk, spec=STATE, newest: int = 5) -> str | None:
    problem = chunk_problem(c, spec, A, newest)
    return None if problem is None else problem[0]


@pytest.mark.parametrize("spec", [STATE, RGB])
def test_a_sound_chunk_passes(spec) -> None:
    assert chunk_problem(chunk(spec), spec, A, 5) is None
    assert chunk_problem(chunk(spec, version=5), spec, A, 5) is None  # the newest released itself
    assert chunk_problem(chunk(spec, version=0), spec, A, 5) is None


def test_versions_no_actor_released_are_rejected() -> None:
    assert reason(chunk(version=6)) == "future_version"
    assert reason(chunk(version=2**62)) == "future_version"
    assert reason(chunk(version=-1)) == "negative_version"
    code, detail = chunk_problem(chunk(version=9), STATE, A, 5)
    assert "9" in detail and "5" in detail


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
    code, detail = chunk_problem(c, spec, A, 5)
    assert code == "nonfinite" and (field in detail or "proprio" in detail)


def test_observations_must_match_the_runs_spec() -> None:
    assert reason(chunk(), spec={"state": ArraySpec((6,), "float32")}) == "shape"  # wrong per-env shape
    assert reason(chunk(), spec={"pixels": ArraySpec((5,), "float32")}) == "shape"  # wrong key
    assert reason(chunk(), spec={"state": ArraySpec((5,), "float16")}) == "shape"  # wrong dtype
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

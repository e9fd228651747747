"""Typed messages exchanged between dvla processes.

One frozen, keyword-only dataclass per message, with a ``TYPE_TAG`` naming it on the wire and a
``validate()`` for invariants a type hint cannot express; :class:`ChunkSpec`, the one description
of a trajectory chunk's arrays. The bytes are :mod:`dvla.fabric.codec`'s (docs/wire-format.md).
Nothing here depends on the rest of dvla.

Field type hints are the schema the codec checks decoded values against: only ``str``, ``int``,
``float``, ``bool``, ``bytes``, ``np.ndarray``, ``dict[str, X]`` of those and ``dict[str, Any]``.
"""

from __future__ import annotations

import functools
import json
import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np

from dvla.fabric.errors import CodecError
from dvla.fabric.keys import check_name

COMMAND_VERBS = ("stop", "checkpoint", "pause", "resume", "revoke")
"""Verbs a :class:`Command` may carry."""

ROLE_STATES = ("starting", "running", "stopping", "error")
"""States a :class:`RoleStatus` may report."""


def _now_ns() -> int:
    return time.time_ns()


class Message:
    """Common base of every fabric message (not itself a wire type)."""

    TYPE_TAG: ClassVar[str] = ""

    def validate(self) -> None:
        """Raise :class:`CodecError` if the message breaks an invariant. Default: nothing to check."""


def _require(ok: bool, reason: str, detail: str) -> None:
    if not ok:
        raise CodecError(reason, detail)


@dataclass(frozen=True, kw_only=True, eq=False)
class TrajectoryChunk(Message):
    """T consecutive steps of N parallel environments, sent by a rollout to the learner.

    Arrays are time-major: ``[T, N, ...]``. Equality is identity (arrays make field-wise
    ``==`` ambiguous). What each array holds is :class:`ChunkSpec`'s to say.
    """

    TYPE_TAG: ClassVar[str] = "traj"

    #: name of the rollout role that produced the chunk
    rollout: str
    #: ``incarnation << 32 | index``: index counts one rollout process's chunks from 0 (gaps
    #: reveal lost chunks), incarnation its restarts (0 for the first process)
    seq: int
    #: version of the policy weights that chose the actions
    policy_version: int
    #: environment steps in this chunk, always T * N
    env_steps: int
    #: observations before each step, name -> [T, N, ...] (e.g. "state" float32 [T, N, D])
    obs: dict[str, np.ndarray]
    #: actions taken, float32 [T, N, A]
    actions: np.ndarray
    #: log-probability of each action under the acting policy, float32 [T, N]
    logprobs: np.ndarray
    #: rewards, float32 [T, N]
    rewards: np.ndarray
    #: episode ended by the task (success/failure), bool [T, N]
    terminated: np.ndarray
    #: episode ended by a time limit, bool [T, N]
    truncated: np.ndarray
    #: task success at this step, bool [T, N]
    success: np.ndarray
    #: observation after the last step, name -> [N, ...] (bootstrap value input)
    next_obs: dict[str, np.ndarray]
    #: observation before auto-reset where an episode ended at that step, zeros elsewhere;
    #: name -> [T, N, ...], same keys, shapes and dtypes as ``obs``
    final_obs: dict[str, np.ndarray]
    #: what the policy declares it needs besides the action to recompute its log-probability
    #: (``extras_spec``, docs/policies.md), name -> [T, N, ...]: e.g. a flow-matching policy's
    #: denoising chain float32 [T, N, K+1, A], a token policy's action bins int32 [T, N, A];
    #: empty for Gaussian policies
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    #: wall-clock creation time, ns since the Unix epoch
    created_ns: int = field(default_factory=_now_ns)

    @property
    def horizon(self) -> int:
        """T, the number of time steps."""
        return int(self.actions.shape[0])

    @property
    def num_envs(self) -> int:
        """N, the number of parallel environments."""
        return int(self.actions.shape[1])

    def validate(self) -> None:
        """Check that every array agrees with the chunk's own ``actions`` [T, N, A] and ``obs``:
        the :class:`ChunkSpec` the chunk implies (reasons ``schema``: keys; ``type``: dtypes;
        ``shape``)."""
        if self.seq < 0:
            raise CodecError("schema", f"seq {self.seq} < 0")
        if self.actions.ndim != 3:
            raise CodecError("shape", f"actions: ndim {self.actions.ndim}, expected 3 [T, N, A]")
        if not self.obs:
            raise CodecError("schema", "obs is empty")
        t, n, _ = self.actions.shape
        mismatch = ChunkSpec.implied_by(self).mismatch(self, n)
        if mismatch is not None:
            raise CodecError(*mismatch)
        if self.env_steps != t * n:
            raise CodecError("shape", f"env_steps {self.env_steps} != T*N = {t * n}")


@dataclass(frozen=True)
class ArraySpec:
    """Shape (without the leading time and env axes) and dtype of one per-step array."""

    #: per-env shape, e.g. (64, 64, 3)
    shape: tuple[int, ...]
    #: numpy dtype name: "float32", "uint8", "int32" or "bool" (the spec a chunk implies holds
    #: its arrays' dtypes as they are)
    dtype: str | np.dtype
    #: token arrays: ids lie in [0, vocab) (None for other arrays)
    vocab: int | None = None


#: a chunk's per-step fields in :class:`TrajectoryChunk` order; the ``KEYED`` ones are dicts of arrays
STEP_FIELDS = ("obs", "actions", "logprobs", "rewards", "terminated", "truncated", "success", "next_obs",
               "final_obs", "extras")
KEYED = ("obs", "next_obs", "final_obs", "extras")

#: where one array of a chunk sits: (field,), or (field, key) in a keyed field
ArrayPath = tuple[str, ...]


def chunk_arrays(chunk: Any) -> dict[ArrayPath, Any]:
    """Every per-step array of ``chunk`` (a :class:`TrajectoryChunk`, or anything with its
    per-step fields, e.g. tensors on a device) by its path, in :data:`STEP_FIELDS` order."""
    out: dict[ArrayPath, Any] = {}
    for f in STEP_FIELDS:
        value = getattr(chunk, f)
        out |= {(f, k): a for k, a in value.items()} if f in KEYED else {(f,): value}
    return out


def nest(arrays: dict[ArrayPath, Any]) -> dict[str, Any]:
    """A chunk's per-step fields from its arrays by path (the inverse of :func:`chunk_arrays`)."""
    out: dict[str, Any] = {f: {} for f in KEYED}
    for path, array in arrays.items():
        if len(path) == 1:
            out[path[0]] = array
        else:
            out[path[0]][path[1]] = array
    return out


#: a dtype from its name, parsed once (the wire checks every array of every chunk)
_dtype = functools.lru_cache(maxsize=64)(np.dtype)


def _name(path: ArrayPath) -> str:
    return path[0] if len(path) == 1 else f"{path[0]}[{path[1]!r}]"


@dataclass(frozen=True, kw_only=True)
class ChunkSpec:
    """The shape of a run's trajectory chunks, T steps of up to N envs: per step the observations
    ``obs`` declares, ``act_dim`` float32 actions, float32 log-prob and reward, bool terminated,
    truncated and success flags, the policy's ``extras``; one ``next_obs`` per env. Built once
    from the task and the policy, it allocates the rollout's chunks (:meth:`zeros`), the actor's
    slots and the learner's batch (:meth:`layout`) and checks a received chunk (:meth:`problem`)."""

    #: observation name -> per-env spec (the keys of obs, next_obs and final_obs)
    obs: dict[str, ArraySpec]
    #: float32 action values per step
    act_dim: int
    #: the policy's per-step extras (docs/policies.md); empty for Gaussian policies
    extras: dict[str, ArraySpec] = field(default_factory=dict)
    #: steps per chunk
    T: int
    #: the most envs one chunk holds (a chunk may hold fewer)
    N: int

    @classmethod
    def implied_by(cls, chunk: TrajectoryChunk) -> ChunkSpec:
        """The spec of a chunk's own ``actions`` [T, N, A] and ``obs`` / ``extras`` arrays."""
        def specs(arrays: dict[str, np.ndarray]) -> dict[str, ArraySpec]:
            return {k: ArraySpec(a.shape[2:], a.dtype) for k, a in arrays.items()}

        t, n, a = chunk.actions.shape
        return cls(obs=specs(chunk.obs), act_dim=a, extras=specs(chunk.extras), T=t, N=n)

    def layout(self, n: int | None = None) -> dict[ArrayPath, tuple[tuple[int, ...], ArraySpec]]:
        """Every array of a chunk of ``n`` envs (N by default), in :data:`STEP_FIELDS` order:
        path -> (shape: (T, n, *per-step), (n, *per-step) for ``next_obs``; per-step spec)."""
        t, n = self.T, self.N if n is None else n
        f32, flag = ArraySpec((), "float32"), ArraySpec((), "bool")
        specs = {("obs", k): s for k, s in self.obs.items()} | {("actions",): ArraySpec((self.act_dim,), "float32")}
        specs |= {(f,): f32 for f in ("logprobs", "rewards")} | {(f,): flag for f in ("terminated", "truncated", "success")}
        specs |= {(f, k): s for f in ("next_obs", "final_obs") for k, s in self.obs.items()}
        specs |= {("extras", k): s for k, s in self.extras.items()}
        return {p: ((n, *s.shape) if p[0] == "next_obs" else (t, n, *s.shape), s) for p, s in specs.items()}

    def zeros(self, n: int | None = None) -> TrajectoryChunk:
        """A chunk of ``n`` envs (N by default) whose arrays are all zero, each its own."""
        arrays = {path: np.zeros(shape, s.dtype) for path, (shape, s) in self.layout(n).items()}
        return TrajectoryChunk(rollout="", seq=0, policy_version=0, env_steps=self.T * (self.N if n is None else n),
                               created_ns=0, **nest(arrays))

    def nbytes(self, n: int | None = None) -> int:
        """Array bytes of a chunk of ``n`` envs (N by default)."""
        return sum(math.prod(shape) * np.dtype(s.dtype).itemsize for shape, s in self.layout(n).values())

    def mismatch(self, chunk: TrajectoryChunk, n: int) -> tuple[str, str] | None:
        """``(reason, detail)`` for the first array of ``chunk`` that is not where or what a chunk
        of ``n`` envs of this spec holds (``schema``: keys, ``type``: dtype, ``shape``)."""
        for f in KEYED:
            want = self.extras if f == "extras" else self.obs
            if getattr(chunk, f).keys() != want.keys():
                return "schema", f"{f} keys {sorted(getattr(chunk, f))} != {sorted(want)}"
        arrays = chunk_arrays(chunk)
        for path, (shape, s) in self.layout(n).items():
            if arrays[path].shape != shape:
                return "shape", f"{_name(path)}: shape {arrays[path].shape}, expected {shape}"
            if arrays[path].dtype != _dtype(s.dtype):
                return "type", f"{_name(path)}: dtype {arrays[path].dtype}, expected {s.dtype}"
        return None

    def problem(self, chunk: TrajectoryChunk) -> tuple[str, str] | None:
        """``(reason, detail)`` when a decoded (so self-consistent) ``chunk`` must not reach a
        learner of this spec, else None: ``shape`` (T, more than N envs, keys, per-step shapes or
        dtypes), ``nonfinite`` (NaN or inf in a float array), ``out_of_range`` (token ids outside
        their ``vocab``). One pass over each float and token array; images are not read."""
        t, n = chunk.horizon, chunk.num_envs
        if t != self.T or not 1 <= n <= self.N:
            return "shape", f"T={t}, N={n}: chunks of this run hold T={self.T}, N<={self.N}"
        mismatch = self.mismatch(chunk, n)
        if mismatch is not None:
            return "shape", mismatch[1]
        layout = self.layout(n)
        for path, a in chunk_arrays(chunk).items():
            vocab = layout[path][1].vocab
            if a.dtype.kind == "f" and not np.isfinite(a).all():
                return "nonfinite", f"{_name(path)} holds NaN or inf"
            if vocab is not None and a.size and (a.min() < 0 or a.max() >= vocab):
                return "out_of_range", f"{_name(path)} holds ids outside [0, {vocab})"
        return None


@dataclass(frozen=True, kw_only=True)
class WeightManifest(Message):
    """Announces a weight version; the payload follows as ``n_chunks`` :class:`WeightChunk`.

    The one manifest of a weight version: the encoder makes it, the actor signs it, relays
    forward it unchanged, and every replica checks its payload against it (dvla.replication).
    """

    TYPE_TAG: ClassVar[str] = "weights.manifest"

    #: role that publishes the weights
    sender: str
    #: policy version the chunks reconstruct
    version: int
    #: version the delta applies to (always ``version - 1``); -1 for a full version
    base_version: int
    #: how the payload encodes the weights: "full", "full-bf16", "delta-bf16" or "delta-topk",
    #: the deltas optionally with "+zstd" (compressed payload)
    encoding: str
    #: ``ParamLayout.hash`` of the sender; receivers refuse a layout they don't have
    layout_hash: str
    #: number of chunks that follow
    n_chunks: int
    #: total payload bytes over all chunks
    total_bytes: int
    #: hex digest of the flat float32 parameters *after* applying this version (what every
    #: replica must hold, bit for bit)
    checksum: str
    #: SHA-256 (hex) of those same bytes: what a snapshot of this version served by any relay
    #: must hash to (the actor signed it; ``checksum`` is fast, not collision resistant)
    digest: str = ""
    #: elements of the flat vector (a relay learns the layout's size from the first manifest
    #: instead of building the model)
    numel: int = 0
    #: content hash of the frozen base checkpoint the replicated tensors apply to ("" when the
    #: whole policy replicates); a receiver whose own base differs refuses the version
    base_hash: str = ""
    #: wall-clock creation time, ns since the Unix epoch
    created_ns: int = field(default_factory=_now_ns)

    def validate(self) -> None:
        _require(self.version >= 0, "schema", f"version {self.version} < 0")
        _require(self.base_version >= -1, "schema", f"base_version {self.base_version} < -1")
        _require(self.n_chunks >= 0, "schema", f"n_chunks {self.n_chunks} < 0")
        _require(self.total_bytes >= 0, "schema", f"total_bytes {self.total_bytes} < 0")
        _require(0 <= self.numel < 2**32, "schema", f"numel {self.numel} out of range")

    def whole(self, n_chunks: int) -> "WeightManifest":
        """This version's manifest for its parameters sent whole, in `n_chunks` chunks (a
        snapshot): ``full`` float32 encoding, no base; checksum and digest are the same."""
        return replace(self, base_version=-1, encoding="full", n_chunks=n_chunks, total_bytes=4 * self.numel)


@dataclass(frozen=True, kw_only=True)
class WeightChunk(Message):
    """One slice of a weight payload announced by a :class:`WeightManifest`."""

    TYPE_TAG: ClassVar[str] = "weights.chunk"

    #: role that publishes the weights
    sender: str
    #: policy version this chunk belongs to
    version: int
    #: position of this chunk, 0 <= index < n_chunks
    index: int
    #: number of chunks of this version
    n_chunks: int
    #: the payload slice
    data: bytes

    def validate(self) -> None:
        _require(0 <= self.index < self.n_chunks, "schema", f"index {self.index} outside [0, {self.n_chunks})")


@dataclass(frozen=True, kw_only=True)
class Command(Message):
    """An operator instruction to one role or to all of them."""

    TYPE_TAG: ClassVar[str] = "cmd"

    #: role name, or "all"
    target: str
    #: one of :data:`COMMAND_VERBS`
    verb: str
    #: verb-specific arguments (msgpack-able scalars, strings, lists, nested dicts)
    args: dict[str, Any] = field(default_factory=dict)
    #: wall-clock issue time, ns since the Unix epoch
    issued_ns: int = field(default_factory=_now_ns)

    def validate(self) -> None:
        _require(self.verb in COMMAND_VERBS, "schema", f"verb {self.verb!r} not in {COMMAND_VERBS}")
        if self.verb == "revoke":
            name = self.args.get("name")
            _require(isinstance(name, str) and bool(name), "schema", f"revoke needs args.name (a role name), got {name!r}")


@dataclass(frozen=True, kw_only=True)
class RoleStatus(Message):
    """Periodic self-report of a role, consumed by the orchestrator and dashboards."""

    TYPE_TAG: ClassVar[str] = "status"

    #: role name
    name: str
    #: role kind (e.g. "actor", "rollout")
    kind: str
    #: host the role runs on
    node: str
    #: rack of that host
    rack: str
    #: process id
    pid: int
    #: one of :data:`ROLE_STATES`
    state: str
    #: newest policy version the role holds
    policy_version: int
    #: environment steps produced (rollouts) or consumed (actor) so far
    env_steps: int
    #: recent throughput, env steps per second
    steps_per_s: float
    #: per-link float metrics, lane name -> metric name -> value
    lanes: dict[str, dict[str, float]] = field(default_factory=dict)
    #: per-plane counters, plane name -> counter name -> value
    planes: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: anything else (msgpack-able scalars, strings, lists, nested dicts)
    extra: dict[str, Any] = field(default_factory=dict)
    #: wall-clock report time, ns since the Unix epoch
    time_ns: int = field(default_factory=_now_ns)

    def validate(self) -> None:
        _require(self.state in ROLE_STATES, "schema", f"state {self.state!r} not in {ROLE_STATES}")


@dataclass(frozen=True, kw_only=True)
class EvalResult(Message):
    """Outcome of deterministic evaluation episodes of one policy version."""

    TYPE_TAG: ClassVar[str] = "eval"

    #: evaluator role name
    sender: str
    #: policy version evaluated
    policy_version: int
    #: number of episodes run
    episodes: int
    #: fraction of episodes that succeeded at any step
    success_once: float
    #: fraction of episodes that were successful at their last step
    success_at_end: float
    #: mean undiscounted episode return
    return_mean: float
    #: 95 % (Wilson) interval of ``success_once`` over these episodes
    success_low: float = 0.0
    success_high: float = 1.0
    #: (shard, shards): this evaluator's block of the evaluation's episodes, of how many blocks
    #: (the orchestrator joins the blocks of one evaluation, docs/evaluation.md)
    shard: int = 0
    shards: int = 1
    #: per task, for envs that name their tasks (LIBERO: "libero_spatial/3"): episodes played and
    #: episodes with a success at any step (empty for other envs)
    task_episodes: dict[str, int] = field(default_factory=dict)
    task_successes: dict[str, int] = field(default_factory=dict)
    #: wall-clock report time, ns since the Unix epoch
    time_ns: int = field(default_factory=_now_ns)

    def validate(self) -> None:
        _require(self.episodes >= 0, "schema", f"episodes {self.episodes} < 0")
        _require(self.task_episodes.keys() == self.task_successes.keys(), "schema",
                 "task_episodes and task_successes name different tasks")
        for task, n in self.task_episodes.items():
            _require(0 <= self.task_successes[task] <= n, "schema",
                     f"task {task!r}: {self.task_successes[task]} successes of {n} episodes")
        _require(0 <= self.shard < self.shards, "schema", f"shard {self.shard} not in [0, {self.shards})")
        for name in ("success_once", "success_at_end", "success_low", "success_high"):
            value = getattr(self, name)
            _require(0.0 <= value <= 1.0, "schema", f"{name} {value!r} not in [0, 1]")
        _require(math.isfinite(self.return_mean), "schema", f"return_mean {self.return_mean!r} is not finite")


@dataclass(frozen=True, kw_only=True)
class SnapshotRequest(Message):
    """Asks a weight holder for its version whole (e.g. after joining late or losing chunks)."""

    TYPE_TAG: ClassVar[str] = "snapshot.req"

    #: role asking
    requester: str
    #: newest version the requester holds, -1 for none
    have_version: int


@dataclass(frozen=True, kw_only=True)
class WeightSnapshot(Message):
    """First reply of a ``snapshot`` queryable (catch-up): the version the sender holds, and the
    ``n_chunks`` :class:`WeightChunk` replies that follow with it whole (its ``full`` encoding).

    ``n_chunks`` 0 is a header-only reply: the sender holds ``version`` (-1: nothing yet) and the
    requester already has it or newer, so no parameters are sent.
    """

    TYPE_TAG: ClassVar[str] = "snapshot"

    #: role that serves the snapshot
    sender: str
    #: policy version held
    version: int
    #: the actor's signed envelope of this version's :class:`WeightManifest`: its ``digest`` is
    #: what the parameters must hash to (empty in a header-only reply)
    manifest: bytes
    #: WeightChunk replies that follow (0: header only)
    n_chunks: int
    #: wall-clock creation time, ns since the Unix epoch
    created_ns: int = field(default_factory=_now_ns)

    def validate(self) -> None:
        _require(self.version >= -1, "schema", f"version {self.version} < -1")
        _require(self.n_chunks >= 0, "schema", f"n_chunks {self.n_chunks} < 0")
        _require(self.version >= 0 or not self.n_chunks, "schema", "version -1 (nothing held) with parameters")


@dataclass(frozen=True, kw_only=True)
class LedgerRecord(Message):
    """A rollout's chunk counters, as its counter file holds them (dvla/ledger.py), sent to its
    learner: a rollout on another machine (``dvla join``) keeps its counter file there, so the
    learner keeps the run's copy and the run's accounting includes it."""

    TYPE_TAG: ClassVar[str] = "ledger"

    #: the rollout's name
    role: str
    #: its counter file's incarnation (the high bits of its chunks' ``seq``)
    incarnation: int
    #: its process id
    pid: int
    #: the counter record, JSON text: an object with ``kind`` "rollout" and this role,
    #: incarnation and pid
    record: str

    def validate(self) -> None:
        try:
            check_name("role", self.role)  # it names a file: one key chunk, no '/'
        except ValueError as err:
            raise CodecError("schema", str(err)) from None
        _require(self.incarnation >= 0, "schema", f"incarnation {self.incarnation} < 0")
        _require(self.pid > 0, "schema", f"pid {self.pid} <= 0")
        try:
            doc = json.loads(self.record)
        except ValueError as err:
            raise CodecError("schema", f"record is not JSON: {err}") from None
        _require(isinstance(doc, dict) and doc.get("kind") == "rollout", "schema", "record is not a rollout's counter record")
        for name in ("role", "incarnation", "pid"):
            _require(doc.get(name) == getattr(self, name), "schema",
                     f"record's {name} {doc.get(name)!r} is not the message's {getattr(self, name)!r}")


@dataclass(frozen=True, kw_only=True)
class ReceiptRequest(Message):
    """A stopping rollout asks its learner how far it got the rollout's chunks, before it closes
    its data session: chunks still in the link's buffers when that closes can be lost
    (docs/reliability.md, "Closing a rollout")."""

    TYPE_TAG: ClassVar[str] = "receipt.req"

    #: the rollout asking
    rollout: str
    #: the seq of the last chunk it shipped (its incarnation in the high bits)
    seq: int

    def validate(self) -> None:
        _require(self.seq >= 0, "schema", f"seq {self.seq} < 0")


@dataclass(frozen=True, kw_only=True)
class Receipt(Message):
    """The learner's reply to a :class:`ReceiptRequest`: the newest chunk of that rollout
    incarnation it has taken out of its inbox (every earlier one has left the link too)."""

    TYPE_TAG: ClassVar[str] = "receipt"

    #: the rollout asked about
    rollout: str
    #: seq of the newest chunk got of the request's incarnation; -1: none yet
    seq: int

    def validate(self) -> None:
        _require(self.seq >= -1, "schema", f"seq {self.seq} < -1")


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE_TAG: cls
    for cls in (TrajectoryChunk, WeightManifest, WeightChunk, Command, RoleStatus, EvalResult, SnapshotRequest,
                WeightSnapshot, LedgerRecord, ReceiptRequest, Receipt)
}
"""Wire type tag -> message class."""

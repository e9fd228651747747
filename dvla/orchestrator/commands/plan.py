"""`dvla plan TOPOLOGY`: placement, weight tree, links and the predicted broadcast time."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from ..plan import make_plan
from ..scale import BYTES_PER_PARAM, DEFAULT_PARAMS
from ..simulate import simulate_broadcast
from ..topology import topology_to_dict
from .common import Format, fail, topology_or_exit

#: weights size assumed without --param-mb: the scale model's default, about the default MLP policy's
DEFAULT_PARAM_MB = DEFAULT_PARAMS * BYTES_PER_PARAM["fp32"] / 1e6


def plan(
    topology: Annotated[Path, typer.Argument(help="topology YAML file")],
    format: Annotated[Format, typer.Option("--format", "-f", help="table or json")] = Format.table,
    param_mb: Annotated[Optional[float], typer.Option(help="weights size (MB) for the broadcast estimate")] = None,
    simulate: Annotated[bool, typer.Option("--simulate", help="model the whole pipeline at scale (docs/scale.md)")] = False,
    nodes: Annotated[Optional[int], typer.Option(help="--simulate: nodes (the topology's racks repeated)")] = None,
    racks: Annotated[Optional[int], typer.Option(help="--simulate: racks the nodes are spread over")] = None,
    params: Annotated[Optional[str], typer.Option(help="--simulate: model parameters, e.g. 7e9, 500M, 7B, 1T")] = None,
    dtype: Annotated[Optional[str], typer.Option(help="--simulate: fp32 or bf16 weights")] = None,
    encoding: Annotated[Optional[str], typer.Option(help="--simulate: full, delta-bf16 or delta-topk")] = None,
    trainable_fraction: Annotated[Optional[float], typer.Option(help="--simulate: share of parameters trained (LoRA: ~0.01)")] = None,
    env_rate: Annotated[Optional[float], typer.Option(help="--simulate: env steps/s of one rollout's simulators")] = None,
    step_bytes: Annotated[Optional[float], typer.Option(help="--simulate: data-plane bytes per env step")] = None,
    learner_rate: Annotated[Optional[float], typer.Option(help="--simulate: env steps/s one learner rank consumes")] = None,
    node_memory_gib: Annotated[Optional[float], typer.Option(help="--simulate: memory per node, GiB")] = None,
    hop_latency_s: Annotated[Optional[float], typer.Option(help="--simulate: one-way latency per link, s")] = None,
    process_gbit: Annotated[Optional[float], typer.Option(help="--simulate: Gbit/s one relay verifies and forwards")] = None,
    sizes: Annotated[str, typer.Option(help="--simulate: node counts of the speedup table ('' for none)")] = "8,16,32,64,128,256,512,1024",
    plot: Annotated[Optional[Path], typer.Option(help="--simulate: speedup plot (PNG) path")] = None,
) -> None:
    """Validate TOPOLOGY and show where every process runs and how weights travel."""
    topo = topology_or_exit(topology)
    if simulate:
        _simulate(topo, locals(), format)
        return
    p = make_plan(topo, run_dir=f"runs/{topo.run}")
    procs = [
        {
            "name": x.config.name, "kind": x.config.kind, "node": x.config.node, "rack": x.config.rack,
            "host": x.host, "parent": x.config.parent, "children": list(x.config.children),
            "actors": list(x.config.actors), "ctrl": {"mode": x.config.ctrl.mode, "listen": list(x.config.ctrl.listen),
            "connect": list(x.config.ctrl.connect)}, "data": {"listen": list(x.config.data.listen),
            "connect": list(x.config.data.connect)},
            "cpus": list(x.config.cpus) if x.config.cpus else None,
            "lane_cpus": {k: list(v) for k, v in x.config.lane_cpus.items()} if x.config.lane_cpus else None,
            "sim_workers": x.config.sim_workers,
        }
        for x in p.processes
    ]
    group = _group(p)
    mb = param_mb if param_mb is not None else DEFAULT_PARAM_MB
    bc = simulate_broadcast(topo, p, int(mb * 1e6))
    estimate = {"param_mb": mb, "param_mb_assumed": param_mb is None, "tree_s": bc.tree_s, "star_s": bc.star_s,
                "bound_s": bc.bound_s, "bound_link": bc.bound_link, "tree_bottleneck": bc.tree_bottleneck,
                "star_bottleneck": bc.star_bottleneck, "depth": bc.depth}
    if format == Format.json:
        doc = {"topology": topology_to_dict(topo), "processes": procs, "warnings": list(p.warnings), "broadcast": estimate,
               "learner_group": group}
        typer.echo(json.dumps(doc, indent=1, sort_keys=True))
        return
    typer.echo(f"run {topo.run}: {len(procs)} processes on {len(topo.nodes())} nodes, mode {topo.mode}, emulate {topo.emulate}")
    for x in procs:
        typer.echo(f"  {x['name']:<28} {x['rack']}/{x['node']:<10} parent={x['parent'] or '-'}{_pinning(x)}")
    typer.echo(f"learner group: {len(group['ranks'])} rank(s), {group['strategy']} over {group['backend']}"
               + (f", rendezvous {group['rendezvous']}" if group["rendezvous"] else "") + "; data routing:")
    for r in group["ranks"]:
        typer.echo(f"  rank {r['rank']} {r['actor']} <- {', '.join(r['rollouts']) or '(no rollouts)'}")
    typer.echo("weight tree:")
    _tree(typer.echo, procs, p.root_actor, "  ")
    routers = [x for x in procs if x["kind"] == "router"]
    if routers:
        typer.echo("routers (outside rollouts join through them: `dvla join`):")
    for x in routers:
        typer.echo(f"  {x['name']}: ctrl {', '.join(x['ctrl']['listen'])} -> {', '.join(x['ctrl']['connect'])}; "
                   f"data {', '.join(x['data']['listen'])} -> {', '.join(x['data']['connect'])}")
    typer.echo(
        f"one version of {estimate['param_mb']:.1f} MB{' (assumed: --param-mb sets it)' if estimate['param_mb_assumed'] else ''}"
        f" as a full copy: ~{estimate['tree_s']:.3f} s through the tree (busiest link: {estimate['tree_bottleneck'] or 'none'}),"
        f" ~{estimate['star_s']:.3f} s as a star (busiest link: {estimate['star_bottleneck'] or 'none'});"
        f" S/B bound {estimate['bound_s']:.3f} s ({estimate['bound_link']}); simulated, see `--simulate`"
    )
    for w in p.warnings:
        typer.echo(f"warning: {w}", err=True)


def _simulate(topo: Any, opts: dict[str, Any], format: Format) -> None:
    from .simulate import parse_params, resolve, run_simulation

    if opts["dtype"] not in (None, "fp32", "bf16"):
        raise fail(f"--dtype: expected fp32 or bf16, got {opts['dtype']!r}")
    if opts["encoding"] not in (None, "full", "delta-bf16", "delta-topk"):
        raise fail(f"--encoding: expected full, delta-bf16 or delta-topk, got {opts['encoding']!r}")
    try:
        sizes = tuple(int(x) for x in opts["sizes"].split(",") if x.strip())
    except ValueError:
        raise fail(f"--sizes: expected comma-separated node counts, got {opts['sizes']!r}")
    if any(n < 1 for n in sizes):
        raise fail(f"--sizes: node counts must be >= 1, got {opts['sizes']!r}")
    flags = {"nodes": opts["nodes"], "racks": opts["racks"], "dtype": opts["dtype"],
             "params": parse_params(opts["params"]) if opts["params"] is not None else None,
             "trainable_fraction": opts["trainable_fraction"], "env_steps_per_s": opts["env_rate"],
             "step_bytes": opts["step_bytes"], "learner_steps_per_s": opts["learner_rate"],
             "node_memory_gib": opts["node_memory_gib"], "hop_latency_s": opts["hop_latency_s"],
             "process_gbit": opts["process_gbit"]}
    plot = opts["plot"] if opts["plot"] is not None else Path("runs") / "simulate" / f"{topo.run}-speedup.png"
    run_simulation(topo, resolve(topo, flags), opts["encoding"], plot if sizes else None, sizes, typer.echo,
                   format == Format.json)


def _group(p: Any) -> dict[str, Any]:
    """The learner group as `dvla plan` shows it: ranks, rendezvous and which rollouts feed each."""
    actors = [x.config for x in p.processes if x.config.kind == "actor"]
    g = actors[0].group
    return {
        "strategy": g.strategy if g else "ddp", "backend": g.backend if g else "none (one rank)",
        "rendezvous": g.init_method if g else None, "timeout_s": g.timeout_s if g else None,
        "ranks": [{"rank": i, "actor": a.name, "node": a.node, "rollouts": list(a.rollouts)} for i, a in enumerate(actors)],
    }


def _pinning(proc: dict[str, Any]) -> str:
    """`` cpus=1 sim@0`` for a pinned process (lanes pinned apart after its own cores), plus a rollout's
    ``sim_workers=N``; else ""."""
    parts = []
    if proc["cpus"]:
        parts.append("cpus=" + ",".join(map(str, proc["cpus"])))
    for lane, cpus in (proc["lane_cpus"] or {}).items():
        parts.append(f"{lane}@" + ",".join(map(str, cpus)))
    if proc["sim_workers"]:  # resolved by the rollout on its node ("auto": that node's cores)
        parts.append(f"sim_workers={proc['sim_workers']}")
    return "  " + " ".join(parts) if parts else ""


def _tree(echo, procs: list[dict], name: str, indent: str) -> None:
    echo(f"{indent}{name}")
    for x in procs:
        if x["parent"] == name and x["kind"] != "router":
            _tree(echo, procs, x["name"], indent + "  ")


"""`dvla plan TOPOLOGY`: placement, weight tree, links and the predicted broadcast time."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from ..estimate import delivery_estimate
from ..plan import make_plan
from ..topology import topology_to_dict
from .common import Format, topology_or_exit


#: weights size assumed without --param-mb: about the default MLP policy's (1.1 MB)
DEFAULT_PARAM_MB = 1.1


def plan(
    topology: Annotated[Path, typer.Argument(help="topology YAML file")],
    format: Annotated[Format, typer.Option("--format", "-f", help="table or json")] = Format.table,
    param_mb: Annotated[Optional[float], typer.Option(help="weights size (MB) for the broadcast estimate")] = None,
) -> None:
    """Validate TOPOLOGY and show where every process runs and how weights travel."""
    topo = topology_or_exit(topology)
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
        }
        for x in p.processes
    ]
    group = _group(p)
    mb = param_mb if param_mb is not None else DEFAULT_PARAM_MB
    estimate = {"param_mb": mb, "param_mb_assumed": param_mb is None, **delivery_estimate(topo, p, int(mb * 1e6))}
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
    typer.echo(
        f"one version of {estimate['param_mb']:.1f} MB{' (assumed: --param-mb sets it)' if estimate['param_mb_assumed'] else ''}"
        f" as a full copy: ~{estimate['tree_s']:.3f} s through the tree (busiest link: {estimate['tree_bottleneck'] or 'none'}),"
        f" ~{estimate['star_s']:.3f} s as a star (busiest link: {estimate['star_bottleneck'] or 'none'});"
        f" link bound {estimate['bound_s']:.3f} s"
    )
    for w in p.warnings:
        typer.echo(f"warning: {w}", err=True)


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
    """`` cpus=1 sim@0`` for a pinned process (lanes pinned apart after its own cores), else ""."""
    parts = []
    if proc["cpus"]:
        parts.append("cpus=" + ",".join(map(str, proc["cpus"])))
    for lane, cpus in (proc["lane_cpus"] or {}).items():
        parts.append(f"{lane}@" + ",".join(map(str, cpus)))
    return "  " + " ".join(parts) if parts else ""


def _tree(echo, procs: list[dict], name: str, indent: str) -> None:
    echo(f"{indent}{name}")
    for x in procs:
        if x["parent"] == name:
            _tree(echo, procs, x["name"], indent + "  ")


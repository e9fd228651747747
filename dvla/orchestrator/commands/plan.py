"""`dvla plan TOPOLOGY`: placement, weight tree, links and the predicted broadcast time."""

from __future__ import annotations

import json
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..plan import make_plan
from ..topology import topology_to_dict
from .common import topology_or_exit


class Format(str, Enum):
    table = "table"
    json = "json"


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
        }
        for x in p.processes
    ]
    estimate = broadcast_estimate(topo, p, param_mb)
    if format == Format.json:
        doc = {"topology": topology_to_dict(topo), "processes": procs, "warnings": list(p.warnings), "broadcast": estimate}
        typer.echo(json.dumps(doc, indent=1, sort_keys=True))
        return
    typer.echo(f"run {topo.run}: {len(procs)} processes on {len(topo.nodes())} nodes, mode {topo.mode}, emulate {topo.emulate}")
    for x in procs:
        typer.echo(f"  {x['name']:<28} {x['rack']}/{x['node']:<10} parent={x['parent'] or '-'}")
    typer.echo("weight tree:")
    _tree(typer.echo, procs, p.root_actor, "  ")
    typer.echo(
        f"broadcast of {estimate['param_mb']:.1f} MB ({topo.replication.encoding}): "
        f"~{estimate['tree_s']:.3f} s through the tree, ~{estimate['star_s']:.3f} s as a star"
    )
    for w in p.warnings:
        typer.echo(f"warning: {w}", err=True)


def _tree(echo, procs: list[dict], name: str, indent: str) -> None:
    echo(f"{indent}{name}")
    for x in procs:
        if x["parent"] == name:
            _tree(echo, procs, x["name"], indent + "  ")


def broadcast_estimate(topo, p, param_mb: float | None) -> dict[str, float]:
    """Store-and-forward per chunk, cut-through between levels: size / slowest link on the path
    plus one chunk per extra hop; a star sends every copy through the actor's NIC."""
    mb = param_mb if param_mb is not None else 1.1
    bits = mb * 8e6
    node_bps = topo.links.node_gbit * 1e9
    uplink_bps = topo.links.rack_uplink_gbit * 1e9
    chunk_bits = topo.replication.chunk_bytes * 8
    leaves = [x for x in p.processes if x.config.kind in ("rollout", "evaluator")]
    depth = max((len(x.config.ancestors) for x in leaves), default=1)
    racks = len(topo.racks)
    max_children = max((len(x.config.children) for x in p.processes), default=1)
    # Each tree node sends a version once per child over its own NIC; cross-rack hops use uplinks.
    per_link = bits * max_children / min(node_bps, uplink_bps if racks > 1 else node_bps)
    tree_s = per_link + (depth - 1) * chunk_bits / min(node_bps, uplink_bps)
    star_s = bits * len(leaves) / min(node_bps, uplink_bps if racks > 1 else node_bps)
    return {"param_mb": mb, "tree_s": tree_s, "star_s": star_s, "depth": depth, "leaves": len(leaves)}

"""`dvla plan TOPOLOGY --simulate`: the scale model's report (docs/scale.md)."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path
from typing import Any, Callable, Optional

from ...config import SimulateConfig, Topology
from ..scale import (LINEAR_SHARE, PipelinePrediction, ScaleError, SpeedupRow, check_inputs, simulate_pipeline,
                     speedup_table, tile)
from .common import fail

_SUFFIX = {"": 1.0, "K": 1e3, "M": 1e6, "B": 1e9, "G": 1e9, "T": 1e12}


def parse_params(text: str) -> float:
    """`7e9`, `7B`, `500M`, `1T` -> parameters."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([kKmMbBgGtT]?)\s*", text)
    if not m:
        raise fail(f"--params: expected a parameter count such as 7e9, 500M, 7B or 1T, got {text!r}")
    return float(m.group(1)) * _SUFFIX[m.group(2).upper()]


def resolve(topo: Topology, flags: dict[str, Any]) -> SimulateConfig:
    """The topology's `simulate:` section with the flags given on the command line applied."""
    given = {k: v for k, v in flags.items() if v is not None}
    return dataclasses.replace(topo.simulate, **given)


def run_simulation(topo: Topology, cfg: SimulateConfig, encoding: str | None, plot: Path | None,
                   sizes: tuple[int, ...], echo: Callable[[str], None], as_json: bool) -> None:
    if encoding is not None:
        topo = dataclasses.replace(topo, replication=dataclasses.replace(topo.replication, encoding=encoding))
    try:
        check_inputs(cfg, topo)
        big = tile(topo, cfg.nodes, cfg.racks)
        pred = simulate_pipeline(big, dataclasses.replace(cfg, nodes=None, racks=None))
        rows, bend = speedup_table(topo, cfg, list(sizes)) if sizes else ([], None)
    except ScaleError as err:
        raise fail(str(err))
    doc = {"config": dataclasses.asdict(cfg), "encoding": topo.replication.encoding, "prediction": _asdict(pred),
           "speedup": [dataclasses.asdict(r) for r in rows], "bend": dataclasses.asdict(bend) if bend else None}
    if plot is not None and rows:
        _plot(rows, bend, plot, f"{topo.run}: {_model(cfg, pred)}")
        doc["plot"] = str(plot)
    if as_json:
        echo(json.dumps(doc, indent=1, sort_keys=True, default=str))
        return
    for line in report(pred, cfg, topo.replication.encoding):
        echo(line)
    if rows:
        echo(f"speedup, racks of {rows[-1].nodes / rows[-1].racks:g} nodes (against {rows[0].nodes} nodes):")
        echo(f"  {'nodes':>6} {'racks':>5} {'env steps/s':>12} {'speedup':>8} {'linear':>7} {'share':>6} "
             f"{'broadcast s':>11} {'lag':>5}  limit")
        for r in rows:
            echo(f"  {r.nodes:>6} {r.racks:>5} {r.env_steps_per_s:>12,.0f} {r.speedup:>8.2f} {r.linear:>7.0f} "
                 f"{r.share_of_linear:>6.2f} {r.broadcast_s:>11.3g} {r.policy_lag_mean:>5.2f}  {r.limit}")
        if bend is not None:
            echo(f"speedup falls below {LINEAR_SHARE}x linear at {bend.nodes} nodes: {bend.limit} ({bend.limit_detail})")
        else:
            echo(f"speedup stays at or above {LINEAR_SHARE}x linear up to {rows[-1].nodes} nodes")
    if "plot" in doc:
        echo(f"plot: {doc['plot']}")


def _model(cfg: SimulateConfig, pred: PipelinePrediction) -> str:
    params = pred.extras["version_bytes_full"]
    return f"{_si(cfg.params) if cfg.params else 'default'} params {cfg.dtype}, version {_bytes(params)}"


def report(pred: PipelinePrediction, cfg: SimulateConfig, encoding: str) -> list[str]:
    b = pred.broadcast
    x = pred.extras
    over = b.tree_s / b.bound_s if b.bound_s > 0 else math.inf
    return [
        f"simulated: {pred.nodes} nodes in {pred.racks} racks, {pred.rollouts} rollouts, {pred.learner_ranks} learner rank(s); "
        f"{_model(cfg, pred)} ({encoding}; delta versions {_bytes(x['version_bytes_delta'])})",
        f"  env steps/s trained      {pred.env_steps_per_s:,.0f}  (rollouts produce {pred.produced_env_steps_per_s:,.0f})",
        f"  learner                  busy {pred.learner_utilisation:.0%}; per version {x['compute_s_per_version']:.3g} s compute "
        f"+ {x['comm_s_per_version']:.3g} s all-reduce",
        f"  policy lag               mean {pred.policy_lag_mean:.2f}, max {pred.policy_lag_max:.0f} versions; a version every "
        f"{pred.version_interval_s:.3g} s",
        f"  weight broadcast         tree {b.tree_s:.3g} s = {over:.2f}x the S/B bound {b.bound_s:.3g} s of the slowest link crossed, "
        f"the {b.bound_link}; star {b.star_s:.3g} s" if b.star_s else
        f"  weight broadcast         tree {b.tree_s:.3g} s = {over:.2f}x the S/B bound {b.bound_s:.3g} s of the {b.bound_link}",
        f"  busiest tree link        {b.tree_bottleneck} ({b.tree_bottleneck_copies} cop{'y' if b.tree_bottleneck_copies == 1 else 'ies'} "
        f"per version); depth {b.depth}; delta versions {x['delta_broadcast_s']:.3g} s",
        f"  data plane               busiest link: {pred.data_link}",
        f"  limit                    {pred.limit}: {pred.limit_detail}",
    ]


def _asdict(pred: PipelinePrediction) -> dict[str, Any]:
    d = dataclasses.asdict(pred)
    d["broadcast"].pop("per_leaf_s", None)
    return d


def _si(x: float) -> str:
    for div, s in ((1e12, "T"), (1e9, "B"), (1e6, "M"), (1e3, "K")):
        if x >= div:
            return f"{x / div:g}{s}"
    return f"{x:g}"


def _bytes(n: float) -> str:
    for div, s in ((1 << 40, "TiB"), (1 << 30, "GiB"), (1 << 20, "MiB"), (1 << 10, "KiB")):
        if n >= div:
            return f"{n / div:.3g} {s}"
    return f"{n:.0f} B"


def _plot(rows: list[SpeedupRow], bend: Optional[SpeedupRow], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r.nodes for r in rows]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    ax.loglog(n, [r.linear for r in rows], "k--", label="linear", base=2)
    ax.loglog(n, [r.speedup for r in rows], "o-", label="simulated", base=2)
    if bend is not None:
        ax.axvline(bend.nodes, color="tab:red", alpha=0.4)
        ax.annotate(f"< {LINEAR_SHARE}x linear: {bend.limit}", (bend.nodes, bend.speedup), fontsize=8,
                    xytext=(5, -15), textcoords="offset points")
    ax.set_ylabel(f"speedup over {n[0]} nodes (trained env steps/s)")
    bx.semilogx(n, [r.broadcast_s for r in rows], "o-", label="tree (simulated)", base=2)
    bx.semilogx(n, [r.bound_s for r in rows], "k--", label="S/B bound", base=2)
    bx.set_ylim(bottom=0)
    bx.set_ylabel("seconds per weight version")
    for a in (ax, bx):
        a.set_xlabel("nodes")
        a.legend()
        a.grid(True, which="both", alpha=0.3)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)

"""`dvla bench ...`: benchmarks that compare against a baseline measured in the same run."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer

from .common import fail

app = typer.Typer(help="Benchmarks (each writes JSON with ratios against an in-run baseline).", no_args_is_help=True)


@app.command("e2e")
def e2e(
    topology: Annotated[Path, typer.Argument(help="topology YAML")] = Path("topologies/local.yaml"),
    seeds: Annotated[str, typer.Option(help="comma-separated seeds")] = "1,2,3",
    json_path: Annotated[Optional[Path], typer.Option("--json", help="write results here")] = None,
    base_port: Annotated[int, typer.Option(help="first TCP port")] = 19400,
) -> None:
    """Train once per seed to the topology's success target; time and steps to get there."""
    from ...bench.e2e import run_seeds

    try:
        seed_list = [int(s) for s in seeds.split(",") if s.strip()]
    except ValueError:
        raise fail(f"--seeds: expected comma-separated integers, got {seeds!r}")
    doc = run_seeds(topology, seed_list, base_port, [])
    for r in doc["runs"]:
        typer.echo(f"seed {r['seed']}: {r['reason']}  env_steps={r['env_steps']}  train_s={_f(r['train_s'])}  "
                   f"startup_s={_f(r['startup_s'])}  steps/s={_f(r['train_steps_per_s'])}")
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(doc, indent=1))
        typer.echo(f"wrote {json_path}")


def _f(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


@app.command("fabric")
def fabric(
    json_path: Annotated[Path, typer.Option("--json", help="write the results (JSON) here")],
    quick: Annotated[bool, typer.Option("--quick", help="tiny counts: checks the machinery, not the speed")] = False,
) -> None:
    """Fabric chunk throughput against raw Zenoh (64 KiB, 1 MiB) and ctrl request/reply p99 RTT: idle,
    with the data plane flooded, and flooded with data and ctrl on one shared session."""
    from ...bench.fabric import format_table, run_bench

    try:
        doc = run_bench(quick=quick, progress=lambda m: typer.echo(f"[bench] {m}", err=True))
    except (RuntimeError, TimeoutError, OSError) as err:
        raise fail(f"bench fabric: {err}", code=1)
    doc["command"] = "dvla bench fabric --json " + str(json_path) + (" --quick" if quick else "")
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(doc, indent=1))
    typer.echo(format_table(doc))
    typer.echo(f"wrote {json_path}  ({doc['elapsed_s']:.0f} s)")

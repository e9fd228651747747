"""`dvla export RUN OUT`: a run's trained policy written back in its checkpoint's own format."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from .common import RUNS_ROOT, fail


class ExportFormat(str, Enum):
    lerobot = "lerobot"


def export(
    run: Annotated[str, typer.Argument(help="run id (a directory under --runs)")],
    out: Annotated[Path, typer.Argument(help="directory to write (must not exist or be empty)")],
    format: Annotated[ExportFormat, typer.Option("--format", "-f", help="checkpoint format to write")] = ExportFormat.lerobot,
    runs: Annotated[Path, typer.Option(help="directory of run directories")] = RUNS_ROOT,
) -> None:
    """Write the run's latest checkpoint as a LeRobot policy directory (pi0, pi05, smolvla runs):
    the checkpoint it started from with the trained tensors applied, LoRA adapters merged into
    their weights; config, processors, statistics and tokenizer files copied unchanged."""
    from ...learn.vla.checkpoint import CheckpointError
    from ...learn.vla.lerobot_format import LEROBOT_FAMILIES, check_lerobot, export_lerobot, read_state_dict
    from ...learn.vla.published import lora_scaling, merge_trained
    from ...learn.checkpoint_files import CheckpointError as RunCheckpointError
    from ...learn.checkpoint_files import read_current
    from ..topology import TopologyError, load_topology

    run_dir = runs / run
    topo_file = run_dir / "topology.yaml"
    if not topo_file.is_file():
        raise fail(f"{run_dir}: not a run directory (no topology.yaml)")
    try:
        task = load_topology(topo_file).task
    except TopologyError as err:
        raise fail(str(err)) from None
    if task.policy not in LEROBOT_FAMILIES:
        raise fail(f"{topo_file}: task.policy {task.policy!r} has no {format.value} format (export needs one of "
                   f"{', '.join(LEROBOT_FAMILIES)})")
    kwargs = task.policy_kwargs
    try:
        ck = check_lerobot(str(kwargs.get("checkpoint", "")), task.policy, tokenizer=kwargs.get("tokenizer"))
        current = read_current(run_dir / "checkpoints")
        if current is None:
            raise fail(f"{run_dir / 'checkpoints'}: no checkpoint written yet")
        version, trained = current
        merged = merge_trained(read_state_dict(ck), trained, lora_scaling(kwargs.get("lora")))
        path = export_lerobot(ck, merged, out, metadata={"dvla.run": run, "dvla.version": str(version),
                                                        "dvla.lora": "merged" if kwargs.get("lora") else "none"})
    except (CheckpointError, RunCheckpointError, ValueError) as err:
        raise fail(str(err)) from None
    typer.echo(f"wrote {run} version {version} ({task.policy}, LoRA {'merged' if kwargs.get('lora') else 'none'}) to {path}")

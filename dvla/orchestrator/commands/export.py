"""`dvla export RUN OUT`: a run's trained policy written back in its checkpoint's own format."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from .common import RUNS_ROOT, fail


class ExportFormat(str, Enum):
    lerobot = "lerobot"
    openvla = "openvla"


def export(
    run: Annotated[str, typer.Argument(help="run id (a directory under --runs)")],
    out: Annotated[Path, typer.Argument(help="directory to write (must not exist or be empty)")],
    format: Annotated[Optional[ExportFormat], typer.Option("--format", "-f", help="checkpoint format to write "
                                                           "(default: the run's checkpoint's own)")] = None,
    runs: Annotated[Path, typer.Option(help="directory of run directories")] = RUNS_ROOT,
) -> None:
    """Write the run's latest checkpoint in its checkpoint's format: a LeRobot policy directory
    (pi0, pi05, smolvla runs) or an OpenVLA directory (openvla, openvla-oft): the checkpoint it
    started from with the trained tensors applied, LoRA adapters merged into their weights;
    config, processors, statistics and tokenizer files copied unchanged."""
    from ...learn.vla.checkpoint import CheckpointError
    from ...learn.vla import lerobot_format, openvla_format
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
    formats = {"lerobot": lerobot_format.LEROBOT_FAMILIES, "openvla": openvla_format.OPENVLA_FAMILIES}
    if format is None:
        format = next((ExportFormat(f) for f, families in formats.items() if task.policy in families), ExportFormat.lerobot)
    if task.policy not in formats[format.value]:
        raise fail(f"{topo_file}: task.policy {task.policy!r} has no {format.value} format (--format {format.value} "
                   f"exports {', '.join(formats[format.value])})")
    kwargs = task.policy_kwargs
    spec = str(kwargs.get("checkpoint", ""))
    try:
        if format == ExportFormat.openvla:
            io: Any = openvla_format
            ck = io.check_openvla(spec, task.policy, dataset=kwargs.get("dataset"), chunk_size=kwargs.get("chunk_size"))
        else:
            io = lerobot_format
            ck = io.check_lerobot(spec, task.policy, tokenizer=kwargs.get("tokenizer"))
        current = read_current(run_dir / "checkpoints")
        if current is None:
            raise fail(f"{run_dir / 'checkpoints'}: no checkpoint written yet")
        version, trained = current
        merged = merge_trained(io.read_state_dict(ck), trained, lora_scaling(kwargs.get("lora")))
        if format == ExportFormat.openvla:  # OFT's heads as they came, or as trained (train_heads: true)
            heads = None
            if any(k.startswith("heads.") for k in trained):
                heads = {name: {**sd, **{k[len(f"heads.{name}."):]: v for k, v in trained.items()
                                         if k.startswith(f"heads.{name}.")}}
                         for name, sd in io.read_oft_components(ck).items()}
            path = io.export_openvla(ck, merged, out, heads=heads)
        else:
            path = io.export_lerobot(ck, merged, out, metadata={"dvla.run": run, "dvla.version": str(version),
                                                               "dvla.lora": "merged" if kwargs.get("lora") else "none"})
    except (CheckpointError, RunCheckpointError, ValueError) as err:
        raise fail(str(err)) from None
    typer.echo(f"wrote {run} version {version} ({task.policy}, LoRA {'merged' if kwargs.get('lora') else 'none'}) to {path}")

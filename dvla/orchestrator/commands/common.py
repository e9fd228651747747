"""Helpers shared by commands: loading a topology with one-line errors, finding a run, the
output format option."""

from __future__ import annotations

import json
import os
from enum import Enum
from pathlib import Path

import typer

from ...config import Topology
from ..topology import TopologyError, load_topology

#: directory of run directories (DVLA_RUNS overrides it)
RUNS_ROOT = Path(os.environ.get("DVLA_RUNS", "runs"))


class Format(str, Enum):
    """`--format` of the commands that render: a table for people, JSON for programs."""

    table = "table"
    json = "json"


def fail(message: str, code: int = 2) -> typer.Exit:
    typer.echo(f"dvla: {message}", err=True)
    return typer.Exit(code)


def topology_or_exit(path: Path) -> Topology:
    try:
        return load_topology(path)
    except TopologyError as err:
        typer.echo(str(err), err=True)
        raise typer.Exit(2)
    except OSError as err:
        raise fail(f"{path}: cannot read topology: {err.strerror or err}")


def find_run(run: str | None, runs_root: Path) -> tuple[str, dict]:
    """The named run, or the newest live one under `runs_root`; returns (run id, state.json)."""
    if run is not None:
        if run.endswith((".yaml", ".yml")) and Path(run).exists():
            run = topology_or_exit(Path(run)).run
        state = runs_root / run / "state.json"
        if not state.exists():
            raise fail(f"run {run!r} is not up (no {state})")
        return run, json.loads(state.read_text())
    live = sorted(runs_root.glob("*/state.json"), key=lambda p: p.stat().st_mtime, reverse=True)
    if not live:
        raise fail(f"no run is up under {runs_root}/ (start one with `dvla up TOPOLOGY`)")
    return live[0].parent.name, json.loads(live[0].read_text())



"""`dvla bench ...`: benchmarks that compare against a baseline measured in the same run."""

from __future__ import annotations

import typer

app = typer.Typer(help="Benchmarks (each writes JSON with ratios against an in-run baseline).", no_args_is_help=True)

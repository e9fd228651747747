"""The `dvla` command line: one Typer app, one module per command under `commands/`; `dvla bench`
is the benchmarks package's app (benchmarks/cli.py), which imports each harness when it runs."""

from __future__ import annotations

import typer

from benchmarks.cli import app as bench_app

from .commands import convert, doctor, down, export, identity, join, logs, plan, status, up

app = typer.Typer(
    name="dvla",
    help="Distributed asynchronous RL for vision-language-action policies over Eclipse Zenoh.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
app.command("up")(up.up)
app.command("status")(status.status)
app.command("down")(down.down)
app.command("logs")(logs.logs)
app.command("plan")(plan.plan)
app.command("doctor")(doctor.doctor)
app.command("export")(export.export)
app.command("convert")(convert.convert)
app.command("join")(join.join)
app.add_typer(identity.app, name="identity")
app.add_typer(bench_app, name="bench")


def main() -> None:
    app()


if __name__ == "__main__":
    main()

"""The CLI surface, through Typer's CliRunner: help, validation errors, plan output."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from dvla.orchestrator.cli import app
from dvla.orchestrator.topology import parse_topology, topology_to_dict

ROOT = Path(__file__).resolve().parents[2]
runner = CliRunner()


def test_help_lists_commands() -> None:
    res = runner.invoke(app, ["--help"])
    assert res.exit_code == 0
    for cmd in ("up", "status", "down", "logs", "plan", "bench"):
        assert cmd in res.output


def test_plan_json_round_trips_the_topology() -> None:
    res = runner.invoke(app, ["plan", str(ROOT / "topologies/local.yaml"), "--format", "json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.output)
    names = {p["name"] for p in doc["processes"]}
    assert "actor-node0-0" in names and len(names) == 5
    from dvla.orchestrator.topology import load_topology

    assert doc["topology"] == json.loads(json.dumps(topology_to_dict(load_topology(ROOT / "topologies/local.yaml"))))


def test_plan_table_shows_tree() -> None:
    res = runner.invoke(app, ["plan", str(ROOT / "topologies/8node.yaml")])
    assert res.exit_code == 0, res.output
    assert "weight tree:" in res.output and "replicator-r1n0-0" in res.output


def test_bad_topology_is_one_line_per_problem(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("run: x\nracks:\n  - name: r\n    nodes:\n      - name: n\n        roles: [{role: learner}]\n")
    res = runner.invoke(app, ["plan", str(bad)])
    assert res.exit_code == 2
    assert "bad.yaml:6" in res.output and "learner" in res.output


def test_up_rejects_bad_options() -> None:
    res = runner.invoke(app, ["up", str(ROOT / "topologies/tiny.yaml"), "--mode", "fast"])
    assert res.exit_code == 2 and "--mode" in res.output
    res = runner.invoke(app, ["up", str(ROOT / "topologies/tiny.yaml"), "--until-success", "1.5"])
    assert res.exit_code == 2 and "--until-success" in res.output


def test_status_without_run_names_the_problem(tmp_path: Path) -> None:
    res = runner.invoke(app, ["status", "--runs", str(tmp_path)])
    assert res.exit_code == 2 and "no run is up" in res.output


def test_missing_topology_file(tmp_path: Path) -> None:
    res = runner.invoke(app, ["plan", str(tmp_path / "nope.yaml")])
    assert res.exit_code == 2 and "nope.yaml" in res.output


def test_status_is_bounded_when_the_control_plane_accepts_but_never_answers(tmp_path: Path) -> None:
    """A run ending under `dvla status`: its listener still accepts connections, nothing answers.
    The command gives up after --connect-timeout, not after Zenoh's own 10 s handshake limit."""
    import socket

    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen(16)
    run = tmp_path / "gone"
    (run / "roles").mkdir(parents=True)
    (run / "secret").write_text("ab" * 32)
    (run / "state.json").write_text(json.dumps({
        "run": "gone", "ctrl_entry": [f"tcp/127.0.0.1:{silent.getsockname()[1]}"], "secret_file": str(run / "secret")}))
    try:
        res = runner.invoke(app, ["status", "gone", "--runs", str(tmp_path), "--connect-timeout", "1", "--timeout", "1"])
    finally:
        silent.close()
    # the open gave up on --connect-timeout ("unreachable"), not on the command's own wait for an
    # answer ("no answer ... within"), which a session held up by Zenoh's 10 s handshake would hit
    assert res.exit_code == 2 and "run gone: control plane unreachable" in res.output, res.output

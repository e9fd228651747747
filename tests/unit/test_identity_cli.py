"""Tests of `dvla identity issue|revoke` (credentials for producers outside the topology) and of
the `revoke` command's effect on a receiving fabric."""

from __future__ import annotations

import stat
from typer.testing import CliRunner

from dvla.fabric.codec import CodecError, decode, encode
from dvla.fabric.identity import Identity, read_revoked
from dvla.fabric.messages import Command
from dvla.orchestrator.cli import app
from dvla.orchestrator.ssh import write_private

runner = CliRunner()


def _run_dir(tmp_path, run="outrun") -> Identity:
    (tmp_path / run).mkdir()
    op = Identity.operator(run)
    write_private(tmp_path / run / "operator.id", op.to_text())
    return op


def test_issue_writes_a_private_credential_certified_by_the_operator(tmp_path):
    op = _run_dir(tmp_path)
    out = tmp_path / "robot.id"
    res = runner.invoke(app, ["identity", "issue", "outrun", "--kind", "rollout", "--name", "robot-1",
                              "-o", str(out), "--runs", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert stat.S_IMODE(out.stat().st_mode) == 0o600
    text = out.read_text()
    assert text.startswith("dvla-id1:outrun:rollout:robot-1:")
    cred = Identity.from_text(text)  # checks the certificate against the operator key it names
    assert (cred.run, cred.kind, cred.name, cred.operator_public) == ("outrun", "rollout", "robot-1", op.public)


def test_issue_refuses_weight_publishers_bad_names_and_unknown_runs(tmp_path):
    _run_dir(tmp_path)
    base = ["identity", "issue", "outrun", "-o", str(tmp_path / "x.id"), "--runs", str(tmp_path)]
    for extra, words in ((["--kind", "actor", "--name", "a"], "--kind 'actor'"),
                         (["--name", "bad/name"], "--name"),
                         (["--kind", "operator", "--name", "a"], "--kind 'operator'")):
        res = runner.invoke(app, base + extra)
        assert res.exit_code == 2 and words in res.output, res.output
    res = runner.invoke(app, ["identity", "issue", "nope", "--name", "a", "-o", str(tmp_path / "y.id"), "--runs", str(tmp_path)])
    assert res.exit_code == 2 and "no operator key" in res.output
    assert not (tmp_path / "x.id").exists()


def test_revoke_records_the_name_and_a_revoked_name_is_not_reissued(tmp_path):
    _run_dir(tmp_path)
    res = runner.invoke(app, ["identity", "revoke", "outrun", "robot-1", "--runs", str(tmp_path)])
    assert res.exit_code == 0 and "not up" in res.output, res.output
    assert read_revoked(tmp_path / "outrun") == {"robot-1"}
    assert stat.S_IMODE((tmp_path / "outrun" / "revoked").stat().st_mode) == 0o600
    res = runner.invoke(app, ["identity", "issue", "outrun", "--name", "robot-1", "-o", str(tmp_path / "r.id"),
                              "--runs", str(tmp_path)])
    assert res.exit_code == 2 and "revoked" in res.output


def test_revoke_command_needs_a_name():
    ok = Command(target="all", verb="revoke", args={"name": "robot-1"}, issued_ns=1)
    assert decode(encode(ok)) == ok
    for args in ({}, {"name": 3}, {"name": ""}):
        try:
            Command(target="all", verb="revoke", args=args, issued_ns=1).validate()
        except CodecError as err:
            assert err.reason == "schema"
        else:
            raise AssertionError(f"revoke with {args} accepted")

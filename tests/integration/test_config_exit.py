"""A role that cannot start with its configuration (an env or a checkpoint to fix) exits with the
config code and is not restarted: the run ends at once as `role_failed`, the role's log ends with
the one line naming the setting, and no restart backoff is spent on it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.integration.test_up_e2e import ROOT, free_port_block, pids_of_run

FACTORY = '''
from dvla.learn.spec import EnvSetupError


def make(task, seed):
    raise EnvSetupError("task.env: refusal_env:make refuses on purpose (set task.env to a real env)")
'''

TOPOLOGY = """
run: refused
task:
  env: refusal_env:make
  obs_mode: state
  budget: {max_env_steps: 1000}
racks:
  - name: r0
    nodes:
      - name: n0
        roles: [{role: actor}, {role: rollout}]
"""


@pytest.mark.timeout(180)
def test_a_role_that_cannot_start_is_not_restarted(tmp_path: Path) -> None:
    (tmp_path / "refusal_env.py").write_text(FACTORY)
    (tmp_path / "refused.yaml").write_text(TOPOLOGY)
    up = subprocess.run(
        [sys.executable, "-m", "dvla", "up", "refused.yaml", "--runs", "runs", "--base-port", str(free_port_block()),
         "--quiet"], cwd=tmp_path, capture_output=True, text=True, timeout=160,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))},
    )
    run_dir = tmp_path / "runs" / "refused"
    assert up.returncode != 0, up.stdout + up.stderr
    result = json.loads((run_dir / "result.json").read_text())
    assert result["reason"].startswith("role_failed:"), result
    assert "not restarted" in up.stdout + up.stderr
    log = (run_dir / "logs" / "actor-n0-0.log").read_text()
    assert "refuses on purpose" in log and "Traceback" not in log
    assert log.count("--- start") == 1  # started once, never again
    assert pids_of_run(run_dir) == []

"""The run plot: written for runs with and without evaluations, without warnings."""

from __future__ import annotations

import warnings

import pytest

from dvla.orchestrator.plots import plot_run

pytest.importorskip("matplotlib")

METRICS = "time_s,steps_per_s,policy_lag_mean\n10,500,0.1\n20,520,0.2\n"
EVALS = "time_s,success_once,success_at_end\n15,0.25,0.0\n25,0.75,0.5\n"


@pytest.mark.parametrize("with_evals", [True, False])
def test_plot_run_writes_a_png_without_warnings(tmp_path, with_evals):
    (tmp_path / "metrics.csv").write_text(METRICS)
    if with_evals:
        (tmp_path / "evals.csv").write_text(EVALS)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # e.g. "No artists with labels found to put in legend"
        out = plot_run(tmp_path)
    assert out == tmp_path / "plots" / "training.png"
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

"""`dvla bench envs` without running it: kinds it cannot run are skipped with the reason, and the
table names every figure of the kinds it ran (tests/integration runs the real benches)."""

from __future__ import annotations

import pytest

from benchmarks.envs import KINDS, format_table, unavailable


def test_unknown_kind_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown env kind 'mujoco'"):
        unavailable("mujoco")
    assert set(KINDS) == {"maniskill-cpu", "maniskill-gpu", "libero"}


def test_the_gpu_kind_says_why_it_cannot_run_on_a_cpu_machine() -> None:
    import torch

    pytest.importorskip("mani_skill")
    if torch.cuda.is_available():
        assert unavailable("maniskill-gpu") is None
    else:
        assert "no CUDA device" in unavailable("maniskill-gpu")


def test_table_of_a_run_and_a_skipped_kind() -> None:
    doc = {"placement": "split", "kinds": {
        "maniskill-cpu": {"skipped": "mani_skill is not installed"},
        "libero": {"sim_only_sps": 4.0, "async_sps": 3.6, "async_over_sim_only": 0.9,
                   "async_over_sim_only_equal_step_cost": 0.92,
                   "env_costs": {"reset_s": 0.25, "task_switch_s": 1.9, "step_ms_rendered": 139.0,
                                 "step_ms_physics": 15.0, "render_ms_per_step": 124.0, "render_ms_per_image": 70.0,
                                 "image_size": 64, "cameras": 2, "max_rss_mib": 2400.0}},
    }}
    text = format_table(doc)
    assert "maniskill-cpu  skipped: mani_skill is not installed" in text
    assert "ratio 0.900, at equal step cost 0.920 (goal >= 0.9: met)" in text
    assert "reset 0.25 s, task switch 1.90 s" in text and "render 124.0 ms per step" in text

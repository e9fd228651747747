"""`dvla bench vla --quick --families-only`: the Hugging Face families' bench machinery (a random
checkpoint of real transformers classes, rendered envs, chunks on the codec, learner processes
with and without micro-batching, JSON), not its speed."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def finite(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def positive(x: object) -> bool:  # for byte counts and memory
    return finite(x) and x > 0  # type: ignore[operator]


@pytest.mark.timeout(400)
def test_bench_vla_quick_measures_both_families(tmp_path: Path) -> None:
    out = tmp_path / "vla.json"
    proc = subprocess.run(
        [sys.executable, "-m", "dvla", "bench", "vla", "--json", str(out), "--quick", "--families-only"],
        cwd=ROOT, capture_output=True, text=True, timeout=380,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    doc = json.loads(out.read_text())
    assert doc["command"].startswith("dvla bench vla") and doc["rollout"] is None
    fam = doc["hf_families"]
    assert fam["device"] == "cpu" and fam["lora_r"] == 4 and set(fam["families"]) == {"tokens", "flow"}
    extras = {"tokens": 4 * 8, "flow": 4 * 5 * 8}  # action bins int32 [8]; chain float32 [K+1=5, 8]
    for name, f in fam["families"].items():
        assert 0 < f["replicated_fraction"] <= 0.05, f
        assert f["bytes_per_full_version"] == 4 * f["replicated_values"]
        for key in ("env_steps_per_s", "act_ms_p50", "act_ms_p99"):
            assert finite(f[key]), (name, key, f[key])
        assert f["act_ms_p50"] <= f["act_ms_p99"] and positive(f["bytes_per_env_step"]), f
        # the extras' bytes per env step: their data plus a few bytes of msgpack per chunk
        assert extras[name] <= f["extras_bytes_per_env_step"] < extras[name] + 40, f
        lr = f["learner"]
        assert lr["micro_batch"] < lr["minibatch"]
        for setting in ("whole", "micro"):
            assert finite(lr[setting]["update_s"]) and positive(lr[setting]["peak_rss_mb"])
            assert lr[setting]["peak_gpu_mb"] is None
    assert "vla-tokens" in proc.stdout and "micro-batches of" in proc.stdout

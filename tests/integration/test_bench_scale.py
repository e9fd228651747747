"""`dvla bench scale` on the emulated 8-node cluster with tiny versions: the machinery (CPU
calibration on three nodes, the real weight tree in network namespaces, the model's predictions,
link counters, JSON), not the figures: no timing ratio is asserted.

Checks the document's structure, that the calibration and the measured transfer are present and
finite and the ratios computed from them, and that no namespace of the bench is left behind.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.scale import CAL_RUN, leftover_namespaces, run_name

from .test_netns import _netns_usable

pytestmark = [
    pytest.mark.netns,
    pytest.mark.skipif(not _netns_usable(), reason="needs root and `ip netns`"),
]

ROOT = Path(__file__).resolve().parents[2]


def finite(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def positive(x: object) -> bool:  # for the model's figures (the topology's links and sizes), not the measured ones
    return finite(x) and x > 0  # type: ignore[operator]


@pytest.mark.timeout(150)
def test_bench_scale_8_nodes_measures_and_predicts(tmp_path: Path) -> None:
    out = tmp_path / "bench" / "scale.json"
    cmd = [sys.executable, "-m", "dvla", "bench", "scale", "--json", str(out), "--topologies",
           str(ROOT / "topologies" / "8node.yaml"), "--size-mib", "4", "--versions", "1", "--calibration-versions", "1"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=130)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert not leftover_namespaces([CAL_RUN, run_name(8)])
    doc = json.loads(out.read_text())
    assert doc["command"].startswith("dvla bench scale") and finite(doc["elapsed_s"])
    assert doc["machine"]["cpus"] >= 1 and doc["netns_left"] == []
    assert doc["size_bytes"] == 4 << 20 and doc["versions"] == 1

    cal = doc["calibration"]
    for kind in ("source", "relay", "sink"):
        assert finite(cal[f"{kind}_s_per_mib"]) and cal[f"{kind}_s_per_mib"] == cal["cpu_s_per_mib"][kind], cal
    assert cal["shared_cores"] == doc["machine"]["cpus"] and len(cal["run"]["versions"]) == 2

    (row,) = doc["rows"]
    assert row["nodes"] == 8 and row["racks"] == 2 and row["sinks"] == 8 and row["relays"] == 2
    assert row["processes"] == 11  # actor, 2 replicators, 8 rollouts: the evaluator is left out
    for key in ("measured_s", "measured_min_s", "measured_max_s", "predicted_s", "predicted_over_measured",
                "predicted_no_cpu_over_measured"):
        assert finite(row[key]), (key, row[key])
    for key in ("predicted_no_cpu_s", "bound_s", "busiest_link_s"):  # the links' rates and the bytes counted
        assert positive(row[key]), (key, row[key])
    assert row["measured_min_s"] <= row["measured_s"] <= row["measured_max_s"]
    assert row["predicted_over_measured"] == pytest.approx(row["predicted_s"] / row["measured_s"])
    assert row["predicted_no_cpu_over_measured"] == pytest.approx(row["predicted_no_cpu_s"] / row["measured_s"])
    versions = row["tree"]["versions"]
    assert [v["warmup"] for v in versions] == [True, False]
    assert len(versions[1]["per_sink_s"]) == 8 and all(finite(t) for t in versions[1]["per_sink_s"].values())
    # every tree edge between nodes crosses links the model counts, and the counters saw the bytes
    model_links = {k: v for k, v in row["links"].items() if v["model_copies"]}
    assert model_links and all(v["copies"] > 0 for v in model_links.values())
    assert {"source", "relay", "sink"} <= set(row["cpu_s_per_mib"])
    assert "nodes" in proc.stdout and "wrote" in proc.stdout

"""docs/topology.md is generated from dvla/config.py: it must list every key, as the schema says."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from dvla import config
from dvla.orchestrator import topology_doc
from dvla.orchestrator.topology import LOADER_OWNED

DOC = Path(__file__).resolve().parents[2] / "docs" / "topology.md"


def test_docs_topology_md_is_the_generated_page():
    assert DOC.read_text() == topology_doc.render(), (
        "docs/topology.md is stale: python -m dvla.orchestrator.topology_doc > docs/topology.md"
    )


def test_every_key_of_the_schema_is_documented_with_its_comment():
    page = topology_doc.render()
    for cls in (config.Topology, config.TaskConfig, config.PPOConfig, config.ReplicationConfig, config.TlsConfig,
                config.NodeConfig, config.SshConfig):
        comments = topology_doc.field_comments(cls)
        for f in dataclasses.fields(cls):
            if cls is config.Topology and f.name in LOADER_OWNED:
                continue
            assert comments.get(f.name), f"{cls.__name__}.{f.name} has no #: comment"
            assert f"| `{f.name}` |" in page and comments[f.name] in page, f"{cls.__name__}.{f.name}"

"""TLS on the planes: real Zenoh sessions over TLS sockets with certificates made here.

Each test builds its own CA, a server and a client certificate (and, for mTLS refusal, a second
CA with a certificate of its own) under pytest's tmp_path, then checks that the fabric's data
and ctrl planes work over `tls/` locators, and that a plain-TCP client or a client whose
certificate another CA signed gets nothing through.
"""

from __future__ import annotations

import dataclasses
import datetime
import ipaddress
import socket
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from dvla.fabric import Command, Fabric, TlsFiles, TrajectoryChunk, plane_config

cryptography = pytest.importorskip("cryptography")
from cryptography import x509  # noqa: E402
from cryptography.hazmat.primitives import hashes, serialization  # noqa: E402
from cryptography.hazmat.primitives.asymmetric import ec  # noqa: E402
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID  # noqa: E402

RUN = "tls"
SECRET = b"tls-test-secret-0123456789abcdef"


# ----------------------------------------------------------------------------- certificates

def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _save(directory: Path, stem: str, key: ec.EllipticCurvePrivateKey, cert: x509.Certificate) -> None:
    (directory / f"{stem}.key").write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    (directory / f"{stem}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _builder(subject: str, issuer: x509.Name, public_key: object) -> x509.CertificateBuilder:
    now = datetime.datetime.now(datetime.timezone.utc)
    return (
        x509.CertificateBuilder().subject_name(_name(subject)).issuer_name(issuer).public_key(public_key)
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(now + datetime.timedelta(hours=2))
    )


def make_ca(directory: Path, stem: str) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    key = ec.generate_private_key(ec.SECP256R1())
    usage = x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
                          key_encipherment=False, data_encipherment=False, key_agreement=False,
                          encipher_only=False, decipher_only=False)
    cert = (
        _builder(f"dvla test {stem}", _name(f"dvla test {stem}"), key.public_key())
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(usage, critical=True)
        .sign(key, hashes.SHA256())
    )
    _save(directory, stem, key, cert)
    return key, cert


def make_leaf(directory: Path, stem: str, ca: tuple[ec.EllipticCurvePrivateKey, x509.Certificate]) -> None:
    """A certificate for 127.0.0.1 / localhost, usable by both listening and connecting sides."""
    ca_key, ca_cert = ca
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        _builder(stem, ca_cert.subject, key.public_key())
        .add_extension(x509.SubjectAlternativeName(
            [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                       critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    _save(directory, stem, key, cert)


@dataclasses.dataclass(frozen=True)
class Pki:
    server: TlsFiles
    client: TlsFiles
    rogue: TlsFiles  # signed by another CA, trusting our CA


@pytest.fixture
def pki(tmp_path: Path) -> Pki:
    ca = make_ca(tmp_path, "ca")
    other = make_ca(tmp_path, "other-ca")
    make_leaf(tmp_path, "server", ca)
    make_leaf(tmp_path, "client", ca)
    make_leaf(tmp_path, "rogue", other)

    def files(stem: str) -> TlsFiles:
        return TlsFiles(root_ca=str(tmp_path / "ca.pem"), cert=str(tmp_path / f"{stem}.pem"),
                        key=str(tmp_path / f"{stem}.key"), mtls=True)

    return Pki(server=files("server"), client=files("client"), rogue=files("rogue"))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def chunk(name: str, seq: int) -> TrajectoryChunk:
    t, n = 4, 2
    rng = np.random.default_rng(seq)
    obs = rng.standard_normal((t, n, 3), dtype=np.float32)
    return TrajectoryChunk(
        rollout=name, seq=seq, policy_version=1, env_steps=t * n, obs={"state": obs},
        actions=rng.standard_normal((t, n, 2), dtype=np.float32), logprobs=np.zeros((t, n), np.float32),
        rewards=np.ones((t, n), np.float32), terminated=np.zeros((t, n), bool), truncated=np.zeros((t, n), bool),
        success=np.zeros((t, n), bool), next_obs={"state": obs[-1].copy()}, final_obs={"state": np.zeros_like(obs)},
    )


def _wait(pred, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.02)
    return pred()


# ----------------------------------------------------------------------------- tests

@pytest.mark.timeout(60)
def test_both_planes_over_tls_carry_chunks_and_signed_commands(pki: Pki) -> None:
    ctrl_port, data_port = free_port(), free_port()
    sink = Fabric(run=RUN, name="actor", secret=SECRET,
                  ctrl_conf=plane_config(mode="router", listen=[f"tls/127.0.0.1:{ctrl_port}"], tls=pki.server),
                  data_conf=plane_config(mode="peer", listen=[f"tls/127.0.0.1:{data_port}"], tls=pki.server))
    source = None
    try:
        inbox = sink.subscribe_traj(maxsize=8, expect=TrajectoryChunk)
        source = Fabric(run=RUN, name="sampler", secret=SECRET,
                        ctrl_conf=plane_config(mode="client", connect=[f"tls/127.0.0.1:{ctrl_port}"], tls=pki.client),
                        data_conf=plane_config(mode="peer", connect=[f"tls/127.0.0.1:{data_port}"], tls=pki.client))
        commands = source.subscribe_ctrl(source.keys.cmd("sampler"), 8, Command)
        # Routes appear asynchronously: repeat until one of each arrives, then check content.
        got_chunk = got_cmd = None
        deadline = time.monotonic() + 15
        seq = 0
        while (got_chunk is None or got_cmd is None) and time.monotonic() < deadline:
            if got_chunk is None:
                source.publish_traj(chunk("sampler", seq))
                seq += 1
                got_chunk = inbox.get(timeout=0.1)
            if got_cmd is None:
                sink.publish_ctrl(sink.keys.cmd("sampler"), Command(target="sampler", verb="pause"))
                got_cmd = commands.get(timeout=0.1)
        assert got_chunk is not None, sink.accounting.snapshot()
        assert got_cmd is not None, source.accounting.snapshot()
        expected = chunk("sampler", got_chunk.seq)
        assert got_chunk.rollout == "sampler"
        np.testing.assert_array_equal(got_chunk.obs["state"], expected.obs["state"])
        np.testing.assert_array_equal(got_chunk.actions, expected.actions)
        sender, cmd = got_cmd
        assert (sender, cmd.verb, cmd.target) == ("actor", "pause", "sampler")
        # the links really are TLS: each session's only peer/router is across a tls/ locator
        assert len(list(sink.data.info.peers_zid())) == 1
        assert sink.accounting.get("data", "rejected") == 0 and source.accounting.get("ctrl", "rejected") == 0
    finally:
        if source is not None:
            source.close()
        sink.close()


def _reaches(listener_port: int, client_conf: zenoh.Config, listener_tls: TlsFiles) -> bool:
    """Whether a put from a session opened with `client_conf` arrives at a TLS listener."""
    listener = zenoh.open(plane_config(mode="peer", listen=[f"tls/127.0.0.1:{listener_port}"], tls=listener_tls))
    got: list[bytes] = []
    try:
        sub = listener.declare_subscriber("dvla/tls/probe", lambda s: got.append(s.payload.to_bytes()))
        client = zenoh.open(client_conf)
        try:
            deadline = time.monotonic() + 3.0
            while not got and time.monotonic() < deadline:
                client.put("dvla/tls/probe", b"hello")
                time.sleep(0.05)
            return bool(got) and list(listener.info.peers_zid()) != []
        finally:
            client.close()
            sub.undeclare()
    finally:
        listener.close()


@pytest.mark.timeout(60)
def test_plain_tcp_and_foreign_ca_clients_are_refused(pki: Pki) -> None:
    port = free_port()
    tls_client = plane_config(mode="peer", connect=[f"tls/127.0.0.1:{port}"], tls=pki.client)
    assert _reaches(port, tls_client, pki.server), "the positive control failed: TLS client did not get through"
    port = free_port()
    assert not _reaches(port, plane_config(mode="peer", connect=[f"tcp/127.0.0.1:{port}"]), pki.server)
    port = free_port()
    rogue = plane_config(mode="peer", connect=[f"tls/127.0.0.1:{port}"], tls=pki.rogue)
    assert not _reaches(port, rogue, pki.server), "mTLS let in a certificate from another CA"
    # without mTLS the listener does not ask for a certificate, so the same client gets in
    port = free_port()
    open_listener = dataclasses.replace(pki.server, mtls=False)
    rogue_no_mtls = plane_config(mode="peer", connect=[f"tls/127.0.0.1:{port}"],
                                 tls=dataclasses.replace(pki.rogue, mtls=False))
    assert _reaches(port, rogue_no_mtls, open_listener)


def test_plane_config_refuses_mixed_schemes_and_missing_files(pki: Pki, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"'tcp/127.0.0.1:1'.*tls/host:port"):
        plane_config(listen=["tcp/127.0.0.1:1"], tls=pki.server)
    with pytest.raises(ValueError, match=r"'tls/127.0.0.1:1'.*needs tls="):
        plane_config(connect=["tls/127.0.0.1:1"])
    missing = dataclasses.replace(pki.server, key=str(tmp_path / "nope.key"))
    with pytest.raises(ValueError, match=r"tls.key: file not found: .*nope.key"):
        plane_config(listen=["tls/127.0.0.1:1"], tls=missing)


@pytest.mark.timeout(60)
def test_topology_tls_section_reaches_the_roles_sessions(pki: Pki, tmp_path: Path, monkeypatch) -> None:
    """topology `tls:` -> plan (tls/ locators on the chosen planes) -> RoleConfig JSON -> the
    role's own `open_fabric`: the actor and a rollout talk over TLS ctrl and plain-TCP data."""
    from dvla.config import RoleConfig
    from dvla.orchestrator.plan import make_plan
    from dvla.orchestrator.topology import TopologyError, parse_topology
    from dvla.roles.runtime import open_fabric

    monkeypatch.setenv("DVLA_SECRET", SECRET.hex())  # what `dvla up` hands every role
    root = Path(__file__).resolve().parents[2]
    text = (root / "topologies" / "local.yaml").read_text()
    tls = (f"\ntls:\n  root_ca: {pki.server.root_ca}\n  cert: {pki.server.cert}\n  key: {pki.server.key}\n"
           f"  planes: [ctrl]\n")
    topo = parse_topology(text + tls, str(root / "topologies" / "local.yaml"))
    with pytest.raises(TopologyError, match=r"tls.cert: TLS file not found: .*missing.pem"):
        parse_topology(text + tls.replace(pki.server.cert, "missing.pem"), str(root / "topologies" / "local.yaml"))
    plan = make_plan(topo, str(tmp_path / "run"), base_port=free_port())
    configs = {p.config.kind: RoleConfig.from_json(p.config.to_json()) for p in plan.processes}
    actor, rollout = configs["actor"], configs["rollout"]
    assert all(ep.startswith("tls/") for ep in (*actor.ctrl.listen, *rollout.ctrl.connect, *plan.ctrl_entry))
    assert all(ep.startswith("tcp/") for ep in (*actor.data.listen, *rollout.data.connect))
    assert actor.ctrl.tls is not None and actor.data.tls is None
    # the replicator is the rollout's parent; point the rollout at the actor's router only
    rollout = dataclasses.replace(rollout, ctrl=dataclasses.replace(rollout.ctrl, connect=actor.ctrl.listen))
    a = open_fabric(actor)
    r = None
    try:
        r = open_fabric(rollout)
        commands = r.subscribe_ctrl(r.keys.cmd(rollout.name), 8, Command)
        inbox = a.subscribe_traj(maxsize=8, expect=TrajectoryChunk)
        got_cmd = got_chunk = None
        deadline = time.monotonic() + 15
        seq = 0
        while (got_cmd is None or got_chunk is None) and time.monotonic() < deadline:
            if got_cmd is None:
                a.publish_ctrl(a.keys.cmd(rollout.name), Command(target=rollout.name, verb="checkpoint"))
                got_cmd = commands.get(timeout=0.1)
            if got_chunk is None:
                r.publish_traj(chunk(rollout.name, seq))
                seq += 1
                got_chunk = inbox.get(timeout=0.1)
        assert got_cmd is not None and got_cmd[1].verb == "checkpoint"
        assert got_chunk is not None and got_chunk.rollout == rollout.name
    finally:
        if r is not None:
            r.close()
        a.close()

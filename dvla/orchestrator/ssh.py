"""Remote nodes over SSH: a node whose host is not this machine runs its roles through OpenSSH.

Both halves of one small protocol (docs/cluster.md walks it): the local :class:`SshWrapper`
starts ``ssh ... HOST -- PYTHON -m dvla.orchestrator.ssh serve`` and writes the role's config and
secrets as one JSON line on its stdin (never a command line); the remote :func:`serve` runs the
role, stops it when that stdin closes (how the orchestrator, or its death, says stop), and sends
the role's result files back as a tar that the local side checks member by member. A remote run
directory is only deleted when it carries dvla's token file (:func:`run_dir_action`). The Slurm
launcher (dvla.orchestrator.slurm) runs the same remote half as a job step, through srun.
"""

from __future__ import annotations

import fcntl
import io
import json
import logging
import os
import platform
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tarfile
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import dvla

from ..config import SshConfig, Topology
from ..fabric.identity import IDENTITY_ENV
from .launcher import die_with_parent, killpg, last_line
from .process import CommandWrapper, Process, Supervised, is_local_host

log = logging.getLogger("dvla.ssh")

#: exit status of the ssh client itself failing (connection, authentication, host key)
SSH_FAILED = 255
#: seconds the remote side gives a role between SIGTERM and SIGKILL after a hang-up
REMOTE_STOP_GRACE_S = 10.0
#: environment variables a remote role gets from the orchestrator's environment, when set there
FORWARDED_ENV = ("DVLA_LOG_LEVEL", "OMP_NUM_THREADS", "PYTHONUNBUFFERED")
#: what a remote role may send back into the local run directory: its own files directly inside
#: these directories (directory -> what follows "<role>." there: ``summaries/<role>.json``,
#: ``counters/<role>.<incarnation>.<pid>``) and, from an actor, these top-level files; a result
#: tar holding anything else (checkpoints, configs, the secret...) is refused whole.
RESULT_DIRS = {"summaries": re.compile(r"json"), "counters": re.compile(r"[0-9]{1,10}\.[0-9]{1,10}")}
RESULT_FILES = ("versions.csv",)
#: the learner group's checkpoint, which travels with a remote rank-0 actor (docs/slurm.md,
#: "Resume"): its manifest, the version high-water mark and the two files of the checkpoint
#: directory the manifest names (the layout of docs/learners.md, "Checkpoints"); sent back with
#: the actor's results and, when a continued run starts it on a node, to that node
CHECKPOINT_MEMBER_RE = re.compile(r"checkpoints/(?:MANIFEST\.json|high_water\.json|v[0-9]{8}/(?:policy|optimizer)\.safetensors)")
#: marks a remote run directory as dvla's own: only a directory holding it is ever deleted
TOKEN_FILE = ".dvla-run-token"
#: exit status of `probe` when the remote run directory exists but is not dvla's
NOT_OURS = 3


class SshError(RuntimeError):
    """A remote node cannot be reached or cannot run dvla; the message is one line naming the host."""


class RunDirError(RuntimeError):
    """The remote run directory exists but is not dvla's own: it is left alone (one line, naming it)."""


class ResultsRefused(SshError):
    """A remote node's result tar holds something other than result files: nothing of it is unpacked."""


# ----------------------------------------------------------------------------------------------
# local half


@dataclass(frozen=True)
class SshTarget:
    """One remote host and how to log in to it."""

    host: str
    ssh: SshConfig

    @property
    def destination(self) -> str:
        host = self.host[1:-1] if self.host.startswith("[") else self.host  # ssh wants IPv6 bare
        return f"{self.ssh.user}@{host}" if self.ssh.user else host

    def label(self) -> str:
        """``user@host:port`` for messages (an IPv6 host in brackets)."""
        host = f"[{self.host}]" if ":" in self.host and not self.host.startswith("[") else self.host
        return f"{self.ssh.user}@{host}:{self.ssh.port}" if self.ssh.user else f"{host}:{self.ssh.port}"

    def argv(self, remote_command: str) -> list[str]:
        """The ssh client command line running `remote_command` (a shell string) on the host."""
        s = self.ssh
        opts = {
            "BatchMode": "yes",  # keys only: a password or passphrase prompt fails instead of hanging
            "PasswordAuthentication": "no",
            "KbdInteractiveAuthentication": "no",
            "StrictHostKeyChecking": s.host_key_check,
            "ConnectTimeout": str(s.connect_timeout_s),
            "ServerAliveInterval": "5",  # a dead network is noticed in ~15 s, and the run told
            "ServerAliveCountMax": "3",
            "ClearAllForwardings": "yes",
            "LogLevel": "ERROR",  # keeps banners and warnings out of the role's log
        }
        if s.known_hosts_file:
            opts["UserKnownHostsFile"] = s.known_hosts_file
        argv = ["ssh", "-T", "-p", str(s.port)]
        if s.identity_file:
            opts["IdentitiesOnly"] = "yes"
            argv += ["-i", s.identity_file]
        for key, value in opts.items():
            argv += ["-o", f"{key}={value}"]
        # "--" first: the destination is never read as an option (a host "-oProxyCommand=..."
        # would run a command here), whatever the topology's validation let through
        return argv + ["--", self.destination, remote_command]

    def python_command(self, *args: str) -> str:
        """Shell string running the remote Python with `args` (each quoted)."""
        return " ".join(shlex.quote(a) for a in (self.ssh.python, *args))


def check_host(target: SshTarget, prepare: tuple[str, str] | None = None) -> dict[str, Any]:
    """Log in once and return what the remote Python reports about itself; :class:`SshError` (one
    line) if the host, the login or the remote dvla fails. With `prepare` (remote run directory,
    run token) the remote side also makes that directory the run's (:func:`prepare_run_dir`)."""
    timeout = target.ssh.connect_timeout_s + 20
    argv = target.argv(target.python_command("-m", "dvla.orchestrator.ssh", "probe"))
    header = json.dumps({"run_dir": prepare[0], "token": prepare[1]}) + "\n" if prepare else ""
    try:
        proc = subprocess.run(argv, input=header, capture_output=True, text=True, timeout=timeout)
    except FileNotFoundError:
        raise SshError(f"ssh {target.label()}: the ssh client is not installed (apt-get install openssh-client)") from None
    except subprocess.TimeoutExpired:
        raise SshError(f"ssh {target.label()}: no answer in {timeout:.0f} s") from None
    if proc.returncode == SSH_FAILED:
        raise SshError(f"ssh {target.label()} failed: {last_line(proc.stderr)}")
    if proc.returncode == NOT_OURS:
        raise SshError(f"ssh {target.label()}: {last_line(proc.stderr)}")
    if proc.returncode != 0:
        raise SshError(f"ssh {target.label()}: remote python {target.ssh.python!r} cannot run dvla "
                       f"(exit {proc.returncode}): {last_line(proc.stderr)}")
    try:
        return json.loads(last_line(proc.stdout))
    except ValueError:
        raise SshError(f"ssh {target.label()}: unexpected probe answer {last_line(proc.stdout)!r}") from None


def remote_targets(topo: Topology) -> dict[str, SshTarget]:
    """Node name -> SSH target, for every node of `topo` whose host is not this machine."""
    return {n.name: SshTarget(n.host, topo.ssh_for(n)) for _r, n in topo.nodes() if not is_local_host(n.host)}


class SshWrapper(CommandWrapper):
    """Launches the processes of remote nodes over SSH; local ones go to `local` (or run as is)."""

    def __init__(self, topo: Topology, secret_hex: str, env: dict[str, str], local: CommandWrapper | None = None) -> None:
        self.topo = topo
        self.targets = remote_targets(topo)
        self.secret_hex = secret_hex
        self.env = {k: env[k] for k in FORWARDED_ENV if k in env}
        self.local = local or CommandWrapper()
        # One token per `dvla up`: the first role of a run to reach a node wipes what an earlier
        # run of the same id left in the remote run directory (a stale checkpoint would be resumed).
        self.token = uuid.uuid4().hex

    def target(self, proc: Process) -> SshTarget | None:
        return self.targets.get(proc.config.node)

    def remote_run_dir(self, target: SshTarget) -> str:
        return str(PurePosixPath(target.ssh.workdir) / self.topo.run)

    def in_place(self, target: SshTarget) -> bool:
        """Whether the role on `target` works in the orchestrator's own run directory (same
        filesystem: nothing to prepare or send back); never over SSH."""
        return False

    def check_all(self) -> None:
        """Probe every remote host once, in parallel, and prepare its run directory; raise one
        :class:`SshError` for the first failure."""
        targets = {t.label(): t for t in self.targets.values()}
        errors: dict[str, str] = {}

        def probe(label: str, t: SshTarget) -> None:
            try:
                info = check_host(t, prepare=(self.remote_run_dir(t), self.token))
                log.info("ssh %s ok: python %s, dvla at %s", label, info.get("python"), info.get("dvla"))
            except SshError as err:
                errors[label] = str(err)

        threads = [threading.Thread(target=probe, args=item, name=f"ssh-probe-{item[0]}") for item in targets.items()]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        if errors:
            raise SshError(errors[sorted(errors)[0]])

    # -- CommandWrapper ------------------------------------------------------------------------

    def __call__(self, proc: Process, argv: list[str]) -> list[str]:
        target = self.target(proc)
        if target is None:
            return self.local(proc, argv)
        return target.argv(target.python_command("-m", "dvla.orchestrator.ssh", "serve"))

    def fork_into(self, proc: Process) -> str | None:
        return self.local.fork_into(proc) if self.target(proc) is None else None

    def stdin_payload(self, proc: Process, argv: list[str], identity: str | None = None) -> bytes | None:
        target = self.target(proc)
        if target is None:
            return self.local.stdin_payload(proc, argv, identity)
        module = argv[argv.index("-m") + 1]  # the same entry point as a local launch
        header = {
            "module": module,
            "config": json.loads(proc.config.to_json()),
            "run_dir": self.remote_run_dir(target),
            "in_place": self.in_place(target),
            "token": self.token,
            "secret_env": proc.config.secret_env,
            "secret": self.secret_hex,
            "identity": identity,
            "env": self.env,
        }
        # a continued run's checkpoint goes to the node of its remote rank-0 actor, after the header
        attached = b"" if header["in_place"] or not writes_checkpoints(proc.config) else checkpoint_tar(Path(proc.config.run_dir))
        header["checkpoint_bytes"] = len(attached)
        return (json.dumps(header) + "\n").encode() + attached

    def output_path(self, sup: Supervised) -> Path | None:
        if self.target(sup.proc) is None:
            return self.local.output_path(sup)
        return sup.log_path.parent.parent / "remote" / f"{sup.name}.tar"

    def finished(self, sup: Supervised, code: int) -> str | None:
        target = self.target(sup.proc)
        if target is None:
            return self.local.finished(sup, code)
        path = self.output_path(sup)
        assert path is not None
        notes = []
        if code == SSH_FAILED:
            try:
                why = last_line(sup.log_path.read_text(errors="replace")[-4000:])
            except OSError:
                why = "(no log)"
            notes.append(f"{sup.name}: ssh {target.label()} failed: {why}")
        try:
            unpacked = unpack_results(path, sup.log_path.parent.parent, sup.name, target.label(),
                                      checkpoints=writes_checkpoints(sup.proc.config))
            if unpacked:
                log.info("%s: %d file(s) back from %s", sup.name, len(unpacked), target.host)
        except ResultsRefused as err:
            log.error("%s: %s", sup.name, err)
            notes.append(f"{sup.name}: {err}")
        except (OSError, tarfile.TarError) as err:
            log.warning("%s: results from %s unreadable: %s", sup.name, target.host, err)
        return "; ".join(notes) or None


def writes_checkpoints(config: Any) -> bool:
    """Whether the role of `config` (a RoleConfig, or its JSON form) writes the learner group's
    checkpoints: an actor of rank 0 (or the only actor)."""
    get = config.get if isinstance(config, dict) else lambda key: getattr(config, key, None)
    group = get("group")
    rank = group.get("rank") if isinstance(group, dict) else getattr(group, "rank", 0)
    return get("kind") == "actor" and (group is None or rank == 0)


def checkpoint_paths(run_dir: Path) -> list[Path]:
    """The files of `run_dir`'s current checkpoint that travel (CHECKPOINT_MEMBER_RE), the
    manifest last, so that it never names files not yet written; [] without a checkpoint."""
    directory = run_dir / "checkpoints"
    try:
        current = json.loads((directory / "MANIFEST.json").read_text()).get("dir", "")
    except (OSError, ValueError, AttributeError):
        return []
    paths = [directory / str(current) / f for f in ("policy.safetensors", "optimizer.safetensors")]
    paths += [directory / "high_water.json", directory / "MANIFEST.json"]
    return [p for p in paths if p.is_file() and not p.is_symlink()
            and CHECKPOINT_MEMBER_RE.fullmatch(p.relative_to(run_dir).as_posix())]


def checkpoint_tar(run_dir: Path) -> bytes:
    """`run_dir`'s current checkpoint as a tar (b"" without one)."""
    paths = checkpoint_paths(run_dir)
    if not paths:
        return b""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for path in paths:
            tar.add(path, arcname=path.relative_to(run_dir).as_posix(), recursive=False)
    return buf.getvalue()


def result_path_problem(member: tarfile.TarInfo, role: str, checkpoints: bool = False) -> str | None:
    """Why a member of role `role`'s result tar may not be unpacked into the local run directory
    (see RESULT_DIRS; with `checkpoints`, a rank-0 actor's, also CHECKPOINT_MEMBER_RE), or None."""
    if not member.isfile():
        return "not a regular file (links, devices and directories are refused)"
    rel = PurePosixPath(member.name)
    if rel.is_absolute() or ".." in rel.parts:
        return "an absolute path or '..'"
    if checkpoints and CHECKPOINT_MEMBER_RE.fullmatch(member.name):
        return None
    parts = rel.parts
    if len(parts) == 1 and parts[0] in RESULT_FILES and role.startswith("actor-"):
        return None
    if len(parts) == 2 and parts[0] in RESULT_DIRS and parts[1].startswith(f"{role}."):
        if RESULT_DIRS[parts[0]].fullmatch(parts[1][len(role) + 1:]):  # the part after "<role>."
            return None
    expected = ", ".join(f"{d}/{role}.*" for d in RESULT_DIRS)
    return f"not a result file of {role} (expected {expected}, or an actor's {', '.join(RESULT_FILES)})"


def unpack_results(path: Path, run_dir: Path, role: str, host: str = "remote node", checkpoints: bool = False) -> list[str]:
    """Unpack remote role `role`'s result tar into `run_dir`; delete the tar. One member that is not
    a result file of this role (:func:`result_path_problem`) refuses the whole tar with
    :class:`ResultsRefused` naming `host` and the member, and nothing is unpacked."""
    if not path.exists():
        return []
    names: list[str] = []
    try:
        if path.stat().st_size == 0:
            return names
        with tarfile.open(path, "r:") as tar:
            members = tar.getmembers()
            for member in members:
                problem = result_path_problem(member, role, checkpoints)
                if problem:
                    raise ResultsRefused(f"results from {host} refused, nothing unpacked: {member.name[:200]!r} is {problem}")
            for member in members:
                rel = PurePosixPath(member.name)
                dest = run_dir.joinpath(*rel.parts)
                dest.parent.mkdir(parents=True, exist_ok=True)
                src = tar.extractfile(member)
                assert src is not None
                tmp = dest.with_name(dest.name + ".part")
                with open(tmp, "wb") as out:
                    while chunk := src.read(1 << 20):
                        out.write(chunk)
                tmp.replace(dest)
                names.append(str(rel))
    finally:
        path.unlink(missing_ok=True)
    return names


# ----------------------------------------------------------------------------------------------
# remote half: `python -m dvla.orchestrator.ssh serve|probe`


def run_dir_action(run_dir: Path, token: str) -> tuple[str, str]:
    """What to do with the remote run directory for the run holding `token`, and why:
    ``create`` (nothing there), ``keep`` (this run's: a restart), ``wipe`` (dvla's, left by an
    earlier run: its checkpoint would be resumed) or ``refuse`` (anything else: never touched).

    Only a directory carrying dvla's token file, owned by this user, is ever deleted."""
    if not os.path.lexists(run_dir):
        return "create", "no such directory"
    if run_dir.is_symlink() or not run_dir.is_dir():
        return "refuse", "exists and is not a directory (a symbolic link or a file)"
    if run_dir.stat().st_uid != os.getuid():
        return "refuse", "exists and belongs to another user"
    token_path = run_dir / TOKEN_FILE
    if token_path.is_symlink() or not token_path.is_file():
        return "refuse", f"exists and is not a dvla run directory (no {TOKEN_FILE})"
    if token_path.read_text(errors="replace").strip() == token:
        return "keep", "this run's"
    return "wipe", "left by an earlier run"


def prepare_run_dir(run_dir: Path, token: str) -> None:
    """Make `run_dir` the remote run directory of the run holding `token` (see
    :func:`run_dir_action`); raise :class:`RunDirError` (one line naming host and path) when
    something that is not dvla's is in the way: it is left as it is."""
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    lock_path = run_dir.parent / f".{run_dir.name}.lock"
    with open(lock_path, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # roles of one node start at once: one of them wipes
        action, why = run_dir_action(run_dir, token)
        if action == "refuse":
            raise RunDirError(f"{os.uname().nodename}: {run_dir} {why}; left as it is: move it away or"
                              " set ssh.workdir to another directory")
        if action == "keep":
            return
        if action == "wipe":
            shutil.rmtree(run_dir)
        run_dir.mkdir()
        write_private(run_dir / TOKEN_FILE, token + "\n")


def write_private(path: Path, text: str) -> None:
    """Write a file only its owner can read (0600 from creation on)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def _results_tar(run_dir: Path, role: str, since: float, checkpoints: bool = False) -> bytes:
    """Result files of `role` in the run directory (modified since it started), as a tar: only
    what the local side accepts (:func:`result_path_problem`); with `checkpoints` (a rank-0
    actor) its current checkpoint too, last. Counter files go whatever their age: those of an
    earlier incarnation killed with its step (so never sent) come back with the next one, and the
    run's accounting stays exact."""
    buf = io.BytesIO()
    candidates = [run_dir / f for f in RESULT_FILES] + [p for d in RESULT_DIRS for p in sorted((run_dir / d).glob("*"))]
    fresh = [p for p in candidates if not p.is_symlink() and p.is_file() and p.suffix not in (".tmp", ".part")
             and (p.parent.name == "counters" or p.stat().st_mtime >= since)]
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for path in fresh + (checkpoint_paths(run_dir) if checkpoints else []):
            info = tar.gettarinfo(path, arcname=path.relative_to(run_dir).as_posix())
            if result_path_problem(info, role, checkpoints) is None:
                with open(path, "rb") as f:
                    tar.addfile(info, f)
    return buf.getvalue()


def _version_in(text: bytes | str | None) -> int:
    """The "version" of a checkpoint manifest or high-water file (-1: none or unreadable)."""
    try:
        return int(json.loads(text or "")["version"])
    except (ValueError, KeyError, TypeError):
        return -1


def unpack_checkpoint(data: bytes, run_dir: Path) -> bool:
    """Write the checkpoint tar the orchestrator sent (CHECKPOINT_MEMBER_RE members only, each
    through a temporary file; the manifest comes last) into `run_dir`, unless the checkpoint there
    is as new (a restart on the same node whose results never came back): never backwards. The
    high-water mark keeps the higher of the two. Returns whether anything was written."""
    def read(path: Path) -> str | None:
        try:
            return path.read_text()
        except OSError:
            return None

    with tarfile.open(fileobj=io.BytesIO(data), mode="r:") as tar:
        members = tar.getmembers()
        for member in members:
            if not member.isfile() or not CHECKPOINT_MEMBER_RE.fullmatch(member.name):
                raise ValueError(f"{member.name[:200]!r} is not a checkpoint file")
        content = {m.name: tar.extractfile(m).read() for m in members}  # type: ignore[union-attr]
    directory = run_dir / "checkpoints"
    if _version_in(read(directory / "MANIFEST.json")) >= _version_in(content.get("checkpoints/MANIFEST.json")):
        return False
    here = read(directory / "high_water.json")
    if _version_in(here) > _version_in(content.get("checkpoints/high_water.json")):
        content["checkpoints/high_water.json"] = (here or "").encode()
    for name, blob in content.items():  # in the tar's order: the manifest last
        dest = run_dir.joinpath(*PurePosixPath(name).parts)
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = dest.with_name(dest.name + ".part")
        tmp.write_bytes(blob)
        tmp.replace(dest)
    return True


def serve() -> int:
    """Run one role as the orchestrator's stdin header says; stop it when stdin closes."""
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    line = stdin.readline()
    if not line:
        print("dvla ssh serve: no header on stdin", file=sys.stderr)
        return 2
    header = json.loads(line)
    config = header["config"]
    run_dir = Path(os.path.expanduser(header["run_dir"])).absolute()
    in_place = bool(header.get("in_place"))  # the orchestrator's own run directory: its files stay there
    if not in_place:
        try:
            prepare_run_dir(run_dir, header["token"])
        except RunDirError as err:
            print(f"dvla ssh serve: {err}", file=sys.stderr, flush=True)
            return NOT_OURS
    if header.get("checkpoint_bytes"):
        try:
            unpack_checkpoint(stdin.read(int(header["checkpoint_bytes"])), run_dir)
        except (OSError, tarfile.TarError, ValueError) as err:
            print(f"dvla ssh serve: the run's checkpoint could not be written to {run_dir}: {err}", file=sys.stderr, flush=True)
            return 1
    config["run_dir"] = str(run_dir)
    roles_dir = run_dir / "roles"
    roles_dir.mkdir(exist_ok=True)
    config_path = roles_dir / f"{config['name']}.json"
    write_private(config_path, json.dumps(config, indent=1, sort_keys=True))
    env = dict(os.environ)
    env.update(header.get("env", {}))
    env.setdefault("PYTHONUNBUFFERED", "1")
    env[header["secret_env"]] = header["secret"]  # the role's environment: never a command line
    if header.get("identity"):
        env[IDENTITY_ENV] = header["identity"]

    hangup = threading.Event()

    def watch_stdin() -> None:
        # the file descriptor, not sys.stdin's buffered reader: a daemon thread blocked inside that
        # reader holds its lock, and the interpreter then aborts at exit (the header was the last
        # thing the orchestrator wrote, so the buffer holds nothing more)
        try:
            while os.read(stdin.fileno(), 4096):
                pass
        except (OSError, ValueError):
            pass
        hangup.set()

    def on_signal(_signum: int, _frame: Any) -> None:
        hangup.set()

    for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
        signal.signal(sig, on_signal)
    started = time.time() - 1.0  # mtime granularity
    argv = [sys.executable, "-m", header["module"], "--config", str(config_path)]
    print(f"--- {os.uname().nodename}: {' '.join(argv)}", file=sys.stderr, flush=True)
    child = subprocess.Popen(
        argv, stdin=subprocess.DEVNULL, stdout=sys.stderr.fileno(), stderr=sys.stderr.fileno(), env=env,
        cwd=run_dir, start_new_session=True, preexec_fn=die_with_parent,
    )
    threading.Thread(target=watch_stdin, name="stdin-watch", daemon=True).start()
    stop_sent = None
    while child.poll() is None:
        if hangup.is_set():
            now = time.monotonic()
            if stop_sent is None:
                print("--- hang-up from the orchestrator: stopping the role", file=sys.stderr, flush=True)
                killpg(child.pid, signal.SIGTERM)
                stop_sent = now
            elif now - stop_sent > REMOTE_STOP_GRACE_S:
                killpg(child.pid, signal.SIGKILL)
        time.sleep(0.1)
    code = child.returncode
    try:
        if not in_place:
            stdout.write(_results_tar(run_dir, config["name"], started, writes_checkpoints(config)))
        stdout.flush()
    except (BrokenPipeError, OSError):
        pass  # the orchestrator is gone: nobody to send results to
    return code if code >= 0 else 128 - code


def probe() -> int:
    """Print what `dvla up` needs to know about this host, as one JSON line. A JSON line on stdin
    (``run_dir``, ``token``) asks for the run directory to be prepared first (:func:`prepare_run_dir`)."""
    line = sys.stdin.readline()
    if line.strip():
        header = json.loads(line)
        try:
            prepare_run_dir(Path(os.path.expanduser(header["run_dir"])).absolute(), header["token"])
        except RunDirError as err:
            print(err, file=sys.stderr)
            return NOT_OURS
    print(json.dumps({"host": os.uname().nodename, "python": platform.python_version(), "dvla": dvla.__file__}))
    return 0


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if args == ["serve"]:
        return serve()
    if args == ["probe"]:
        return probe()
    print("usage: python -m dvla.orchestrator.ssh serve|probe (started by `dvla up` over ssh)", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())

"""`dvla doctor`'s checks: can this host run the roles (of a topology, when one is given)?

A failing check is ``fail`` when the host cannot run its roles without it (``required``), else
``warn``, with the command that fixes it. Anything slow or able to crash (importing torch,
SAPIEN's device query) runs in a subprocess with a timeout, so one broken driver cannot hang or
kill the doctor.
"""

from __future__ import annotations

import errno
import json
import os
import platform
import shutil
import socket
import subprocess
import sys
from dataclasses import asdict, dataclass
from typing import Callable, Literal

from ..config import LIBERO_ASSETS_ENV, LIBERO_ENV, LIBERO_RENDERER_FIX, LiberoConfig, Topology, libero_assets_problem
from .launcher import last_line
from .plan import make_plan, pinning_problems, role_cpus
from .process import endpoint_address, is_local_host
from .slurm import SlurmError, slurm_job_for
from .ssh import SshError, check_host, remote_targets

Status = Literal["ok", "warn", "fail", "skip"]
STATUSES: tuple[Status, ...] = ("ok", "warn", "fail", "skip")
#: seconds a probing subprocess may take (SAPIEN's first Vulkan query can take a while on lavapipe)
PROBE_TIMEOUT_S = 90.0
SETUP_PYTHON = "bash scripts/setup.sh python"
SETUP_SYSTEM = "bash scripts/setup.sh system"


@dataclass(frozen=True, kw_only=True)
class CheckResult:
    """The outcome of one check."""

    #: short name, e.g. "vulkan"
    name: str
    #: ok, warn (a problem that does not block), fail (a required check failed) or skip
    status: Status
    #: what was found (one line)
    detail: str
    #: how to fix a warn or fail (a command where one exists)
    fix: str | None = None
    #: whether the host cannot run its roles without this check passing
    required: bool = False


def outcome(name: str, good: bool, detail: str, *, fix: str | None = None, required: bool) -> CheckResult:
    """ok when `good`; otherwise fail if `required`, else warn."""
    if good:
        return CheckResult(name=name, status="ok", detail=detail, required=required)
    return CheckResult(name=name, status="fail" if required else "warn", detail=detail, fix=fix, required=required)


def skip(name: str, detail: str) -> CheckResult:
    return CheckResult(name=name, status="skip", detail=detail)


@dataclass(frozen=True, kw_only=True)
class Needs:
    """What the roles placed on this host need, from a topology (or everything, without one)."""

    #: rollouts or evaluators run here (SAPIEN, ManiSkill, Vulkan)
    simulator: bool = True
    #: a role here wants CUDA (device or sim backend set to cuda)
    cuda: bool = False
    #: rollouts or evaluators here run LIBERO tasks (task.env: libero)
    libero: bool = False
    #: emulate: netns
    netns: bool = False
    #: (role, listen endpoint) of every plane bound on this machine
    endpoints: tuple[tuple[str, str], ...] = ()
    #: remote nodes to log in to
    remote_nodes: tuple[str, ...] = ()
    #: a topology was given
    topology: bool = False
    #: the policy loads a Hugging Face checkpoint here (transformers and peft must import)
    hf: bool = False


def needs_of(topo: Topology | None) -> Needs:
    if topo is None:
        return Needs()
    plan = make_plan(topo, run_dir=f"runs/{topo.run}")
    local = [p for p in plan.processes if is_local_host(p.host)]
    kinds = frozenset(p.config.kind for p in local)
    task = topo.task
    return Needs(
        simulator=bool(kinds & {"rollout", "evaluator"}),
        cuda="cuda" in (task.device, task.rollout_device, task.eval_device) or task.sim_backend == "physx_cuda",
        libero=task.env == LIBERO_ENV and bool(kinds & {"rollout", "evaluator"}),
        netns=topo.emulate == "netns",
        endpoints=tuple((p.config.name, ep) for p in local for ep in (*p.config.ctrl.listen, *p.config.data.listen)),
        remote_nodes=tuple(n.name for _r, n in topo.nodes() if not is_local_host(n.host)),
        topology=True,
        hf=task.policy in ("vla-tokens", "vla-flow") and bool(kinds & {"actor", "rollout", "evaluator"}),
    )


# ----------------------------------------------------------------------------------------------
# helpers


def _run(cmd: list[str], timeout: float = 30.0) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of `cmd`; -1 and why as stderr when it cannot start or times out."""
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return -1, "", f"no answer in {timeout:.0f} s"
    except OSError as err:
        return -1, "", str(err)
    return p.returncode, p.stdout, p.stderr


def _python_probe(code: str) -> tuple[int, str, str]:
    """:func:`_run` of `code` in a fresh interpreter."""
    return _run([sys.executable, "-c", code], PROBE_TIMEOUT_S)


def parse_device_summary(text: str) -> list[str]:
    """Names of the render devices SAPIEN marks ``Supported: 1`` in `get_device_summary()`."""
    devices, current = [], None
    for line in text.splitlines():
        line = line.strip()
        if line.startswith(("GPU:", "CPU:")):
            current = line.split(":", 1)[1].strip()
        elif line.replace(" ", "") == "Supported:1" and current:
            devices.append(current)
            current = None
    return devices


def parse_ntp(value: str) -> bool | None:
    """`timedatectl show -p NTPSynchronized --value` -> synchronised? (None: unknown)."""
    v = value.strip().lower()
    return True if v == "yes" else False if v == "no" else None


# ----------------------------------------------------------------------------------------------
# checks


def check_python() -> CheckResult:
    ok = sys.version_info >= (3, 10)
    return outcome("python", ok, f"{platform.python_version()} at {sys.executable}",
                   fix="install Python >= 3.10", required=True)


def check_torch(needs: Needs) -> list[CheckResult]:
    code = ("import json, torch; print(json.dumps({'v': torch.__version__, 'cuda': torch.cuda.is_available(),"
            " 'n': torch.cuda.device_count()}))")
    rc, out, err = _python_probe(code)
    if rc != 0:
        return [outcome("torch", False, f"import failed: {last_line(err)}", fix=SETUP_PYTHON, required=True),
                skip("cuda", "torch unavailable")]
    info = json.loads(last_line(out))
    torch_ok = outcome("torch", True, f"torch {info['v']}", required=True)
    if info["cuda"]:
        cuda = outcome("cuda", True, f"{info['n']} CUDA device(s)", required=needs.cuda)
    elif needs.cuda:
        cuda = outcome("cuda", False, "no CUDA device, but the topology asks for cuda", required=True,
                       fix="install the NVIDIA driver and the CUDA build of torch (bash scripts/setup.sh python on a GPU host), "
                           "or run on the CPU: task.device, rollout_device and eval_device auto or cpu, sim_backend "
                           "auto or physx_cpu, env_batching auto or loop (docs/envs.md)")
    else:
        cuda = CheckResult(name="cuda", status="ok", detail="no CUDA device: torch runs on the CPU")
    return [torch_ok, cuda]


def check_zenoh() -> CheckResult:
    try:
        from importlib.metadata import PackageNotFoundError, version

        import zenoh  # noqa: F401

        try:
            v = version("eclipse-zenoh")
        except PackageNotFoundError:
            v = "unknown"
    except ImportError as err:
        return outcome("zenoh", False, f"import failed: {err}", fix=SETUP_PYTHON, required=True)
    ok = v.split(".")[0] == "1"
    return outcome("zenoh", ok, f"eclipse-zenoh {v}" + ("" if ok else " (dvla needs 1.x)"),
                   fix="python -m pip install 'eclipse-zenoh>=1.4,<2'", required=True)


def check_vulkan(needs: Needs) -> CheckResult:
    """A Vulkan device SAPIEN can render with (the simulator of rollouts and evaluators)."""
    fix = f"install a Vulkan driver: {SETUP_SYSTEM} (Mesa lavapipe >= 24.3 where there is no GPU driver)"
    rc, out, err = _python_probe("import sapien.render as r; print(r.get_device_summary())")
    devices = parse_device_summary(out) if rc == 0 else []
    if devices:
        return outcome("vulkan", True, "SAPIEN render device: " + ", ".join(devices), required=needs.simulator)
    why = f"SAPIEN found no supported device ({last_line(err) if rc != 0 else 'none listed'})"
    if shutil.which("vulkaninfo"):
        code, listing, _err = _run(["vulkaninfo", "--summary"])
        names = [l.split("=", 1)[1].strip() for l in listing.splitlines() if l.strip().startswith("deviceName")]
        if code == 0 and names:
            why += f"; vulkaninfo lists {', '.join(names)}"
        elif code == -1:
            why += "; vulkaninfo timed out"
    return outcome("vulkan", False, why, fix=fix, required=needs.simulator)


def check_maniskill(needs: Needs) -> CheckResult:
    rc, out, err = _python_probe("import mani_skill; print(mani_skill.__version__)")
    detail = f"mani_skill {last_line(out)}" if rc == 0 else f"import failed: {last_line(err)}"
    return outcome("maniskill", rc == 0, detail, fix=SETUP_PYTHON, required=needs.simulator)


PHYSX_GPU_PROBE = (
    "import json, pathlib, torch, sapien.physx as p; v = p.version(); "
    "f = pathlib.Path.home() / '.sapien' / 'physx' / v / 'libPhysXGpu_64.so'; "
    "print(json.dumps({'cuda': torch.cuda.is_available(), 'version': v, 'path': str(f), 'present': f.is_file()}))"
)


def physx_gpu_result(info: dict, needs: Needs) -> CheckResult:
    """The ``physx-gpu`` check from :data:`PHYSX_GPU_PROBE`'s answer: SAPIEN downloads its PhysX GPU
    library from GitHub the first time a physx_cuda scene is made, so on a GPU host without network
    every such scene fails (``sim_backend: auto`` picks one for a CUDA rollout of several envs)."""
    if not info["cuda"] and not needs.cuda:
        return skip("physx-gpu", "no CUDA device: ManiSkill simulates on physx_cpu")
    path = info["path"]
    if info["present"]:
        return outcome("physx-gpu", True, f"PhysX GPU library {info['version']} at {path}", required=False)
    return outcome(
        "physx-gpu", False,
        f"no PhysX GPU library at {path}: the first physx_cuda scene downloads it from GitHub (needs network)",
        fix=(f"offline: unzip linux-so.zip of release {info['version']} of sapien-sim/physx-precompiled into "
             f"{path.rsplit('/', 1)[0]}, or set task.sim_backend: physx_cpu"),
        required=False)


def check_physx_gpu(needs: Needs) -> CheckResult:
    rc, out, err = _python_probe(PHYSX_GPU_PROBE)
    if rc != 0:
        return skip("physx-gpu", f"probe failed: {last_line(err)}")
    return physx_gpu_result(json.loads(last_line(out)), needs)


def check_transformers(needs: Needs) -> CheckResult:
    """transformers and peft import (the Hugging Face policies). The usual failure: a torchvision
    built for another torch (robomimic's), which transformers imports whenever it is installed."""
    rc, out, err = _python_probe("import transformers, peft; print(transformers.__version__, peft.__version__)")
    if rc == 0:
        v = last_line(out).split()
        return outcome("transformers", True, f"transformers {v[0]}, peft {v[-1]}", required=needs.hf)
    why = last_line(err)
    fix = ("pip uninstall torchvision (dvla does not use it; this one does not load with your torch)"
           if "torchvision" in err else SETUP_PYTHON)
    return outcome("transformers", False, f"import failed: {why}", fix=fix, required=needs.hf)


LIBERO_INSTALL = ("pip install -e '.[libero]' -c <a constraints file pinning your torch and numpy> "
                  "(docs/libero.md)")


def check_libero(topo: Topology | None, needs: Needs) -> CheckResult:
    """LIBERO's needs: hf-libero importable, MuJoCo rendering offscreen with the topology's
    renderer (one frame, in a subprocess) and, for a LIBERO topology, its assets directory.
    Optional (skipped when hf-libero is absent) unless the topology runs LIBERO here."""
    import importlib.util

    required = needs.libero
    if importlib.util.find_spec("libero") is None:
        if not required:
            return skip("libero", f"hf-libero not installed (optional, for task.env: libero: {LIBERO_INSTALL})")
        return outcome("libero", False, "hf-libero not installed", fix=LIBERO_INSTALL, required=True)
    cfg = (topo.task.libero if topo is not None else None) or LiberoConfig()
    problem = render_problem(cfg.renderer)
    if problem:
        return outcome("libero", False, f"MuJoCo cannot render offscreen: {problem}",
                       fix=LIBERO_RENDERER_FIX[cfg.renderer], required=required)
    detail = f"hf-libero installed; MuJoCo renders offscreen with MUJOCO_GL={cfg.renderer}"
    if required:
        assets = cfg.assets or os.environ.get(LIBERO_ASSETS_ENV)
        problem = libero_assets_problem(os.path.abspath(assets)) if assets else f"not set and {LIBERO_ASSETS_ENV} is empty"
        if problem:
            return outcome("libero", False, f"task.libero.assets: {problem}",
                           fix="set task.libero.assets to LIBERO's assets directory (docs/libero.md)", required=True)
        detail += f"; assets {assets}"
    return outcome("libero", True, detail, required=required)


def render_problem(renderer: str, size: int = 32) -> str | None:
    """Why MuJoCo cannot render one frame offscreen with MUJOCO_GL=`renderer` here, or None
    (a fresh interpreter: MuJoCo picks its GL backend once per process)."""
    code = "\n".join((
        "import os",
        f"os.environ['MUJOCO_GL'] = os.environ['PYOPENGL_PLATFORM'] = {renderer!r}",
        "import mujoco",
        "m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><light pos=\"0 0 1\"/>"
        "<geom type=\"sphere\" size=\".1\"/></worldbody></mujoco>')",
        "d = mujoco.MjData(m); mujoco.mj_forward(m, d)",
        f"r = mujoco.Renderer(m, {size}, {size}); r.update_scene(d); img = r.render()",
        f"assert img.shape == ({size}, {size}, 3) and img.any(), 'the frame is blank'",
    ))
    rc, _out, err = _python_probe(code)
    return None if rc == 0 else f"MUJOCO_GL={renderer}: {last_line(err) or f'exit {rc}'}"


def _bind_error(endpoint: str) -> tuple[str, int, int | None]:
    """(address, port, errno or None) of trying to listen on a ``tcp/ADDR:PORT`` endpoint."""
    addr, port = endpoint_address(endpoint)
    family = socket.AF_INET6 if ":" in addr else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.bind((addr, port))
            s.listen(1)
    except OSError as err:
        return addr, port, err.errno
    return addr, port, None


def check_ports(needs: Needs) -> CheckResult:
    if not needs.topology:
        return skip("ports", "give a TOPOLOGY to check the ports its planes listen on")
    if not needs.endpoints:
        return skip("ports", "no plane listens on this host")
    busy, foreign, inside = [], [], 0
    for role, ep in needs.endpoints:
        addr, port, code = _bind_error(ep)
        if code is None:
            continue
        if code == errno.EADDRNOTAVAIL and needs.netns:
            inside += 1  # a namespace address: only exists once `dvla up` builds the fabric
        elif code == errno.EADDRNOTAVAIL:
            foreign.append(f"{addr} ({role})")
        else:
            busy.append(f"{port} ({role}: {os.strerror(code)})")
    checked = len(needs.endpoints) - inside
    if checked == 0 and not busy and not foreign:
        return skip("ports", f"all {inside} listen ports are inside netns namespaces: dvla up checks them")
    note = f"; {inside} inside netns namespaces, checked by dvla up" if inside else ""
    if busy:
        return outcome("ports", False, f"in use: {', '.join(busy)}{note}", required=True,
                       fix="stop what holds them (ss -ltnp shows it) or start at another port: dvla up --base-port N")
    if foreign:
        return outcome("ports", False, f"not an address of this host: {', '.join(foreign)}", required=True,
                       fix="set the node's address: to one of this host's addresses (ip -br addr)")
    return outcome("ports", True, f"{checked} listen port(s) free{note}", required=True)


def check_cpus(topo: Topology | None) -> CheckResult:
    """Every core a local process is pinned to (``cpus``, ``lane_cpus``) exists on this host."""
    if topo is None:
        return skip("cpus", "give a TOPOLOGY to check the cores it pins roles and lanes to")
    pinned = sum(r.count for _rack, n in topo.nodes() if is_local_host(n.host)
                 for r in n.roles if role_cpus(n, r) or r.lane_cpus)
    if not pinned:
        return skip("cpus", "no process on this host is pinned")
    problems = pinning_problems(topo)
    if problems:
        return outcome("cpus", False, "; ".join(problems), required=True,
                       fix="pin to cores this host has (nproc; taskset -pc $$ shows the usable ones)")
    return outcome("cpus", True, f"{pinned} pinned process(es): every core exists here", required=True)


def check_netns(needs: Needs) -> CheckResult:
    """Build a throwaway namespace with a veth pair, a bridge and a tbf shaper; remove it."""
    fix = "run as root with iproute2 installed (apt-get install iproute2); the kernel needs network " \
          "namespaces, veth, bridge and sch_tbf (modprobe veth bridge sch_tbf)"
    if os.geteuid() != 0:
        return outcome("netns", False, "not root: emulate: netns needs root", fix=fix, required=needs.netns)
    if not shutil.which("ip") or not shutil.which("tc"):
        return outcome("netns", False, "ip or tc not found", fix=fix, required=needs.netns)
    ns = f"dvdoc{os.getpid()}"
    # exactly what an emulated cluster is made of: veth pairs, a bridge, tbf on a veth
    steps = [
        ["ip", "netns", "add", ns],
        ["ip", "-n", ns, "link", "add", "v0", "type", "veth", "peer", "name", "v1"],
        ["ip", "-n", ns, "link", "add", "b0", "type", "bridge"],
        ["ip", "-n", ns, "link", "set", "v1", "master", "b0", "up"],
        ["ip", "-n", ns, "link", "set", "v0", "up"],
        ["tc", "-n", ns, "qdisc", "add", "dev", "v0", "root", "tbf", "rate", "1mbit", "burst", "32kbit", "latency", "25ms"],
    ]
    try:
        for cmd in steps:
            code, _out, err = _run(cmd)
            if code != 0:
                return outcome("netns", False, f"`{' '.join(cmd)}`: {last_line(err)}", fix=fix, required=needs.netns)
    finally:
        _run(["ip", "netns", "del", ns])
    return outcome("netns", True, "namespace, veth, bridge and tbf work (throwaway namespace removed)", required=needs.netns)


def check_ssh(topo: Topology | None, needs: Needs) -> list[CheckResult]:
    if not needs.remote_nodes or topo is None:
        return [skip("ssh", "no remote nodes" if needs.topology else "give a TOPOLOGY to check its remote nodes")]
    try:
        job = slurm_job_for(topo)
    except SlurmError as err:
        return [outcome("ssh", False, str(err), fix="run it inside the Slurm job, or set launcher: ssh", required=True)]
    if job is not None:
        return [skip("ssh", f"remote roles start as steps of Slurm job {job.job_id}, not over SSH")]
    results = []
    for node, target in remote_targets(topo).items():
        fix = (f"key login must work without a prompt: ssh-copy-id -p {target.ssh.port} {target.destination}; "
               f"dvla must be installed for {target.ssh.python} there")
        try:
            info = check_host(target)
            results.append(outcome(f"ssh:{node}", True, f"{target.label()}: python {info.get('python')}, dvla {info.get('dvla')}",
                                   required=True))
        except SshError as err:
            results.append(outcome(f"ssh:{node}", False, str(err), fix=fix, required=True))
    return results


def check_clock() -> CheckResult:
    """Clock synchronisation: metrics and status timestamps are compared across hosts."""
    if not shutil.which("timedatectl"):
        return skip("clock", "timedatectl not found: check NTP by hand (chronyc tracking)")
    code, out, err = _run(["timedatectl", "show", "-p", "NTPSynchronized", "--value"], timeout=10)
    if code == -1:
        return skip("clock", "timedatectl did not answer")
    synced = parse_ntp(out) if code == 0 else None
    if synced is None:
        return skip("clock", f"NTP status unknown ({last_line(err)})")
    return outcome("clock", synced, "NTP synchronised" if synced else "clock not NTP-synchronised",
                   fix="timedatectl set-ntp true (or install chrony)", required=False)


#: every check, in the order it runs (its name is what `dvla doctor --skip` takes)
CHECKS: dict[str, Callable[[Topology | None, Needs], CheckResult | list[CheckResult]]] = {
    "python": lambda topo, needs: check_python(),
    "torch": lambda topo, needs: check_torch(needs),
    "zenoh": lambda topo, needs: check_zenoh(),
    "vulkan": lambda topo, needs: check_vulkan(needs),
    "maniskill": lambda topo, needs: check_maniskill(needs),
    "physx-gpu": lambda topo, needs: check_physx_gpu(needs),
    "transformers": lambda topo, needs: check_transformers(needs),
    "libero": check_libero,
    "ports": lambda topo, needs: check_ports(needs),
    "cpus": lambda topo, needs: check_cpus(topo),
    "netns": lambda topo, needs: check_netns(needs),
    "ssh": lambda topo, needs: check_ssh(topo, needs),
    "clock": lambda topo, needs: check_clock(),
}


def run_checks(
    topo: Topology | None, progress: Callable[[str], None] | None = None, skipped: tuple[str, ...] = ()
) -> list[CheckResult]:
    """Every check, in a fixed order; those named in `skipped` are reported as skipped."""
    needs = needs_of(topo)
    results: list[CheckResult] = []
    for name, fn in CHECKS.items():
        if name in skipped:
            results.append(skip(name, "skipped (--skip)"))
            continue
        if progress is not None:
            progress(name)
        r = fn(topo, needs)
        results.extend(r if isinstance(r, list) else [r])
    return results


# ----------------------------------------------------------------------------------------------
# rendering


def exit_code(results: list[CheckResult]) -> int:
    """1 when a required check failed, else 0 (warnings do not fail the doctor)."""
    return 1 if any(r.status == "fail" for r in results) else 0


_LABEL = {"ok": "ok", "warn": "WARN", "fail": "FAIL", "skip": "skip"}


def format_text(results: list[CheckResult], header: str) -> str:
    width = max((len(r.name) for r in results), default=4)
    lines = [header]
    for r in results:
        lines.append(f"  {_LABEL[r.status]:<4}  {r.name:<{width}}  {r.detail}")
        if r.fix and r.status in ("warn", "fail"):
            lines.append(f"  {'':<4}  {'':<{width}}  fix: {r.fix}")
    counts = {s: sum(r.status == s for r in results) for s in STATUSES}
    verdict = "this host can run its roles" if exit_code(results) == 0 else "a required check failed"
    lines.append(f"{counts['ok']} ok, {counts['warn']} warning(s), {counts['fail']} failure(s), "
                 f"{counts['skip']} skipped: {verdict}")
    return "\n".join(lines)


def format_json(results: list[CheckResult], context: dict) -> str:
    doc = {**context, "ok": exit_code(results) == 0, "checks": [asdict(r) for r in results]}
    return json.dumps(doc, indent=1)

"""The package's layers, checked on the source: which part may import which, and no cycles.

- ``dvla.fabric`` imports nothing else from dvla (it is usable on its own);
- no ``dvla.roles`` module imports the orchestrator or the benchmarks;
- ``dvla.orchestrator`` imports no role module (it starts roles as processes, by module name);
- ``dvla.learn`` and ``dvla.replication`` import neither roles nor the orchestrator;
- only ``dvla/orchestrator/cli.py`` imports the top-level ``benchmarks`` package (it mounts its
  ``dvla bench`` app);
- ``benchmarks/`` uses dvla's public names only (no ``_private`` name, module or attribute);
- the module import graph of dvla has no cycle.

Every import counts, wherever it sits (inside a function, under ``if TYPE_CHECKING``): an import
hidden in a function still ties the two modules together. Each violation is reported as
``file:line``.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BENCH_CLI = "dvla/orchestrator/cli.py"


@dataclass(frozen=True)
class Import:
    """One imported module (and the names taken from it) at one place in a file."""

    file: str
    line: int
    #: absolute dotted name of the module imported (a submodule when ``from pkg import sub``)
    module: str
    #: names taken with ``from module import ...`` (empty for ``import module``)
    names: tuple[str, ...] = ()

    def at(self) -> str:
        return f"{self.file}:{self.line}"


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def sources(top: str) -> dict[str, Path]:
    """Dotted module name -> file, for every .py file under ROOT/top."""
    base = ROOT / top
    return {module_name(p): p for p in sorted(base.rglob("*.py"))} if base.is_dir() else {}


def imports_of(path: Path, known: set[str], root: Path = ROOT) -> list[Import]:
    """Every import of a file, relative ones resolved; ``from pkg import sub`` names the submodule."""
    rel = str(path.relative_to(root))
    name = module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), rel)):
        if isinstance(node, ast.Import):
            out += [Import(rel, node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            names = tuple(a.name for a in node.names)
            subs = [n for n in names if f"{base}.{n}" in known]
            out += [Import(rel, node.lineno, f"{base}.{n}") for n in subs]
            rest = tuple(n for n in names if n not in subs)
            if rest or not subs:
                out.append(Import(rel, node.lineno, base, rest))
    return out


def under(module: str, *packages: str) -> bool:
    return any(module == p or module.startswith(p + ".") for p in packages)


def extensions(top: str) -> set[str]:
    """Dotted names of the C extension modules under ROOT/top (their sources, or built in place)."""
    files = [p for p in (ROOT / top).rglob("*") if p.suffix in (".c", ".so")]
    return {module_name(p.with_name(p.name.split(".")[0])) for p in files}


def all_imports() -> dict[str, list[Import]]:
    mods = sources("dvla") | sources("benchmarks")
    known = set(mods) | extensions("dvla")
    return {m: imports_of(p, known) for m, p in mods.items()}


def layer_violations(graph: dict[str, list[Import]]) -> list[str]:
    """Every import that crosses a layer the wrong way, as ``file:line: what``."""
    bad = []
    for mod, imps in graph.items():
        for imp in imps:
            target = imp.module
            if under(mod, "dvla.fabric") and under(target, "dvla") and not under(target, "dvla.fabric"):
                bad.append(f"{imp.at()}: dvla.fabric imports {target}")
            if under(mod, "dvla.roles") and under(target, "dvla.orchestrator", "dvla.bench", "benchmarks"):
                bad.append(f"{imp.at()}: role module {mod} imports {target}")
            if under(mod, "dvla.orchestrator") and under(target, "dvla.roles"):
                bad.append(f"{imp.at()}: the orchestrator imports role module {target}")
            if under(mod, "dvla.learn", "dvla.replication") and under(target, "dvla.roles", "dvla.orchestrator"):
                bad.append(f"{imp.at()}: {mod} imports {target}")
            if under(mod, "dvla") and under(target, "benchmarks") and imp.file != BENCH_CLI:
                bad.append(f"{imp.at()}: {mod} imports the benchmarks ({target}); only {BENCH_CLI} may")
    return bad


def private_uses(path: Path, known: set[str], root: Path = ROOT) -> list[str]:
    """Private dvla names a benchmarks/ file reaches: imported, or as an attribute of a dvla module."""
    rel = str(path.relative_to(root))
    bad = []
    aliases: set[str] = set()  # local names bound to dvla modules
    for imp in imports_of(path, known, root):
        if not under(imp.module, "dvla"):
            continue
        parts = imp.module.split(".") + list(imp.names)
        private = [p for p in parts if p.startswith("_") and not p.startswith("__")]
        if private:
            bad.append(f"{imp.at()}: private name {private[0]} of {imp.module}")
    for node in ast.walk(ast.parse(path.read_text(), rel)):
        if isinstance(node, ast.Import):
            aliases |= {a.asname or a.name.split(".")[0] for a in node.names if under(a.name, "dvla")}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and under(node.module or "", "dvla"):
            aliases |= {a.asname or a.name for a in node.names if f"{node.module}.{a.name}" in known}
    for node in ast.walk(ast.parse(path.read_text(), rel)):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            root = node.value
            while isinstance(root, ast.Attribute):
                root = root.value
            if isinstance(root, ast.Name) and root.id in aliases:
                bad.append(f"{rel}:{node.lineno}: private name {node.attr} of a dvla module")
    return bad


def cycles(graph: dict[str, list[Import]]) -> list[str]:
    """One line per strongly connected group of dvla modules (import cycle), with the imports in it."""
    edges = {m: sorted({i.module for i in imps if i.module in graph and i.module != m and under(i.module, "dvla")})
             for m, imps in graph.items() if under(m, "dvla")}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    out = []
    for group in groups:
        inside = [f"{i.at()} -> {i.module}" for m in group for i in graph[m] if i.module in group and i.module != m]
        out.append(f"import cycle among {', '.join(group)}: " + "; ".join(inside))
    return out


def test_layers() -> None:
    bad = layer_violations(all_imports())
    assert not bad, "\n".join(bad)


def test_benchmarks_use_public_names_only() -> None:
    mods = sources("benchmarks")
    known = set(sources("dvla")) | set(mods)
    bad = [line for path in mods.values() for line in private_uses(path, known)]
    assert not bad, "\n".join(bad)


def test_no_import_cycles() -> None:
    found = cycles(all_imports())
    assert not found, "\n".join(found)


def test_the_checks_catch_what_they_look_for(tmp_path: Path) -> None:
    """The checks themselves: a cycle, a wrong-way import and a private name are each found."""
    graph = {
        "dvla.a": [Import("dvla/a.py", 3, "dvla.b")],
        "dvla.b": [Import("dvla/b.py", 7, "dvla.a")],
        "dvla.fabric.x": [Import("dvla/fabric/x.py", 1, "dvla.config")],
        "dvla.orchestrator.y": [Import("dvla/orchestrator/y.py", 2, "dvla.roles.counters")],
        "dvla.roles.z": [Import("dvla/roles/z.py", 4, "dvla.orchestrator.plan")],
    }
    assert cycles(graph) == ["import cycle among dvla.a, dvla.b: dvla/a.py:3 -> dvla.b; dvla/b.py:7 -> dvla.a"]
    assert layer_violations(graph) == [
        "dvla/fabric/x.py:1: dvla.fabric imports dvla.config",
        "dvla/orchestrator/y.py:2: the orchestrator imports role module dvla.roles.counters",
        "dvla/roles/z.py:4: role module dvla.roles.z imports dvla.orchestrator.plan",
    ]
    probe = tmp_path / "benchmarks" / "probe.py"
    probe.parent.mkdir()
    probe.write_text("from dvla.orchestrator import netns\nfrom dvla.fabric import _x\n\n\ndef f():\n    netns._ip()\n")
    assert private_uses(probe, {"dvla.orchestrator.netns"}, tmp_path) == [
        "benchmarks/probe.py:2: private name _x of dvla.fabric",
        "benchmarks/probe.py:6: private name _ip of a dvla module",
    ]


def test_the_cli_does_not_import_torch():
    """`dvla status`, `dvla stop`, `dvla logs` and the tests' many status calls start in half a
    second because the orchestrator's modules stay free of torch (dvla.learn imports it); a torch
    import there once made every `dvla` call 1.5 s slower and a timing-bound test flaky."""
    import subprocess
    import sys

    code = "import sys, dvla.orchestrator.cli; print(sorted(m for m in ('torch', 'mani_skill', 'wandb') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", out.stdout

"""The packages' import graph, read with ``ast``: one-way layers, no circles, no simulator in
production code, and a host library that costs only the base layer.

Layers, bottom to top (a unit may import only the units listed for it; every import counts,
also those inside functions)::

    device.core   errors, sphere, healpix, light sets, the Q2-Tree and SG wire formats (and the SG
                  fit, which probe and hosts share), the calibration model, image I/O, atomic
                  writes, exit codes
    drivers       the camera protocol and the hardware backends
    calibration   technician routines and the calibration store
    device        burst, HDR, projection, samplers, pipeline (the processing)
    device.service  publication: HTTP/WebSocket API, mDNS, systemd
    device.cli    the command line and the bootstrap that wires a probe
    sim           the simulator: implements the camera protocol; only bench/tests and the
                  ``lightprobe.cameras`` entry points (pyproject) reach it
    hostlink      the host library: the base layer only
    bench         benchmarks: anything
"""

from __future__ import annotations

import ast
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("device", "drivers", "sim", "calibration", "hostlink", "bench")

ALLOWED: dict[str, set[str]] = {
    "device.core": set(),
    "drivers": {"device.core"},
    "calibration": {"device.core", "drivers"},
    "device": {"device.core", "drivers", "calibration"},
    "device.service": {"device.core", "drivers", "calibration", "device"},
    "device.cli": {"device.core", "drivers", "calibration", "device", "device.service"},
    "sim": {"device.core", "drivers"},
    "hostlink": {"device.core"},
    "bench": {"device.core", "drivers", "calibration", "device", "device.service", "device.cli", "sim",
              "hostlink"},
}
PRODUCTION = ("device", "drivers", "calibration", "hostlink")


def unit(module: str) -> str:
    """The layer a module belongs to."""
    for prefix in ("device.core", "device.service", "device.cli"):
        if module == prefix or module.startswith(prefix + "."):
            return prefix
    return module.split(".")[0]


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def import_graph() -> dict[str, dict[str, int]]:
    """module -> {imported project module: first line}. Relative imports are resolved;
    ``from pkg import name`` counts as an import of ``pkg.name`` when that is a module."""
    modules = {_module_name(p): p for top in PACKAGES for p in (ROOT / top).rglob("*.py")}
    graph: dict[str, dict[str, int]] = defaultdict(dict)
    for mod, path in modules.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    base = base[: len(base) - (node.level - 1)]
                    name = ".".join(base + ([node.module] if node.module else []))
                else:
                    name = node.module or ""
                # ``from pkg import sub`` imports the module pkg.sub; other names come from pkg
                targets = [f"{name}.{a.name}" if f"{name}.{a.name}" in modules else name
                           for a in node.names]
            for t in targets:
                if t.split(".")[0] not in PACKAGES:
                    continue
                while t and t not in modules:  # the module that defines the imported name
                    t = t.rpartition(".")[0]
                if t and t != mod:
                    graph[mod].setdefault(t, node.lineno)
    return graph


def _cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    nodes = set(graph) | {t for d in graph.values() for t in d}
    for root in sorted(nodes):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.get(root, {}))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph.get(w, {})))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


@pytest.fixture(scope="module")
def graph() -> dict[str, dict[str, int]]:
    return import_graph()


def test_the_graph_is_read(graph: dict[str, dict[str, int]]) -> None:
    # the reader must see the imports it is meant to police, or every check below is vacuous
    assert "device.core.errors" in graph["calibration.store"]
    assert "drivers.base" in graph["device.burst"]
    assert "sim.camera" in graph["sim.plugin"]
    assert unit("device.core.sphere") == "device.core"
    assert unit("device.pipeline") == "device"


def test_no_import_cycles(graph: dict[str, dict[str, int]]) -> None:
    assert _cycles(graph) == []
    # the check finds a circle when there is one
    assert _cycles({"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}}) == [["a", "b", "c"]]


def test_layers_point_one_way(graph: dict[str, dict[str, int]]) -> None:
    bad = sorted(f"{m}:{line} imports {t} ({unit(m)} -> {unit(t)})"
                 for m, deps in graph.items() for t, line in deps.items()
                 if unit(t) != unit(m) and unit(t) not in ALLOWED[unit(m)])
    assert bad == []
    # the layer units themselves have no circle
    units: dict[str, dict[str, int]] = defaultdict(dict)
    for m, deps in graph.items():
        for t in deps:
            if unit(t) != unit(m):
                units[unit(m)][unit(t)] = 1
    assert _cycles(units) == []


def test_production_never_imports_the_simulator(graph: dict[str, dict[str, int]]) -> None:
    bad = sorted(f"{m} imports {t}" for m, deps in graph.items() for t in deps
                 if unit(m).split(".")[0] in PRODUCTION and unit(m) != "bench" and t.split(".")[0] == "sim")
    assert bad == []


def test_hostlink_takes_only_the_base_layer(graph: dict[str, dict[str, int]]) -> None:
    bad = sorted(f"{m} imports {t}" for m, deps in graph.items() if m.split(".")[0] == "hostlink"
                 for t in deps if t.split(".")[0] != "hostlink" and unit(t) != "device.core")
    assert bad == []


def test_device_package_imports_nothing() -> None:
    tree = ast.parse((ROOT / "device" / "__init__.py").read_text(encoding="utf-8"))
    assert not [n for n in ast.walk(tree) if isinstance(n, ast.Import | ast.ImportFrom)]
    core = ast.parse((ROOT / "device" / "core" / "__init__.py").read_text(encoding="utf-8"))
    assert not [n for n in ast.walk(core) if isinstance(n, ast.Import | ast.ImportFrom)]


def test_import_hostlink_costs_only_the_base_layer() -> None:
    code = ("import sys, hostlink; hostlink.ProbeClient; hostlink.Discovery; hostlink.merge_q2trees; "
            "print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                       timeout=60, check=True)
    loaded = set(r.stdout.split())
    assert "hostlink" in loaded
    assert "device" in loaded
    assert loaded.isdisjoint({"cv2", "numba", "scipy", "sim", "calibration", "drivers"}), loaded
    r = subprocess.run([sys.executable, "-c", code.replace("print(", "print(sorted(m for m in sys.modules "
                        "if m.startswith('device.')), ")], capture_output=True, text=True, cwd=ROOT,
                       timeout=60, check=True)
    device_modules = {m.strip("',[]") for m in r.stdout.split("] ")[0].split(", ")}
    assert all(m.startswith("device.core") for m in device_modules), device_modules

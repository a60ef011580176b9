"""The packages' import graph, read with ``ast``: one-way layers, no circles, no simulator in
production code, and a host library that costs only the base layer.

Every module is ``lightprobe.<folder>...`` (setup.py maps the top-level folders into the one
namespace). Layers, bottom to top (a unit may import only the units listed for it; every import
counts, also those inside functions; absolute, relative and ``lightprobe.``-prefixed imports are
all resolved to the module they name)::

    core              the base: contracts and conventions (mDNS TXT, MQTT topics), sphere maths,
                      HEALPix, the wire types of light sets, SH, SG, Q2-Tree, KTX2 and scene files,
                      the calibration model, errors, image I/O, atomic writes, exit codes
    drivers           the camera protocol and the hardware backends
    calibration       technician routines and the calibration store
    device.formats    the producers of the host formats (SH + primary light, SG fit, cube maps,
                      glTF/USD): the probe's, and a host's offline, computed alike
    device            burst, HDR, projection, samplers, pipeline (the processing)
    device.service    publication: HTTP/WebSocket API, mDNS, MQTT, systemd
    sim               the simulator: implements the camera protocol; only bench/tests and the
                      ``lightprobe.cameras`` entry points (pyproject) reach it
    hostlink          the host library (discovery, client, streams, merge): the base layer only
    hostlink.relight  host relighting (cuts, SG, the room): the client and the format producers
    bench             benchmarks: anything but the command line
    cli               the ``lightprobe`` command and its subcommands: anything
"""

from __future__ import annotations

import ast
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FOLDERS = ("core", "drivers", "calibration", "device", "sim", "hostlink", "bench", "cli")
PACKAGES = tuple(f"lightprobe.{f}" for f in FOLDERS)

_BELOW_DEVICE = {"core", "drivers", "calibration", "device.formats"}
ALLOWED: dict[str, set[str]] = {
    "core": set(),
    "drivers": {"core"},
    "calibration": {"core", "drivers"},
    "device.formats": {"core"},
    "device": _BELOW_DEVICE,
    "device.service": _BELOW_DEVICE | {"device"},
    "sim": {"core", "drivers"},
    "hostlink": {"core"},
    "hostlink.relight": {"core", "hostlink", "device.formats"},
    "bench": {"core", "drivers", "calibration", "device.formats", "device", "device.service", "sim", "hostlink",
              "hostlink.relight"},
    "cli": {"core", "drivers", "calibration", "device.formats", "device", "device.service", "sim", "hostlink",
            "hostlink.relight", "bench"},
}
PRODUCTION = ("core", "drivers", "calibration", "device.formats", "device", "device.service", "hostlink",
              "hostlink.relight")


def unit(module: str) -> str:
    """The layer a module belongs to (``lightprobe.`` dropped)."""
    name = module.removeprefix("lightprobe.")
    for prefix in ("device.formats", "device.service", "hostlink.relight"):
        if name == prefix or name.startswith(prefix + "."):
            return prefix
    return name.split(".")[0]


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(["lightprobe", *parts])


def import_graph() -> dict[str, dict[str, int]]:
    """module -> {imported project module: first line}. Relative imports are resolved;
    ``from pkg import name`` counts as an import of ``pkg.name`` when that is a module. An import
    of a project folder by its bare name (``import device``) is an error: it names no module of
    the installed package."""
    modules = {_module_name(p): p for top in FOLDERS for p in (ROOT / top).rglob("*.py")}
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
                if t.split(".")[0] in FOLDERS:
                    raise AssertionError(f"{path}:{node.lineno}: imports {t!r}: the package is lightprobe.{t}")
                if not t.startswith("lightprobe."):
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
    assert "lightprobe.core.errors" in graph["lightprobe.calibration.store"]  # absolute
    assert "lightprobe.drivers.base" in graph["lightprobe.device.burst"]
    assert "lightprobe.sim.camera" in graph["lightprobe.sim.plugin"]  # relative
    assert "lightprobe.cli.serve" in graph["lightprobe.cli"]  # the commands, by import, not by string
    assert "lightprobe.hostlink.relight.cuts.render" in graph["lightprobe.cli.relight"]
    assert unit("lightprobe.core.sphere") == "core"
    assert unit("lightprobe.device.pipeline") == "device"
    assert unit("lightprobe.device.formats.sgfit") == "device.formats"
    assert unit("lightprobe.hostlink.relight.sg.relighter") == "hostlink.relight"


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
                 if unit(m) in PRODUCTION and unit(t) == "sim")
    assert bad == []


def test_hostlink_takes_only_the_base_layer(graph: dict[str, dict[str, int]]) -> None:
    bad = sorted(f"{m} imports {t}" for m, deps in graph.items() if unit(m) == "hostlink"
                 for t in deps if unit(t) not in ("hostlink", "core"))
    assert bad == []


def test_base_layer_imports_numpy_and_the_standard_library_only() -> None:
    """``core`` is what a host installs: no numba, OpenCV, SciPy or OpenEXR at its import (the
    image I/O reads EXR and PNG through them when it is asked to, inside its functions)."""
    allowed = set(sys.stdlib_module_names) | {"numpy", "lightprobe"}
    bad = []
    for path in sorted((ROOT / "core").rglob("*.py")):
        for node in ast.parse(path.read_text(encoding="utf-8")).body:  # module level only
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            bad += [f"{path.name}:{node.lineno} {n}" for n in names if n.split(".")[0] not in allowed]
    assert bad == []


def test_package_init_files_import_nothing_heavy() -> None:
    for init in (ROOT / "device" / "__init__.py", ROOT / "core" / "__init__.py"):
        tree = ast.parse(init.read_text(encoding="utf-8"))
        assert not [n for n in ast.walk(tree) if isinstance(n, ast.Import | ast.ImportFrom)], init


def test_import_hostlink_costs_only_the_base_layer() -> None:
    code = ("import sys; import lightprobe.hostlink as h; h.ProbeClient; h.Discovery; h.merge_q2trees; "
            "print(' '.join(sorted(m for m in sys.modules if m.startswith('lightprobe.')))); "
            "print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT / "tests",
                       timeout=60, check=True)
    ours, loaded = (set(line.split()) for line in r.stdout.splitlines())
    assert "lightprobe.hostlink.client" in ours
    assert all(unit(m) in ("hostlink", "core") for m in ours if m != "lightprobe"), ours
    assert loaded.isdisjoint({"cv2", "numba", "scipy", "OpenEXR", "matplotlib"}), loaded


def test_the_wheel_maps_every_folder() -> None:
    """setup.py's folders are the layers' folders: a new top-level package is placed in both."""
    import re

    text = (ROOT / "setup.py").read_text(encoding="utf-8")
    folders = re.search(r"FOLDERS = \(([^)]*)\)", text)
    assert folders is not None
    assert set(re.findall(r'"(\w+)"', folders.group(1))) == set(FOLDERS)
    on_disk = {p.parent.name for p in ROOT.glob("*/__init__.py")} - {"tests"}
    assert on_disk == set(FOLDERS)

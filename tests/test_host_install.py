"""The host library as a host application installs it: the built wheel, in a fresh virtual
environment, without extras (``pip install lightprobe``).

The wheel holds one top-level package, ``lightprobe``; its bare install pulls none of the
probe's numerics (numba, OpenCV, SciPy, OpenEXR, matplotlib); and from that install a host
discovers a running probe over mDNS and reads its lights, with ``lightprobe.hostlink`` and with
``lightprobe discover``.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest
from service_harness import running_service, service_config
from waiting import HANG_S

ROOT = Path(__file__).resolve().parents[1]
PROBE_SIDE = {"numba", "opencv-contrib-python-headless", "opencv-python", "opencv-python-headless", "scipy",
              "openexr", "matplotlib", "embreex", "trimesh"}

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", str(out), str(ROOT)],
                   check=True, timeout=600)
    (whl,) = out.glob("lightprobe-*.whl")
    return whl


@pytest.fixture(scope="module")
def host_venv(wheel: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh venv with the bare wheel installed (its dependencies from the package index)."""
    env = tmp_path_factory.mktemp("host") / "venv"
    venv.EnvBuilder(with_pip=True).create(env)
    subprocess.run([str(env / "bin" / "python"), "-m", "pip", "install", "--quiet", str(wheel)],
                   check=True, timeout=900)
    return env


def test_the_wheel_holds_one_top_level_package(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as z:
        tops = {n.split("/")[0] for n in z.namelist()}
        names = z.namelist()
    tops = {t for t in tops if not t.endswith((".dist-info", ".data"))}
    assert tops == {"lightprobe"}
    # every folder of the repository is in it, as lightprobe.<folder>, with the service's static files
    for folder in ("core", "cli", "device", "drivers", "sim", "calibration", "hostlink", "bench"):
        assert f"lightprobe/{folder}/__init__.py" in names, folder
    assert "lightprobe/device/service/static/index.html" in names
    # the three.js host module, which the probe serves at /js/ from beside its own package
    for name in ("lightprobe-three.js", "lightprobe-three.d.ts", "package.json"):
        assert f"lightprobe/hostlink/threejs/{name}" in names, name


def test_the_bare_install_is_the_host_library_alone(host_venv: Path) -> None:
    py = str(host_venv / "bin" / "python")
    listed = json.loads(subprocess.run([py, "-m", "pip", "list", "--format", "json"], capture_output=True,
                                       text=True, check=True, timeout=120).stdout)
    installed = {d["name"].lower() for d in listed}
    assert "lightprobe" in installed
    assert installed.isdisjoint(PROBE_SIDE), installed & PROBE_SIDE
    r = subprocess.run([py, "-c", "import lightprobe.hostlink as h; h.ProbeClient; h.Discovery; h.MergedStream; "
                        "print(h.ProbeClient.__module__)"], capture_output=True, text=True, timeout=120,
                       cwd=host_venv)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "lightprobe.hostlink.client"


HOST_SCRIPT = """
import asyncio, json, sys
from lightprobe.hostlink import Discovery, ProbeClient

async def main(pid):
    async with Discovery(interfaces=["127.0.0.1"]) as d:
        found = await d.wait_for(lambda p: pid in p, within=float(sys.argv[2]))
        info = found[pid]
        async with ProbeClient(info.url) as c:
            for _ in range(600):
                try:
                    lights = await c.lights()
                    break
                except Exception:
                    await asyncio.sleep(0.1)
            print(json.dumps({"url": info.url, "probe": lights.probe, "count": len(lights),
                              "energy": float(lights.rgb.sum())}))

asyncio.run(main(sys.argv[1]))
"""


async def test_a_host_with_the_bare_install_discovers_a_probe_and_reads_its_lights(
        host_venv: Path, tmp_path: Path) -> None:
    pid = "hostinstall01"
    cfg = service_config(tmp_path, mdns={"enabled": True, "interfaces": ["127.0.0.1"]},
                         probe={"name": "Bare host", "id": pid}, pipeline={"light_count": 32})
    async with running_service(cfg, probe_id=pid) as s:
        proc = await asyncio.create_subprocess_exec(
            str(host_venv / "bin" / "python"), "-c", HOST_SCRIPT, pid, str(HANG_S), cwd=tmp_path,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        out, err = await asyncio.wait_for(proc.communicate(), 2 * HANG_S)
        assert proc.returncode == 0, err.decode()[-2000:]
        got = json.loads(out)
        assert got["url"] == s.url
        assert got["probe"] == pid
        assert got["count"] == 32
        assert got["energy"] > 0
        # and the command line of that install finds it too
        proc = await asyncio.create_subprocess_exec(
            str(host_venv / "bin" / "lightprobe"), "discover", "--timeout", "5", "--interface", "127.0.0.1", "--json", cwd=tmp_path,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        out, err = await asyncio.wait_for(proc.communicate(), 2 * HANG_S)
        assert proc.returncode == 0, err.decode()[-2000:]
        assert pid in {p["id"] for p in json.loads(out)["probes"]}

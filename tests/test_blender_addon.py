"""The Blender add-on (``hostlink/blender/lightprobe_blender``, issue 44) in Blender itself: ``bpy``
from the package index in a virtual environment of its own (every ``bpy`` for CPython 3.11 pins
numpy < 2; the project needs numpy >= 2; the add-on imports nothing of the project).

Blender installs the add-on's zip as a user does (Preferences > Add-ons > Install from Disk:
``preferences.addon_install``), enables it, connects it to a running simulated probe (URL and
token) and goes live; then Cycles renders a white diffuse sphere from above under the World and
the Sun lamp the add-on made, and its pixels are the probe's own irradiance at their normals / pi
(a brute-force cosine integral of the probe's map, written here, posed into Blender's frame as the
add-on documents) within 3%. A wrong axis, a mirrored map or a sun counted twice is far off.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
ADDON = ROOT / "hostlink" / "blender" / "lightprobe_blender"
BPY_VENV = ROOT / "build" / "bpy-venv"
BPY_SPEC = "bpy>=4.2,<4.3"  # Blender 4.2 LTS, the oldest the add-on supports
H = W = 96
ORTHO = 2.1

pytestmark = pytest.mark.slow

DRIVER = r'''
import json, sys, bpy
zip_path, url, token, out, ortho, w, h = sys.argv[-7:]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.preferences.addon_install(filepath=zip_path, overwrite=True)
bpy.ops.preferences.addon_enable(module="lightprobe_blender")
import addon_utils
assert addon_utils.check("lightprobe_blender")[1], "add-on not enabled"
scene = bpy.context.scene
s = scene.lightprobe
s.url, s.token = url, token
assert bpy.ops.lightprobe.live() == {"FINISHED"}, s.status
assert bpy.ops.lightprobe.freeze() == {"FINISHED"}
sun = bpy.data.objects["lightprobe primary light"]
# a white diffuse sphere seen from above, orthographic
bpy.ops.mesh.primitive_uv_sphere_add(segments=256, ring_count=128, radius=1.0)
sphere = bpy.context.active_object
bpy.ops.object.shade_smooth()
mat = bpy.data.materials.new("white")
mat.use_nodes = True
nt = mat.node_tree
nt.nodes.clear()
d = nt.nodes.new("ShaderNodeBsdfDiffuse")
d.inputs["Color"].default_value = (1, 1, 1, 1)
o = nt.nodes.new("ShaderNodeOutputMaterial")
nt.links.new(d.outputs["BSDF"], o.inputs["Surface"])
sphere.data.materials.append(mat)
cam_data = bpy.data.cameras.new("cam")
cam_data.type = "ORTHO"
cam_data.ortho_scale = float(ortho)
cam = bpy.data.objects.new("cam", cam_data)
scene.collection.objects.link(cam)
cam.location = (0, 0, 5)
scene.camera = cam
scene.render.engine = "CYCLES"
scene.cycles.device = "CPU"
scene.cycles.samples = 1024
scene.cycles.use_denoising = False
scene.cycles.max_bounces = 1
scene.cycles.seed = 1
scene.render.resolution_x, scene.render.resolution_y = int(w), int(h)
scene.render.resolution_percentage = 100
scene.view_settings.view_transform = "Standard"
scene.render.image_settings.file_format = "OPEN_EXR"
scene.render.image_settings.color_depth = "32"
scene.render.filepath = out
bpy.ops.render.render(write_still=True)
print("LIGHTPROBE " + json.dumps({"frame": s.frame, "sun_energy": sun.data.energy,
                                  "sun_z": list(sun.matrix_world.col[2][:3]),
                                  "world": scene.world.name}))
'''


@pytest.fixture(scope="session")
def bpy_python() -> Path:
    """``build/bpy-venv``: Blender as a Python module, made once (``make test`` makes it first)."""
    py = BPY_VENV / "bin" / "python"
    if not py.exists() or subprocess.run([str(py), "-c", "import bpy"], capture_output=True, timeout=300).returncode:
        subprocess.run([sys.executable, "-m", "venv", "--clear", str(BPY_VENV)], check=True, timeout=300)
        subprocess.run([str(py), "-m", "pip", "install", "--quiet", BPY_SPEC], check=True, timeout=1800)
    return py


def addon_zip(out: Path) -> Path:
    """The zip a user installs: the add-on's folder at its root."""
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(ADDON.rglob("*")):
            if f.is_file() and "__pycache__" not in f.parts:
                z.write(f, f"lightprobe_blender/{f.relative_to(ADDON)}")
    return out


def _irradiance(equirect: np.ndarray, normals_probe: np.ndarray) -> np.ndarray:
    """Brute force: sum over the map's pixels of L(d) max(0, n . d) dOmega, RGB (N, 3)."""
    from lightprobe.core.sphere import equirect_directions, equirect_solid_angle

    h = equirect.shape[0]
    d = equirect_directions(h).reshape(-1, 3)
    w = (equirect.astype(np.float64) * equirect_solid_angle(h)[..., None]).reshape(-1, 3)
    return np.maximum(normals_probe @ d.T, 0.0) @ w


@pytest.mark.timeout(2400)
async def test_the_addon_lights_a_cycles_render_with_the_probes_irradiance(bpy_python: Path, tmp_path: Path,
                                                                         artifacts_dir: Path) -> None:
    import asyncio

    import aiohttp
    from service_harness import running_service, service_config

    from lightprobe.core.imageio import read_hdr_image

    cfg = service_config(tmp_path, pipeline={"fps": 10.0, "light_count": 64})
    out = tmp_path / "render.exr"
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER)
    z = addon_zip(tmp_path / "lightprobe_blender.zip")
    env = {**os.environ, "BLENDER_USER_CONFIG": str(tmp_path / "bl-config"),
           "BLENDER_USER_SCRIPTS": str(tmp_path / "bl-scripts"), "BLENDER_USER_DATAFILES": str(tmp_path / "bl-data")}
    async with running_service(cfg, scene="rooitou_park") as s, aiohttp.ClientSession() as c, \
            c.ws_connect(s.api + "/stream") as ws:
        for _ in range(40):  # past the start: the bracket settled
            await ws.receive_json(timeout=120)
        proc = await asyncio.create_subprocess_exec(str(bpy_python), str(driver), "--", str(z), s.url, s.token,
                                                    str(out), str(ORTHO), str(W), str(H), env=env, stdout=asyncio.subprocess.PIPE,
                                                    stderr=asyncio.subprocess.STDOUT)
        log, _ = await asyncio.wait_for(proc.communicate(), 1800)
        text = log.decode(errors="replace")
        (artifacts_dir / "blender_addon.log").write_text(text)
        assert proc.returncode == 0, text[-3000:]
        async with c.get(s.api + "/probe.exr", headers={"Authorization": f"Bearer {s.token}"}) as r:
            assert r.status == 200
            (tmp_path / "probe.exr").write_bytes(await r.read())
    info = json.loads(next(line for line in text.splitlines() if line.startswith("LIGHTPROBE "))[len("LIGHTPROBE "):])
    assert info["sun_energy"] > 0  # rooitou_park's sun is the primary light
    img = read_hdr_image(out)[..., :3].astype(np.float64)
    probe_map = read_hdr_image(tmp_path / "probe.exr")[..., :3]

    # 16 normals of the upper hemisphere (the probe sees it), each a 3 x 3 pixel patch
    from lightprobe.device.sampling.metrics import fibonacci_normals

    n_all = fibonacci_normals(64)
    n_all = n_all[n_all[:, 1] > 0.3][:16]  # probe frame, +y up ...
    to_blender = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)  # ... and Blender's (x, -z, y)
    pix, ref = [], []
    for n in n_all @ to_blender.T:
        col = int((n[0] / (ORTHO / 2) + 1) / 2 * W)
        row = int((1 - n[1] / (ORTHO / 2)) / 2 * H)
        rr, cc = np.mgrid[row - 1:row + 2, col - 1:col + 2]
        x = -ORTHO / 2 + (cc + 0.5) * ORTHO / W
        y = ORTHO / 2 - (rr + 0.5) * ORTHO / H
        nb = np.stack([x, y, np.sqrt(np.clip(1 - x * x - y * y, 0, 1))], -1).reshape(-1, 3)
        pix.append(img[rr, cc].reshape(-1, 3).mean(axis=0))
        ref.append(_irradiance(probe_map, nb @ to_blender).mean(axis=0) / np.pi)  # Blender -> probe: inverse
    pix_a, ref_a = np.array(pix), np.array(ref)
    lum = np.array([0.2126, 0.7152, 0.0722])
    err = np.abs(pix_a @ lum - ref_a @ lum) / (ref_a @ lum)
    (artifacts_dir / "blender_addon.json").write_text(json.dumps({"max_rel_err": float(err.max()),
                                                                  "median_rel_err": float(np.median(err)),
                                                                  **info}, indent=1))
    print(f"Cycles vs the probe's irradiance: median {np.median(err):.4f}, max {err.max():.4f}")
    assert err.max() <= 0.03, (err, pix_a, ref_a)


async def test_the_addon_finds_a_probe_by_dns_sd(tmp_path: Path) -> None:
    """The add-on's own one-shot mDNS query (standard library only) finds a probe the service
    advertises (python-zeroconf answering a legacy unicast query), with its URL and id."""
    import asyncio
    import importlib.util

    import aiohttp
    from service_harness import running_service, service_config

    spec = importlib.util.spec_from_file_location("lightprobe_blender_probe_io", ADDON / "probe_io.py")
    assert spec is not None
    assert spec.loader is not None
    probe_io = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(probe_io)
    cfg = service_config(tmp_path, mdns={"enabled": True, "interfaces": ["127.0.0.1"]}, probe={"name": "Stage left"})
    async with running_service(cfg, probe_id="b1b2c3d4e5f6") as s:
        found: list[dict[str, Any]] = []
        for _ in range(10):  # the advertisement is up once the probe has announced itself
            found = await asyncio.to_thread(probe_io.discover, 1.0, interface="127.0.0.1")
            if any(p["id"] == "b1b2c3d4e5f6" for p in found):
                break
        mine = [p for p in found if p["id"] == "b1b2c3d4e5f6"]
        assert mine, found
        assert mine[0]["name"] == "Stage left"
        assert mine[0]["url"] == f"http://127.0.0.1:{s.port}"
        async with aiohttp.ClientSession() as c, c.get(mine[0]["url"] + "/api/v1/healthz") as r:
            assert r.status == 200

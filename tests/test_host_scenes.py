"""glTF and USD scene files of the probe's lighting, checked by the field's own tools: the Khronos
glTF-Validator (npm), ktx-parse (npm) and Pixar's usd-core (pxr); and the service endpoints."""

from __future__ import annotations

import asyncio
import json
import math
import shutil
import subprocess
from pathlib import Path

import aiohttp
import numpy as np
import pytest
from service_harness import running_service, service_config

from lightprobe.core.imageio import read_hdr_image
from lightprobe.core.ktx2 import ktx2_cubemap_bytes, read_ktx2_cubemap
from lightprobe.core.sphere import coarse_equirect
from lightprobe.device.formats.cubemap import CubemapFilter
from lightprobe.device.formats.primary import ambient_map
from lightprobe.device.formats.scene import gltf_environment, usd_environment
from lightprobe.device.formats.sh_primary import EnvironmentEstimator

NODE_DIR = Path(__file__).parent / "node"
NODE = shutil.which("node")
needs_node = pytest.mark.skipif(NODE is None or not (NODE_DIR / "node_modules" / "gltf-validator").is_dir(),
                                reason="node + tests/node/node_modules (make test runs npm ci there)")


def _node(script: str, path: Path) -> dict:
    out = subprocess.run([NODE, str(NODE_DIR / script), str(path)], capture_output=True, text=True,
                         timeout=120, check=True)
    return json.loads(out.stdout)


@pytest.fixture(scope="module")
def sunny_env(shared_data: Path) -> tuple[np.ndarray, object]:
    m = read_hdr_image(shared_data / "envmaps" / "rooitou_park_1k.hdr")
    m = coarse_equirect(np.where(np.isfinite(m) & (m > 0), m, 0).astype(np.float32), 128)
    pose = {"rotation": [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], "position": [1.0, 2.5, -0.5]}
    env = EnvironmentEstimator().estimate(m, frame=7, probe="testprobe", pose=pose)
    return m, env


def _write_gltf(tmp: Path, m: np.ndarray, env: object) -> Path:
    cm = CubemapFilter(32).filter(ambient_map(m, env.primary))  # type: ignore[attr-defined]
    doc, files = gltf_environment(env, cm)  # type: ignore[arg-type]
    for uri, data in files.items():
        (tmp / uri).parent.mkdir(parents=True, exist_ok=True)
        (tmp / uri).write_bytes(data)
    path = tmp / "environment.gltf"
    path.write_text(json.dumps(doc))
    return path


@needs_node
def test_environment_gltf_passes_the_khronos_validator(tmp_path: Path, sunny_env: tuple) -> None:
    m, env = sunny_env
    path = _write_gltf(tmp_path, m, env)
    report = _node("validate_gltf.mjs", path)
    issues = report["issues"]
    assert issues["numErrors"] == 0, issues["messages"]
    doc = json.loads(path.read_text())
    # the validator saw the lights and every image (6 faces x 4 mips at 32 down to 4)
    assert len(doc["images"]) == 24
    assert report["info"]["resources"]
    assert all(r.get("image") or r["storage"] != "external"
                                                for r in report["info"]["resources"])
    light = doc["extensions"]["KHR_lights_punctual"]["lights"][0]
    assert light["type"] == "directional"
    # the node's local -Z (where the light shines) is minus the posed primary direction
    q = doc["nodes"][0]["rotation"]
    x, y, z, w = q
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    pose = np.array(env.pose["rotation"])
    assert np.allclose(rot @ [0, 0, -1], -(pose @ env.primary.direction), atol=1e-6)
    ibl = doc["extensions"]["EXT_lights_image_based"]["lights"][0]
    assert len(ibl["irradianceCoefficients"]) == 9
    assert ibl["specularImageSize"] == 32


@needs_node
def test_a_broken_gltf_fails_the_validator(tmp_path: Path, sunny_env: tuple) -> None:
    """The validator check can fail: an image index out of range is an error."""
    m, env = sunny_env
    path = _write_gltf(tmp_path, m, env)
    doc = json.loads(path.read_text())
    doc["scenes"][0]["nodes"] = [5]
    path.write_text(json.dumps(doc))
    assert _node("validate_gltf.mjs", path)["issues"]["numErrors"] > 0


@needs_node
def test_ktx2_cubemap_reads_in_ktx_parse(tmp_path: Path, sunny_env: tuple) -> None:
    m, _ = sunny_env
    cm = CubemapFilter(32).filter(m)
    path = tmp_path / "cube.ktx2"
    path.write_bytes(ktx2_cubemap_bytes(cm.mips, {"lightprobe.roughness": "0,0.25,0.5,0.75"}))
    info = _node("read_ktx2.mjs", path)
    assert info["vkFormat"] == 97
    assert info["typeSize"] == 2
    assert info["faceCount"] == 6
    assert info["pixelWidth"] == 32
    assert info["levelCount"] == 4
    assert info["supercompressionScheme"] == 0
    assert [lv["bytes"] for lv in info["levels"]] == [6 * n * n * 8 for n in (32, 16, 8, 4)]
    dfd = info["dfd"][0]
    assert (dfd["colorModel"], dfd["colorPrimaries"], dfd["transferFunction"]) == (1, 1, 1)
    assert dfd["bytesPlane"][0] == 8
    assert len(dfd["samples"]) == 4
    assert [s["bitOffset"] for s in dfd["samples"]] == [0, 16, 32, 48]
    assert info["keyValue"]["KTXwriter"].startswith("lightprobe")


def _openexr_direction(u: float, v: float) -> np.ndarray:
    """OpenEXR's latitude-longitude direction of a pixel centre (ImfEnvmap LatLong, as UsdLux
    DomeLight documents it): u, v in [0, 1] across the data window."""
    lat = -math.pi * (v - 0.5)
    lon = -2 * math.pi * (u - 0.5)
    return np.array([math.sin(lon) * math.cos(lat), math.sin(lat), math.cos(lon) * math.cos(lat)])


def test_environment_usda_opens_in_pxr_and_its_dome_points_at_the_sun(tmp_path: Path, sunny_env: tuple) -> None:
    pxr = pytest.importorskip("pxr")
    from pxr import Gf, Usd, UsdGeom, UsdLux

    from lightprobe.core.imageio import write_exr

    m, env = sunny_env
    (tmp_path / "environment.usda").write_text(usd_environment(env))
    write_exr(tmp_path / "environment_latlong.exr", m)
    write_exr(tmp_path / "environment_ambient_latlong.exr", ambient_map(m, env.primary))
    stage = Usd.Stage.Open(str(tmp_path / "environment.usda"))
    assert stage is not None
    assert pxr is not None
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    dome = UsdLux.DomeLight(stage.GetPrimAtPath("/Environment/Dome"))
    assert dome
    assert dome.GetTextureFormatAttr().Get() == UsdLux.Tokens.latlong
    tex = dome.GetTextureFileAttr().Get().resolvedPath
    assert Path(tex).name == "environment_latlong.exr"
    assert Path(tex).is_file()
    # the dome's brightest pixel, read in USD's (OpenEXR's) convention and posed by the stage
    img = read_hdr_image(tex)
    h, w = img.shape[:2]
    r, c = np.unravel_index(np.argmax(img @ [0.2126, 0.7152, 0.0722]), (h, w))
    d_local = _openexr_direction((c + 0.5) / w, (r + 0.5) / h)
    xf = UsdGeom.Xformable(dome.GetPrim()).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    d_world = np.array(xf.TransformDir(Gf.Vec3d(*d_local)))
    want = np.array(env.pose["rotation"]) @ env.primary.direction
    angle = math.degrees(math.acos(np.clip(d_world @ want / np.linalg.norm(d_world), -1, 1)))
    assert angle <= 3.0, angle
    # the other variant: ambient dome + a DistantLight whose -Z is the sun's travel
    stage.GetPrimAtPath("/Environment").GetVariantSets().GetVariantSet("lighting").SetVariantSelection("dome_and_sun")
    sun = UsdLux.DistantLight(stage.GetPrimAtPath("/Environment/PrimaryLight"))
    assert sun
    xs = UsdGeom.Xformable(sun.GetPrim()).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    travel = np.array(xs.TransformDir(Gf.Vec3d(0, 0, -1)))
    assert np.allclose(travel / np.linalg.norm(travel), -want, atol=1e-6)
    assert Path(UsdLux.DomeLight(stage.GetPrimAtPath("/Environment/Dome")).GetTextureFileAttr().Get().path).name \
        == "environment_ambient_latlong.exr"


# ---- the service -------------------------------------------------------------------------------
async def _first(c: aiohttp.ClientSession, url: str, within: float = 120.0) -> dict:
    loop = asyncio.get_running_loop()
    t_end = loop.time() + within
    while True:
        async with c.get(url) as r:
            if r.status == 200:
                return await r.json()  # type: ignore[no-any-return]
        if loop.time() > t_end:
            raise AssertionError(f"{url}: no 200 in {within} s")
        await asyncio.sleep(0.1)


async def test_service_serves_sh_cubemap_and_scene_files(tmp_path: Path) -> None:
    cfg = service_config(tmp_path, pipeline={"fps": 10.0, "light_count": 64})
    async with running_service(cfg) as s, aiohttp.ClientSession() as c:
        body = await _first(c, s.api + "/sh?convention=threejs")  # lighting data: no token needed
        assert body["kind"] == "sh"
        assert body["convention"] == "threejs"
        assert body["order"] == 2
        assert len(body["coefficients"]) == 9
        assert all(len(x) == 3 for x in body["coefficients"])
        assert body["probe"] == "probetest0001"
        assert body["stale"] is False
        async with c.get(s.api + "/sh?convention=webxr") as r:
            x = await r.json()
            assert len(x["sphericalHarmonicsCoefficients"]) == 27
        async with c.get(s.api + "/sh?convention=opengl") as r:
            assert r.status == 400
            assert (await r.json())["param"] == "convention"
        async with c.get(s.api + "/sh?order=3") as r:
            assert r.status == 400
        # images of the room need the token
        for path in ("/cubemap.ktx2", "/cubemap/px.exr", "/environment.gltf", "/environment.usda",
                     "/environment_latlong.exr"):
            async with c.get(s.api + path) as r:
                assert r.status == 401, path
        hdr = {"Authorization": f"Bearer {s.token}"}
        async with c.get(s.api + "/cubemap.ktx2?size=16", headers=hdr) as r:
            assert r.status == 200
            assert r.content_type == "image/ktx2"
            mips, kv = read_ktx2_cubemap(await r.read())
            assert [x.shape[1] for x in mips] == [16, 8, 4]
            assert kv["lightprobe.roughness"] == "0,0.5,1"
        async with c.get(s.api + "/cubemap.ktx2?size=48", headers=hdr) as r:
            assert r.status == 400
            assert (await r.json())["param"] == "size"
        async with c.get(s.api + "/cubemap/qx.exr", headers=hdr) as r:
            assert r.status == 404
        async with c.get(s.api + "/cubemap/py.exr?size=16&mip=2", headers=hdr) as r:
            assert r.status == 200
            (tmp_path / "py.exr").write_bytes(await r.read())
            assert read_hdr_image(tmp_path / "py.exr").shape == (4, 4, 3)
        async with c.get(s.api + "/environment.gltf", params={"access_token": s.token}) as r:
            assert r.status == 200
            doc = json.loads(await r.read())
        uri = doc["images"][0]["uri"]
        assert "access_token=" in uri  # a loader fetching it relative to the document keeps the token
        async with c.get(s.api + "/" + uri) as r:
            assert r.status == 200
            assert r.content_type == "image/png"
        async with c.get(s.api + "/environment.usda", headers=hdr) as r:
            text = await r.text()
            assert 'token inputs:texture:format = "latlong"' in text
        async with c.get(s.api + "/environment/nothing.png", headers=hdr) as r:
            assert r.status == 404


async def test_stream_subscription_interleaves_sh_with_light_sets(tmp_path: Path) -> None:
    cfg = service_config(tmp_path, pipeline={"fps": 10.0, "light_count": 64})
    async with running_service(cfg) as s, aiohttp.ClientSession() as c:
        await _first(c, s.api + "/sh")
        async with c.ws_connect(s.api + "/stream") as ws:
            await ws.send_str(json.dumps({"subscribe": ["sh"], "convention": "unity"}))
            msgs = [json.loads((await ws.receive(timeout=30)).data) for _ in range(8)]
            lights = [m["frame"] for m in msgs if "lights" in m]
            shs = [m for m in msgs if m.get("kind") == "sh"]
            assert shs
            assert all(m["convention"] == "unity" for m in shs)
            for m in shs:  # each SH message follows the light set of its own frame
                i = msgs.index(m)
                assert i > 0
                assert msgs[i - 1]["frame"] == m["frame"]
            assert lights
            await ws.send_str(json.dumps({"subscribe": ["sh"], "convention": "nope"}))
            err = None
            for _ in range(6):
                m = json.loads((await ws.receive(timeout=30)).data)
                if "error" in m:
                    err = m
                    break
            assert err is not None
            assert err["param"] == "subscribe"
            await ws.send_str(json.dumps({"subscribe": []}))
            await asyncio.sleep(0.5)
            tail = [json.loads((await ws.receive(timeout=30)).data) for _ in range(4)]
            assert all("lights" in m for m in tail[1:])


async def test_hostlink_reads_sh_cubemap_and_environment_and_the_served_gltf_validates(tmp_path: Path) -> None:
    from lightprobe.device.formats.sh_primary import sh_from_map
    from lightprobe.hostlink.client import ProbeAuthError, ProbeClient, ProbeRequestError

    cfg = service_config(tmp_path, pipeline={"fps": 10.0, "light_count": 64})
    async with running_service(cfg) as s, aiohttp.ClientSession() as c:
        await _first(c, s.api + "/sh")
        async with ProbeClient(s.url) as anon:
            sh = await anon.sh("filament")
            assert sh.convention == "filament"
            assert sh.coefficients.shape == (9, 3)
            with pytest.raises(ProbeRequestError, match="convention"):
                await anon.sh("directx")
            with pytest.raises(ProbeAuthError):
                await anon.cubemap()
        async with ProbeClient(s.url, token=s.token, timeout=60) as cl:
            cube = await cl.cubemap(size=16)
            assert [m.shape for m in cube.mips] == [(6, 16, 16, 3), (6, 8, 8, 3), (6, 4, 4, 3)]
            assert cube.roughness == [0.0, 0.5, 1.0]
            # the host's offline conversion of one frame's map agrees with the probe's SH of it
            result = s.state.runner.result
            env = await s.state.runner.environment()
            assert result.frame == env.frame
            mine = sh_from_map(result.equirect, "unity")
            assert np.allclose(mine.coefficients, env.to_json("unity")["coefficients"], rtol=1e-9, atol=1e-12)
            assert np.allclose(mine.ambient, env.to_json("unity")["ambient_coefficients"], rtol=1e-9, atol=1e-12)
            gl = await cl.environment("gltf")
            path = gl.save(tmp_path / "served")
            assert len(gl.files) == 30
            assert path.is_file()
            usd = await cl.environment("usd")
            usd.save(tmp_path / "served")
            assert (tmp_path / "served" / "environment_latlong.exr").is_file()
    if NODE is not None and (NODE_DIR / "node_modules" / "gltf-validator").is_dir():
        assert _node("validate_gltf.mjs", path)["issues"]["numErrors"] == 0
    pxr = pytest.importorskip("pxr")
    from pxr import Usd

    assert pxr is not None
    assert Usd.Stage.Open(str(tmp_path / "served" / "environment.usda"))


def test_export_cli_writes_every_format_and_rejects_bad_input(tmp_path: Path, shared_data: Path) -> None:
    from lightprobe.cli import main

    src = shared_data / "envmaps" / "lebombo_1k.hdr"
    assert main(["export", str(src), "--format", "sh", "--convention", "webxr", "--out", str(tmp_path / "sh.json")]) == 0
    body = json.loads((tmp_path / "sh.json").read_text())
    assert body["convention"] == "webxr"
    assert len(body["sphericalHarmonicsCoefficients"]) == 27
    assert main(["export", str(src), "--format", "ktx2", "--size", "16", "--out", str(tmp_path / "c.ktx2")]) == 0
    assert [m.shape[1] for m in read_ktx2_cubemap((tmp_path / "c.ktx2").read_bytes())[0]] == [16, 8, 4]
    assert main(["export", str(src), "--format", "usd", "--out", str(tmp_path / "env.usda")]) == 0
    assert (tmp_path / "env_latlong.exr").is_file()
    assert (tmp_path / "env_ambient_latlong.exr").is_file()
    assert main(["export", str(src), "--format", "gltf", "--size", "8", "--out", str(tmp_path / "env.gltf")]) == 0
    doc = json.loads((tmp_path / "env.gltf").read_text())
    assert all((tmp_path / im["uri"]).is_file() for im in doc["images"])
    (tmp_path / "pose.json").write_text('{"rotation": [[2, 0, 0], [0, 1, 0], [0, 0, 1]]}')
    bad = [["export", str(tmp_path / "none.hdr"), "--format", "sh", "--out", str(tmp_path / "x.json")],
           ["export", str(src), "--format", "ktx2", "--size", "12", "--out", str(tmp_path / "x.ktx2")],
           ["export", str(src), "--format", "sh", "--pose", str(tmp_path / "pose.json"), "--out", str(tmp_path / "x.json")]]
    for argv in bad:
        assert main(argv) == 2, argv
    assert not (tmp_path / "x.json").exists()
    assert not (tmp_path / "x.ktx2").exists()

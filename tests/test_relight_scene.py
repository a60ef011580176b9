"""Relighting end to end on a tiny scene: scene files, errors (exit 2), precompute cache, VCF,
rasteriser, images, CLI and live mode against a local probe-like server."""

from __future__ import annotations

import asyncio
import json
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from lightprobe.core.errors import InputError
from lightprobe.hostlink.relight.scene import load_obj, load_scene

CUBE = """# unit cube
v -0.5 0 -0.5
v 0.5 0 -0.5
v 0.5 1 -0.5
v -0.5 1 -0.5
v -0.5 0 0.5
v 0.5 0 0.5
v 0.5 1 0.5
v -0.5 1 0.5

f 1 4 3 2
f 5 6 7 8
f 1 2 6 5
f 4 8 7 3
f 1 5 8 4
f 2/1/1 3/2/2 7/3/3 6/4/4
"""


def write_scene(d: Path, movable: bool = True, **over: object) -> Path:
    (d / "cube.obj").write_text(CUBE)
    doc = {"version": 1,
           "materials": {"paint": {"type": "blinn-phong", "kd": [0.5, 0.4, 0.3], "ks": [0.2, 0.2, 0.2],
                                   "exponent": 30},
                         "floor": {"type": "lambert", "kd": [0.5, 0.5, 0.5]}},
           "objects": [{"name": "cube", "mesh": "cube.obj", "material": "paint", "movable": movable,
                        "translation": [0, 0, 0], "rotation_deg": [0, 20, 0], "scale": 0.5}],
           "ground": {"y": "auto", "size": 4.0, "resolution": 6, "material": "floor"},
           "camera": {"position": [1.5, 1.5, 2.5], "look_at": [0, 0.2, 0], "fov_deg": 45,
                      "width": 64, "height": 48}}
    doc.update(over)
    p = d / "scene.json"
    p.write_text(json.dumps(doc, indent=1))
    return p


def sky(h: int = 32) -> np.ndarray:
    """An equirect map: dim sky plus a bright sun patch (float32)."""
    img = np.full((h, 2 * h, 3), 0.2, np.float32)
    img[h // 4 - 1:h // 4 + 1, 5:7] = 500.0
    return img


# ---- scene files and errors -----------------------------------------------------------------------


def test_obj_parser_polygons_and_normals(tmp_path: Path) -> None:
    p = tmp_path / "cube.obj"
    p.write_text(CUBE)
    m = load_obj(p)
    assert m.vertices.shape == (8, 3)
    assert m.faces.shape == (12, 3)
    from lightprobe.hostlink.relight.scene import vertex_normals

    n = vertex_normals(m)
    c = m.vertices - m.vertices.mean(axis=0)
    assert np.all(np.einsum("ij,ij->i", n, c) > 0)       # outward normals


@pytest.mark.parametrize(("line", "needle"), [("v 1 2", "vertex needs 3"), ("v 1 a 2", "malformed vertex"),
                                              ("f 1 2 99", "out of range"), ("f 1 x 3", "malformed face")])
def test_malformed_obj_lines_name_file_and_line(tmp_path: Path, line: str, needle: str) -> None:
    p = tmp_path / "bad.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n# comment\n" + line + "\n")
    with pytest.raises(InputError, match=rf"bad\.obj:5: .*{needle}"):
        load_obj(p)


def test_scene_errors_exit_2_naming_the_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from lightprobe.cli.relight import main

    lights = tmp_path / "sky.exr"
    from lightprobe.core.imageio import write_exr

    write_exr(lights, sky())
    out = tmp_path / "o.png"
    # unknown material
    p = write_scene(tmp_path)
    doc = json.loads(p.read_text())
    doc["objects"][0]["material"] = "chrome"
    p.write_text(json.dumps(doc, indent=1))
    lineno = next(i for i, s in enumerate(p.read_text().splitlines(), 1) if '"chrome"' in s)
    assert main([str(p), "--lights", str(lights), "--out", str(out), "--quiet"]) == 2
    assert f"scene.json:{lineno}: unknown material 'chrome'" in capsys.readouterr().err
    # missing mesh
    doc["objects"][0].update(material="paint", mesh="nothere.obj")
    p.write_text(json.dumps(doc, indent=1))
    lineno = next(i for i, s in enumerate(p.read_text().splitlines(), 1) if "nothere.obj" in s)
    assert main([str(p), "--lights", str(lights), "--out", str(out), "--quiet"]) == 2
    assert f"scene.json:{lineno}: mesh file 'nothere.obj'" in capsys.readouterr().err
    # malformed OBJ line inside the mesh
    (tmp_path / "bad.obj").write_text(CUBE.replace("v 0.5 1 0.5", "v 0.5 1"))
    doc["objects"][0]["mesh"] = "bad.obj"
    p.write_text(json.dumps(doc))
    assert main([str(p), "--lights", str(lights), "--out", str(out), "--quiet"]) == 2
    assert "bad.obj:8: vertex needs 3 coordinates" in capsys.readouterr().err
    # unknown material type, invalid JSON
    p.write_text('{"objects": [],\n "materials": {"x": {"type": "glass"}}}')
    with pytest.raises(InputError, match=r"scene\.json:2: .*unknown type 'glass'"):
        load_scene(p)
    p.write_text('{"objects": [\n}')
    assert main([str(p), "--lights", str(lights), "--out", str(out), "--quiet"]) == 2
    assert "scene.json:2: invalid JSON" in capsys.readouterr().err


# ---- precompute, render ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> tuple[object, object, Path]:
    from lightprobe.hostlink.relight.cuts.precompute import precompute

    d = tmp_path_factory.mktemp("tiny")
    scene = load_scene(write_scene(d))
    pre = precompute(scene, spheres=4, grid=6, cache_dir=d / "cache", progress=False)
    return scene, pre, d


def test_precompute_is_cached_and_deterministic(tiny: tuple) -> None:
    from lightprobe.hostlink.relight.cuts.coding import is_cut
    from lightprobe.hostlink.relight.cuts.precompute import precompute

    scene, pre, d = tiny
    again = precompute(scene, spheres=4, grid=6, cache_dir=d / "cache", progress=False)
    assert again.cached
    assert not pre.cached
    assert np.array_equal(again.svc_heights, pre.svc_heights)
    np.testing.assert_array_equal(again.svc_values, pre.svc_values)
    fresh = precompute(scene, spheres=4, grid=6, cache_dir=d / "cache2", progress=False)
    assert np.array_equal(fresh.svc_heights, pre.svc_heights)
    assert np.array_equal(fresh.vcf[0].heights, pre.vcf[0].heights)
    for i in range(0, len(pre.vertices), 7):
        assert is_cut(pre.svc_heights[pre.svc_offsets[i]:pre.svc_offsets[i + 1]])
    f = pre.vcf[0]
    assert len(f.offsets) - 1 == 4 * 6 * 6 * 6
    for k in range(0, len(f.offsets) - 1, 37):
        assert is_cut(f.heights[f.offsets[k]:f.offsets[k + 1]])


def test_vcf_shadows_ground_and_moving_far_away_removes_them(tiny: tuple) -> None:
    from lightprobe.hostlink.relight.cuts.render import Relighter

    scene, pre, _ = tiny
    rl = Relighter(scene, pre)
    rl.set_equirect(sky())
    ground = np.nonzero(pre.object_id == 1)[0]
    eye = scene.camera.position
    with_obj, _ = rl.vertex_radiance(eye, ground)
    rl.move("cube", [100.0, 0, 0])                       # out of every VCF sphere
    without, _ = rl.vertex_radiance(eye, ground)
    static, _ = rl.vertex_radiance(eye, ground, use_vcf=False)
    np.testing.assert_allclose(without, static, rtol=1e-9)   # dynamic path == SVC path when culled
    assert (with_obj.sum(axis=1) < without.sum(axis=1) - 1e-9).sum() > 3   # the cube casts shadows
    assert np.all(with_obj <= without + 1e-9)


def test_all_black_lights_give_black_vertices(tiny: tuple) -> None:
    from lightprobe.hostlink.relight.cuts.render import Relighter

    scene, pre, _ = tiny
    rl = Relighter(scene, pre)
    rl.set_equirect(np.zeros((16, 32, 3), np.float32))
    b, _ = rl.vertex_radiance(scene.camera.position)
    assert np.all(b == 0)


def test_raster_bary_and_render_outputs(tiny: tuple, tmp_path: Path) -> None:
    from lightprobe.core.imageio import read_hdr_image
    from lightprobe.hostlink.relight.cuts.render import Relighter, rasterize
    from lightprobe.hostlink.relight.raster import write_image

    scene, pre, _ = tiny
    r = rasterize(scene.camera, pre.vertices, pre.faces)
    hit = r.tri >= 0
    assert 0.2 < hit.mean() < 1.0
    np.testing.assert_allclose(r.bary[hit].sum(axis=1), 1, atol=1e-5)
    assert np.all(r.bary[hit] >= -1e-6)
    rl = Relighter(scene, pre)
    rl.set_equirect(sky())
    img, stats = rl.render(background=sky(), raster=r)
    assert img.shape == (48, 64, 3)
    assert np.isfinite(img).all()
    assert img[hit].max() > 0
    assert 0 < stats["visible_vertices"] < len(pre.vertices)
    write_image(tmp_path / "x.exr", img)
    np.testing.assert_allclose(read_hdr_image(tmp_path / "x.exr"), img, rtol=1e-6)
    write_image(tmp_path / "x.png", img)
    assert (tmp_path / "x.png").stat().st_size > 100


def test_material_edit_changes_only_that_material(tiny: tuple) -> None:
    from lightprobe.hostlink.relight.cuts.render import Relighter
    from lightprobe.hostlink.relight.scene import Material

    scene, pre, _ = tiny
    rl = Relighter(scene, pre)
    rl.set_equirect(sky())
    eye = scene.camera.position
    a, _ = rl.vertex_radiance(eye)
    rl.set_material("paint", Material("ward", (0.1, 0.1, 0.1), (0.5, 0.5, 0.5), alpha=0.15))
    b, _ = rl.vertex_radiance(eye)
    cube = pre.object_id == 0
    assert not np.allclose(a[cube], b[cube])
    np.testing.assert_array_equal(a[~cube], b[~cube])


# ---- CLI with a light set, and live mode against a local server ------------------------------------


def _lightset_doc(frame: int, scale: float) -> dict:
    return {"version": 1, "probe": "test", "frame": frame, "timestamp": 0.0, "method": "q2tree",
            "unit": "relative", "stale": False,
            "pose": {"rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "position": [0, 0, 0]},
            "lights": [{"direction": [0.3, 0.9, 0.3], "rgb": [scale, scale, scale], "solid_angle": 0.01},
                       {"direction": [0, 1, 0], "rgb": [1, 1, 1], "solid_angle": 1.0}]}


@pytest.fixture
def probe_server() -> Iterator[str]:
    from aiohttp import web

    loop = asyncio.new_event_loop()
    ready = threading.Event()
    state: dict[str, object] = {}

    async def lights(_: web.Request) -> web.Response:
        return web.json_response(_lightset_doc(1, 5.0))

    async def stream(request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse()
        await ws.prepare(request)
        for k in range(3):
            await ws.send_str(json.dumps(_lightset_doc(k + 2, 10.0 * (k + 1))))
            await asyncio.sleep(0.05)
        await ws.close()
        return ws

    async def start() -> None:
        app = web.Application()
        app.router.add_get("/api/v1/lights", lights)
        app.router.add_get("/api/v1/stream", stream)
        runner = web.AppRunner(app)
        await runner.setup()
        site = web.TCPSite(runner, "127.0.0.1", 0)
        await site.start()
        state["runner"] = runner
        state["port"] = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
        ready.set()

    t = threading.Thread(target=lambda: (loop.run_until_complete(start()), loop.run_forever()), daemon=True)
    t.start()
    assert ready.wait(10)
    yield f"http://127.0.0.1:{state['port']}"
    asyncio.run_coroutine_threadsafe(state["runner"].cleanup(), loop).result(10)  # type: ignore[union-attr]
    loop.call_soon_threadsafe(loop.stop)
    t.join(10)


def test_cli_lightset_json_url_and_live(tmp_path: Path, probe_server: str) -> None:
    from lightprobe.cli.relight import main

    p = write_scene(tmp_path, movable=False)
    lj = tmp_path / "lights.json"
    lj.write_text(json.dumps(_lightset_doc(1, 5.0)))
    cache = tmp_path / "cache"
    assert main([str(p), "--lights", str(lj), "--out", str(tmp_path / "a.exr"), "--cache", str(cache), "--quiet"]) == 0
    from lightprobe.core.imageio import read_hdr_image

    a = read_hdr_image(tmp_path / "a.exr")
    assert a.max() > 0
    assert main([str(p), "--lights", probe_server, "--out", str(tmp_path / "b.exr"), "--cache", str(cache), "--quiet"]) == 0
    np.testing.assert_allclose(read_hdr_image(tmp_path / "b.exr"), a, rtol=1e-6)   # same light set
    out = tmp_path / "live.exr"
    assert main([str(p), "--lights", probe_server, "--out", str(out), "--cache", str(cache), "--quiet",
                 "--live", "--frames", "3"]) == 0
    live = read_hdr_image(out)                           # last frame: sun 30x the first, brighter
    assert live.sum() > a.sum() * 2
    assert main([str(p), "--lights", str(tmp_path / "nope.txt"), "--out", str(out), "--quiet"]) == 2


def test_dispatcher_exit_codes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from lightprobe.cli import main as lightprobe

    p = write_scene(tmp_path, movable=False)
    assert lightprobe(["relight", str(p), "--lights", str(tmp_path / "x.exr"), "--out", str(tmp_path / "o.jpg")]) == 2
    assert "--out must end in .png or .exr" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        lightprobe(["relight", str(p), "--out", "o.png"])     # --lights missing: argparse
    assert e.value.code == 2


def test_render_cache_matches_fresh_render(tiny: tuple) -> None:
    from lightprobe.hostlink.relight.cuts.render import Relighter
    from lightprobe.hostlink.relight.scene import Camera, Material

    scene, pre, _ = tiny
    rl = Relighter(scene, pre)
    rl.set_equirect(sky())
    rl.render()

    def fresh(cam: Camera) -> np.ndarray:
        f = Relighter(scene, pre)
        f.mats = rl.mats.copy()
        f.translation = rl.translation.copy()
        f.set_equirect(sky())
        return f.render(cam)[0]

    cam2 = Camera(np.array([-1.0, 1.2, 2.0]), scene.camera.look_at, scene.camera.up, 45, 64, 48)
    img, st = rl.render(cam2)                              # view change: glossy cube re-shaded
    assert 0 < st["shaded_vertices"] < st["visible_vertices"]
    np.testing.assert_allclose(img, fresh(cam2), rtol=1e-6, atol=1e-9)
    rl.set_material("floor", Material("lambert", (0.9, 0.1, 0.1)))
    np.testing.assert_allclose(rl.render(cam2)[0], fresh(cam2), rtol=1e-6, atol=1e-9)
    rl.move("cube", [0.3, 0, 0.1])
    np.testing.assert_allclose(rl.render(cam2)[0], fresh(cam2), rtol=1e-6, atol=1e-9)
    assert rl.render(cam2)[1]["shaded_vertices"] == 0     # nothing changed: all cached


def test_cli_move_and_rotate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from lightprobe.cli.relight import main
    from lightprobe.core.imageio import read_hdr_image, write_exr

    p = write_scene(tmp_path)
    lights = tmp_path / "sky.exr"
    write_exr(lights, sky())
    base = [str(p), "--lights", str(lights), "--cache", str(tmp_path / "cache"), "--spheres", "4", "--grid", "6",
            "--quiet"]
    assert main([*base, "--out", str(tmp_path / "a.exr"), "--move", "cube=0.3,0,0"]) == 0
    assert main([*base, "--out", str(tmp_path / "b.exr"), "--move", "cube=0.3,0,0", "--rotate", "cube=0,35,0"]) == 0
    a, b = read_hdr_image(tmp_path / "a.exr"), read_hdr_image(tmp_path / "b.exr")
    assert np.isfinite(b).all()
    assert np.abs(a - b).max() > 1e-3 * a.max()                # the cube turned
    assert main([*base, "--out", str(tmp_path / "c.exr"), "--rotate", "cube=0,x,0"]) == 2
    assert "--rotate 'cube=0,x,0': expected NAME=rx,ry,rz" in capsys.readouterr().err
    assert main([*base, "--out", str(tmp_path / "c.exr"), "--rotate", "ground=0,10,0"]) == 2
    assert "'ground' is not a movable object" in capsys.readouterr().err

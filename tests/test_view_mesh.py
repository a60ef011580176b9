"""The mesh ``/view`` shows beside its spheres: ``[view] mesh`` / ``lightprobe serve --view-mesh``,
checked at start-up (a bad file names itself and stops the start, exit 2) and served as it is
at ``GET /view/mesh.obj`` (404 when none is configured). The page itself loading it is in
``tests/test_host_threejs.py``."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import aiohttp
import pytest

from lightprobe.core.errors import InputError
from lightprobe.device.service.viewmesh import MAX_BYTES, load_view_mesh


def test_the_shared_cow_is_read_as_the_page_draws_it(shared_data: Path) -> None:
    m = load_view_mesh(shared_data / "meshes" / "spot.obj")
    assert m.name == "spot.obj"
    assert m.triangles == 5856  # spot.obj's own 'f' lines, all triangles
    assert m.vertices > 2900
    assert m.body == (shared_data / "meshes" / "spot.obj").read_bytes()


def test_polygons_count_as_fans_and_negative_indices_are_relative(tmp_path: Path) -> None:
    p = tmp_path / "quad.obj"
    p.write_text("# a quad and a pentagon\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\n"
                 "f 1/1 2/1 3/1 4/1\nv 0.5 2 0\nf -5 -4 -3 -2 -1\ng rest\nusemtl x\n")
    m = load_view_mesh(p)
    assert (m.vertices, m.triangles) == (5, 2 + 3)


@pytest.mark.parametrize(("text", "words"), [
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", "face vertex '4'"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", "at least three"),
    ("v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "three finite"),
    ("v 0 0\n", "three finite"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces"),
    ("f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n", "defined before it"),
    ("", "no faces"),
])
def test_a_bad_mesh_names_its_file_and_line(tmp_path: Path, text: str, words: str) -> None:
    p = tmp_path / "bad.obj"
    p.write_text(text)
    with pytest.raises(InputError, match=words) as e:
        load_view_mesh(p)
    assert str(p) in str(e.value)
    assert e.value.param == "view.mesh"


def test_missing_and_binary_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="cannot read") as e:
        load_view_mesh(tmp_path / "nope.obj", "--view-mesh")
    assert "nope.obj" in str(e.value)
    assert e.value.param == "--view-mesh"
    b = tmp_path / "b.obj"
    b.write_bytes(b"\xff\xfe\x00v 0 0 0")
    with pytest.raises(InputError, match="not a text"):
        load_view_mesh(b)


def test_serve_with_a_bad_view_mesh_exits_2(tmp_path: Path) -> None:
    from tests.test_service_cli import ROOT, SERVE, _env

    bad = tmp_path / "broken.obj"
    bad.write_text("v 0 0 0\nf 1 2 3\n")
    p = subprocess.run([os.sys.executable, str(SERVE), "--port", "0", "--state-dir", str(tmp_path / "s"),  # type: ignore[attr-defined]
                        "--view-mesh", str(bad)], cwd=ROOT, env=_env(), capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 2, p.stderr
    assert "broken.obj" in p.stderr
    assert "--view-mesh" in p.stderr


async def test_the_mesh_is_served_and_none_is_a_404(tmp_path: Path, shared_data: Path) -> None:
    from service_harness import running_service, service_config

    spot = shared_data / "meshes" / "spot.obj"
    async with running_service(service_config(tmp_path / "a", view={"mesh": str(spot)})) as s, \
            aiohttp.ClientSession() as http:
        async with http.get(s.url + "/view/mesh.obj") as r:  # a model, not the room: no token
            assert r.status == 200
            assert r.content_type == "model/obj"
            assert r.headers["X-Mesh-Triangles"] == "5856"
            assert await r.read() == spot.read_bytes()
        async with http.get(s.url + "/view/mesh.obj?x=1") as r:
            assert r.status == 400
    async with running_service(service_config(tmp_path / "b")) as s, aiohttp.ClientSession() as http:
        r = await http.get(s.url + "/view/mesh.obj")
        assert r.status == 404
        body = await r.json()
        assert body["param"] == "view.mesh"
        assert "--view-mesh" in body["error"]


def test_devices_and_oversized_files_are_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not a regular file"):
        load_view_mesh("/dev/zero")  # would never end if read
    with pytest.raises(InputError, match="not a regular file"):
        load_view_mesh(tmp_path)
    big = tmp_path / "big.obj"
    with big.open("wb") as f:  # sparse: no disk used
        f.truncate(MAX_BYTES + 10)
    with pytest.raises(InputError, match="more than the") as e:
        load_view_mesh(big)
    assert "big.obj" in str(e.value)


async def test_put_config_checks_a_new_mesh_before_saving_it(tmp_path: Path, shared_data: Path) -> None:
    """A mesh the next start could not load is refused now (400, nothing saved), like a
    ``service.host`` that does not resolve; a good one is saved and pending a restart."""
    from service_harness import running_service, service_config

    from lightprobe.device.service.config import load_config

    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nf 1 2 3\n")
    async with running_service(service_config(tmp_path)) as s, aiohttp.ClientSession() as http:
        r = await http.put(s.api + "/config", json={"view": {"mesh": str(bad)}}, headers=s.auth)
        assert r.status == 400
        body = await r.json()
        assert body["param"] == "view.mesh"
        assert "bad.obj" in body["error"]
        assert load_config(tmp_path / "config.toml").get("view", "mesh") == ""
        spot = str(shared_data / "meshes" / "spot.obj")
        r = await http.put(s.api + "/config", json={"view": {"mesh": spot}}, headers=s.auth)
        assert r.status == 200
        assert load_config(tmp_path / "config.toml").get("view", "mesh") == spot
        assert (await r.json())["pending"]["view"]["mesh"] == spot  # takes effect at the next start

"""SG relighting (Michiels et al. 2015; lightprobe.hostlink.relight.sg.relighter): closed forms, spot.obj on a ground plane
under the six shared maps against the brute force (2^15 directions, every ray cast, the true map,
so the SG fit's error counts), deformation, the CLI.

Metric as in test_relight_accuracy.py: relative RMS over vertices of the luminance of the radiance
towards the camera, every 5th vertex. Bounds are the issue's targets.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lightprobe.core.errors import InputError

pytestmark = pytest.mark.slow

MAPS = ["studio_small_03_1k.hdr", "rooitou_park_1k.hdr", "potsdamer_platz_1k.hdr", "lebombo_1k.hdr",
        "dikhololo_night_1k.hdr", "interior_blender.exr"]


def _scene_doc(shared: Path, clay: str = "phong") -> dict:
    return {"version": 1,
            "materials": {"clay": {"type": clay, "kd": [0.6, 0.5, 0.4], "ks": [0.2, 0.2, 0.2], "exponent": 20},
                          "floor": {"type": "lambert", "kd": [0.5, 0.5, 0.5]}},
            "objects": [{"name": "spot", "mesh": str(shared / "meshes" / "spot.obj"), "material": "clay"}],
            "ground": {"y": "auto", "size": 3.0, "resolution": 24, "material": "floor"},
            "camera": {"position": [2.0, 1.2, 2.5], "look_at": [0, -0.2, 0.4], "fov_deg": 40,
                       "width": 96, "height": 72}}


def _rel_rms(b: np.ndarray, ref: np.ndarray) -> float:
    from lightprobe.core.sphere import luminance

    y, yr = luminance(b), luminance(ref)
    return float(np.sqrt(((y - yr) ** 2).sum() / (yr ** 2).sum()))


def _reference(rl, light: tuple[np.ndarray, np.ndarray], eye: np.ndarray, vidx: np.ndarray) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The independent brute force (:mod:`lightprobe.bench.relight_reference`) of the relighter's
    current geometry under ``light`` = (directions, radiance x solid angle) per map."""
    from lightprobe.bench.relight_reference import brute_force_radiance

    return brute_force_radiance(rl.vertices, rl.faces, rl.normals(), rl.matid, rl.mats, *light, eye, vidx)


@pytest.fixture(scope="module")
def maps(envmap_paths: dict[str, Path]) -> list[np.ndarray]:
    from lightprobe.core.imageio import read_hdr_image

    return [read_hdr_image(envmap_paths[m]) for m in MAPS]


@pytest.fixture(scope="module")
def lobes(maps: list[np.ndarray]):  # type: ignore[no-untyped-def]
    """The SG fit of each map, as a probe would serve it (fitted once)."""
    from lightprobe.device.formats.sgfit import fit_sg

    return [fit_sg(m) for m in maps]


@pytest.fixture(scope="module", params=["lambert", "phong"])
def spot(request, shared_data: Path, maps: list[np.ndarray], tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    from lightprobe.bench.relight_reference import equirect_quadrature
    from lightprobe.hostlink.relight.scene import load_scene
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter

    d = tmp_path_factory.mktemp("sg")
    (d / "spot.json").write_text(json.dumps(_scene_doc(shared_data, request.param)))
    scene = load_scene(d / "spot.json")
    rl = SGRelighter(scene, visibility="rays")
    vidx = np.arange(0, len(rl.vertices), 5)
    light = equirect_quadrature(maps)
    ref = _reference(rl, light, scene.camera.position, vidx)
    return request.param, scene, vidx, light, ref


def test_zonal_cosine_matches_quadrature_and_limits() -> None:
    """C(t) = integral exp(lam (p.w - 1)) max(a.w, 0) dw against a Fibonacci-sphere sum; as lam -> 0
    it is pi for every t, for a sharp lobe (2 pi / lam) max(t, 0)."""
    from lightprobe.hostlink.relight.sg.tables import zonal_cosine

    n = 400_000
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    r = np.sqrt(1 - z * z)
    ph = k * np.pi * (3 - np.sqrt(5))
    w = np.stack([r * np.cos(ph), r * np.sin(ph), z], 1)
    t = np.linspace(-1, 1, 1025)
    for lam in (0.5, 3.0, 20.0):
        c = zonal_cosine(lam)
        for ti in (-0.9, -0.2, 0.0, 0.4, 0.95):
            a = np.array([np.sqrt(1 - ti * ti), 0.0, ti])
            q = float((np.exp(lam * (w[:, 2] - 1)) * np.maximum(w @ a, 0)).sum() * 4 * np.pi / n)
            assert np.interp(ti, t, c) == pytest.approx(q, rel=2e-3, abs=1e-6)
    np.testing.assert_allclose(zonal_cosine(1e-7), np.pi, rtol=5e-5)
    sharp = zonal_cosine(5000.0)
    np.testing.assert_allclose(sharp[t > 0.05] * 5000 / (2 * np.pi), t[t > 0.05], rtol=2e-3)
    assert np.all(sharp[t < -0.2] < 1e-12)


def test_unshadowed_shading_is_exact_for_the_lobes(shared_data: Path, lobes, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """A ground plane alone (nothing can shadow it): the host's tables give the lobes' own
    irradiance within 0.5% with rays and with voxels (a plane cannot hide anything above it from
    its own points, so their cones are not traced: no voxel self-shadowing), measured 0.00-0.02%:
    the reference sums the
    residual lobes' SG radiance on 2^15 cells (its own quadrature) and adds the peaks (too sharp for those
    directions: the sun is 0.5 deg) by their zonal integral, checked against quadrature above.
    What is left in the tests below is visibility and the probe's fit."""
    from lightprobe.bench.relight_reference import function_quadrature
    from lightprobe.core.sg import SGLighting
    from lightprobe.hostlink.relight.scene import load_scene
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter
    from lightprobe.hostlink.relight.sg.tables import zonal_cosine

    doc = _scene_doc(shared_data, "lambert")
    doc["objects"] = []
    (tmp_path / "ground.json").write_text(json.dumps(doc))
    scene = load_scene(tmp_path / "ground.json")
    vidx = np.arange(0, 625, 7)
    res, peaks = [], []
    for sg in lobes:
        keep = np.array([k == "residual" for k in sg.kinds])
        res.append(SGLighting(sg.axes[keep], sg.sharpness[keep], sg.amplitude[keep], ["residual"] * int(keep.sum())))
        peaks.append((sg.axes[~keep], sg.sharpness[~keep], sg.amplitude[~keep]))
    light = function_quadrature([sg.radiance for sg in res])
    t = np.linspace(-1, 1, 1025)
    for vis in ("rays", "voxels"):
        rl = SGRelighter(scene, visibility=vis)
        ref = _reference(rl, light, scene.camera.position, vidx)
        kd = rl.mats[rl.matid[vidx], 1:4] / np.pi
        for k, (ax, lam, amp) in enumerate(peaks):
            for a, la, mu in zip(ax, lam, amp, strict=True):
                ref[k] += kd * mu * np.interp(rl.normals()[vidx] @ a, t, zonal_cosine(float(la)))[:, None]
        for k in range(len(MAPS)):
            rl.set_sg(lobes[k])
            err = _rel_rms(rl.vertex_radiance(scene.camera.position, vidx), ref[k])
            print(vis, MAPS[k], f"{err:.4f}")
            assert err <= 0.005, (vis, MAPS[k], err)


# the targets: 3% / 5% with exact visibility, 8% / 12% with voxels (measured 2026-12-07:
# Lambert voxels <= 6.7%, Phong voxels <= 6.5%, BENCHMARKS.md "Issue 17, host side")
BOUNDS = {("lambert", "rays"): 0.03, ("phong", "rays"): 0.05,
          ("lambert", "voxels"): 0.08, ("phong", "voxels"): 0.12}


@pytest.mark.parametrize("visibility", ["rays", "voxels"])
def test_spot_on_the_ground_under_every_map(spot, lobes, visibility: str) -> None:  # type: ignore[no-untyped-def]
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter

    clay, scene, vidx, _light, ref = spot
    rl = SGRelighter(scene, visibility=visibility)
    errs = []
    for k in range(len(MAPS)):
        rl.set_sg(lobes[k])
        errs.append(_rel_rms(rl.vertex_radiance(scene.camera.position, vidx), ref[k]))
    print(clay, visibility, " ".join(f"{m}: {e:.4f}" for m, e in zip(MAPS, errs, strict=True)))
    for m, e in zip(MAPS, errs, strict=True):
        assert e <= BOUNDS[clay, visibility], (m, e)
    assert min(errs) > 0
    if visibility == "voxels":   # cones approximate what the rays measure: never better than them
        rays = SGRelighter(scene, visibility="rays")
        rays.set_sg(lobes[3])
        assert _rel_rms(rays.vertex_radiance(scene.camera.position, vidx), ref[3]) < errs[3]


def test_a_deforming_mesh_keeps_its_accuracy_and_revoxelises_only_itself(spot, lobes) -> None:  # type: ignore[no-untyped-def]
    """Deform the cow every frame (squash and shear, different each frame): no precompute, the
    error against the brute force of the deformed scene stays near the static one; the ground
    is no voxels at all (a rectangle: an exact occluder of the cones)."""
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter

    clay, scene, vidx, light, _ref = spot
    if clay != "phong":
        pytest.skip("one material is enough for the deformation")
    rl = SGRelighter(scene, visibility="voxels")
    rl.set_sg(lobes[1])
    rl.vertex_radiance(scene.camera.position, vidx)
    assert rl._occ[1] is None
    assert 1 in rl._rects()[1]
    assert rl._occ[0] is not None
    rest = rl.objects[0].rest
    lo = rest[:, 1].min()
    for f in range(3):
        v = rest.copy()
        s = 1.0 - 0.12 * (f + 1)
        v[:, 1] = lo + (v[:, 1] - lo) * s          # squash towards the ground
        v[:, 0] += 0.15 * f * (v[:, 1] - lo)        # and shear
        rl.set_vertices("spot", v)
        b = rl.vertex_radiance(scene.camera.position, vidx)
        assert rl._occ[1] is None
        ref = _reference(rl, (light[0][1:2], light[1][1:2]), scene.camera.position, vidx)[0]
        err = _rel_rms(b, ref)
        print(f"frame {f}: {err:.4f}")
        assert err <= 0.04          # measured 2.4-2.8% (static, same map: 2.4%)
    with pytest.raises(InputError) as e:
        rl.set_vertices("spot", rest[:10])
    assert e.value.param == "vertices"
    with pytest.raises(InputError, match="no object named 'cat'"):
        rl.move("cat", np.zeros(3))


def test_shadow_rays_leave_out_only_the_planes_that_cannot_occlude(spot) -> None:  # type: ignore[no-untyped-def]
    """The sun's shadow rays go up from the ground and the cow: the floor cannot occlude any of
    them, so it is left out of their BVH, with the same answer as the full scene; a light below
    the floor's horizon keeps it in."""
    from lightprobe.hostlink.relight.rays import occluded, scene_eps
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter

    _clay, scene, _vidx, _light, _ref = spot
    rl = SGRelighter(scene, visibility="voxels")
    pos, nrm = rl.vertices, rl.normals()
    ground = [k for k, o in enumerate(rl.objects) if o.name == "ground"]
    assert [k for k, p in enumerate(rl._planes()) if p is not None] == ground
    eps = scene_eps(scene)
    for d, left_out in ((np.array([0.3, 0.8, -0.52]), True), (np.array([0.6, -0.2, 0.77]), False)):
        d = d / np.linalg.norm(d)
        got = rl._shadow_rays(pos, nrm, d)
        up = nrm @ d > 0
        full = np.zeros(len(pos))
        full[up] = ~occluded(rl._embree_scene(), pos[up] + eps * nrm[up], np.broadcast_to(d, (int(up.sum()), 3)))
        assert np.array_equal(got, full)
        assert 0 < full.mean() < 1
        o = pos[up] + eps * nrm[up]
        assert (rl._occluders(o, d[None]) is rl._embree_scene(frozenset(ground))) == left_out


def test_broad_peaks_render_soft_shadows_from_the_vertices(spot, lobes) -> None:  # type: ignore[no-untyped-def]
    """studio_small_03's lamps (2-4 deg) are broad peaks: with voxels their shadows are 8 lobe
    rays per vertex of the visible triangles, interpolated; the image agrees with the per-vertex
    shading where pixels sit on vertices, and a light change re-traces nothing."""
    from lightprobe.core.sg import SGLighting
    from lightprobe.hostlink.relight.raster import rasterize
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter

    _clay, scene, _vidx, _light, _ref = spot
    rl = SGRelighter(scene, visibility="voxels")
    rl.set_sg(lobes[0])
    assert not rl._thin().any()
    img, stats = rl.render()
    assert np.isfinite(img).all()
    assert stats["peak_cones"] > 0
    vis = np.unique(rl._frame["fv"])
    assert stats["peak_cones"] <= len(vis) * len(rl._thin())   # per vertex, not per pixel
    ras = rasterize(scene.camera, rl.vertices, rl.faces, rays=False)
    cov = ras.tri >= 0
    corner = ras.bary[cov].max(axis=1) > 0.97   # pixels almost on a vertex
    fv = rl.faces[ras.tri[cov]][corner]
    v = fv[np.arange(len(fv)), ras.bary[cov][corner].argmax(axis=1)]
    want = rl.vertex_radiance(scene.camera.position, v)
    got = img[cov][corner]
    lum = np.array([0.2126, 0.7152, 0.0722])
    rel = np.abs(got @ lum - want @ lum) / np.maximum(want @ lum, 1e-6)
    assert np.median(rel) < 0.03, np.median(rel)
    sg = lobes[0]
    rl.set_sg(SGLighting(sg.axes, sg.sharpness, sg.amplitude * 0.5, list(sg.kinds)))   # the lamps dim
    dim, again = rl.render()
    assert again["wide_cones"] == 0
    assert again["peak_cones"] == 0
    assert np.allclose(dim, 0.5 * img, rtol=1e-5, atol=1e-7)


def test_refuses_what_it_cannot_shade(shared_data: Path, tmp_path: Path) -> None:
    from lightprobe.hostlink.relight.scene import load_scene
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter

    doc = _scene_doc(shared_data, "ward")
    (tmp_path / "w.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="lambert and phong, not 'ward'") as e:
        SGRelighter(load_scene(tmp_path / "w.json"))
    assert e.value.param == "material"
    (tmp_path / "p.json").write_text(json.dumps(_scene_doc(shared_data)))
    scene = load_scene(tmp_path / "p.json")
    with pytest.raises(InputError) as e:
        SGRelighter(scene, voxels=100)
    assert e.value.param == "voxels"
    with pytest.raises(InputError, match="no lighting yet"):
        SGRelighter(scene).vertex_radiance(scene.camera.position)


def test_cli_renders_without_precompute(shared_data: Path, envmap_paths: dict[str, Path], lobes, tmp_path: Path) -> None:
    """``lightprobe relight SCENE --method sg`` from a map and from an SG JSON: an image, no cache
    directory written; a bad flag is exit 2 naming it."""
    import cv2

    (tmp_path / "spot.json").write_text(json.dumps(_scene_doc(shared_data)))
    sgj = tmp_path / "sg.json"
    sgj.write_text(json.dumps(lobes[1].to_json()))
    env = {"XDG_CACHE_HOME": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin"}
    for src in (str(envmap_paths["rooitou_park_1k.hdr"]), str(sgj)):
        out = tmp_path / "out.png"
        r = subprocess.run([sys.executable, "-m", "lightprobe.cli", "relight", str(tmp_path / "spot.json"), "--method", "sg",
                            "--lights", src, "--out", str(out), "--move", "spot=0.1,0,0"],
                           capture_output=True, text=True, env=env, timeout=300, cwd=Path(__file__).parents[1])
        assert r.returncode == 0, r.stderr
        img = cv2.imread(str(out))
        assert img.shape == (72, 96, 3)
        assert img.mean() > 5
    assert not (tmp_path / "cache").exists()
    r = subprocess.run([sys.executable, "-m", "lightprobe.cli", "relight", str(tmp_path / "spot.json"), "--method", "sg",
                        "--lights", str(sgj), "--out", str(tmp_path / "x.png"), "--voxels", "100"],
                       capture_output=True, text=True, env=env, timeout=300, cwd=Path(__file__).parents[1])
    assert r.returncode == 2
    assert "voxels" in r.stderr


def test_scene_file_frames_deform_and_moves_keep_the_shape(shared_data: Path, lobes, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """A scene file's deforming object (``"frames"``: OBJ shapes with the mesh's topology):
    ``set_frame`` takes each shape, a move poses the current shape (it does not reset it), and a
    frame with another topology or a missing file is refused naming it; the CLI's ``--frame``."""
    from lightprobe.hostlink.relight.scene import load_obj, load_scene
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter

    mesh = load_obj(shared_data / "meshes" / "spot.obj")
    for k, s in enumerate((0.9, 0.7)):
        v = mesh.vertices.copy()
        v[:, 1] *= s
        (tmp_path / f"spot_{k}.obj").write_text("\n".join([*(f"v {a} {b} {c}" for a, b, c in v),
                                                            *(f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces)]) + "\n")
    doc = _scene_doc(shared_data, "lambert")
    doc["objects"][0]["frames"] = ["spot_0.obj", "spot_1.obj"]
    doc["objects"][0]["translation"] = [0.0, 0.1, 0.0]
    (tmp_path / "d.json").write_text(json.dumps(doc))
    scene = load_scene(tmp_path / "d.json")
    rl = SGRelighter(scene)
    n = len(mesh.vertices)
    rl.set_frame(1)
    want = mesh.vertices * np.array([1.0, 0.7, 1.0]) + np.array([0.0, 0.1, 0.0])
    np.testing.assert_allclose(rl.vertices[:n], want, atol=1e-12)
    rl.move("spot", np.array([0.5, 0.0, 0.0]))
    np.testing.assert_allclose(rl.vertices[:n], want + np.array([0.5, 0.0, 0.0]), atol=1e-12)
    with pytest.raises(InputError, match="frame 2 out of range") as e:
        rl.set_frame(2)
    assert e.value.param == "frame"
    sgj = tmp_path / "sg.json"
    sgj.write_text(json.dumps(lobes[1].to_json()))
    for frame, code in (("1", 0), ("5", 2)):
        r = subprocess.run([sys.executable, "-m", "lightprobe.cli", "relight", str(tmp_path / "d.json"), "--method", "sg",
                            "--lights", str(sgj), "--out", str(tmp_path / "f.png"), "--frame", frame],
                           capture_output=True, text=True, timeout=300, cwd=Path(__file__).parents[1])
        assert r.returncode == code, r.stderr
    assert "frame 5 out of range" in r.stderr
    (tmp_path / "bad.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    doc["objects"][0]["frames"] = ["spot_0.obj", "bad.obj"]
    (tmp_path / "b.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"bad\.obj: frame of object 'spot' must have the mesh's"):
        load_scene(tmp_path / "b.json")
    doc["objects"][0]["frames"] = ["nope.obj"]
    (tmp_path / "c.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"frame file 'nope\.obj'"):
        load_scene(tmp_path / "c.json")


def test_rectangles_occlude_the_cones_exactly_and_the_grid_follows_the_objects(spot, lobes) -> None:  # type: ignore[no-untyped-def]
    """The ground (a rectangle) is not voxelised: each cone's share of rays that meet it is
    counted exactly, so a cone from the cow's belly straight down is (nearly) black where the
    voxel floor let 20-30% through; a planar mesh that is not a rectangle (the ground's triangles
    without one corner) stays voxels. The grid holds the cow only and is refitted when the cow
    moves out of it; the moved cow still shadows the ground as the rays say."""
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter

    clay, scene, _vidx, _light, _ref = spot
    if clay != "lambert":
        pytest.skip("geometry only")
    rl = SGRelighter(scene, visibility="voxels")
    rl.set_sg(lobes[3])
    rects, objs, _ = rl._rects()
    assert objs == frozenset({1})
    assert len(rects) == 1
    lo, hi = rl._voxel_bounds()
    cow = rl.vertices[:len(rl.objects[0].rest)]
    np.testing.assert_allclose([lo, hi], [cow.min(axis=0), cow.max(axis=0)])
    assert rl.vox * rl.R < 1.3 * float((hi - lo).max())          # not the floor's 3 m
    # straight down from under the belly: the floor blocks every ray of the cone
    belly = np.array([[0.0, -0.3, 0.4]])
    down = np.array([[0.0, -1.0, 0.0]])
    t = rl._trace(belly, down, down[:, None, :], np.full((1, 1), 0.3), owner=np.array([0]))
    assert t[0, 0] < 0.05, t
    # cut one corner triangle off the ground: no longer a rectangle, so voxels again
    ground = rl.objects[1]
    v = rl.vertices[ground.base:ground.base + len(ground.rest)]
    corner = int(np.argmin(v[:, 0] + v[:, 2]))
    keep = ~np.any(ground.faces == corner, axis=1)
    ground.faces = ground.faces[keep]
    ground.version += 1
    rl._geometry += 1
    assert rl._rects()[1] == frozenset()
    # move the cow 1.2 m along x: out of the grid, which follows it; the ground in its shadow
    rl = SGRelighter(scene, visibility="voxels")
    rays = SGRelighter(scene, visibility="rays")
    for r in (rl, rays):
        r.set_sg(lobes[1])
        r.move("spot", np.array([1.2, 0.0, 0.0]))
    origin = rl.origin.copy()
    g = rl.objects[1]
    gi = np.arange(g.base, g.base + len(g.rest))[::3]
    b = rl.vertex_radiance(scene.camera.position, gi)
    assert not np.allclose(rl.origin, origin)
    a = rays.vertex_radiance(scene.camera.position, gi)
    err = _rel_rms(b, a)
    print(f"moved cow, ground against rays: {err:.4f}")
    assert err <= 0.05


def test_a_wall_from_a_mesh_file_is_an_exact_rectangle(shared_data: Path, tmp_path: Path) -> None:
    """A wall rotated 30 deg about the vertical and tilted, written with six decimals (as mesh
    files are): still a plane and a rectangle (found along its triangles' edges, not the axes), so
    an exact occluder: a cone aimed at its middle from in front is black, one aimed away clear,
    one half over its top edge half through. Cut a corner triangle off and it is voxels."""
    from lightprobe.hostlink.relight.scene import load_scene
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter

    th = np.radians(30.0)
    e1 = np.array([np.cos(th), 0.0, np.sin(th)]) * 2.0
    n = np.cross(e1, [0.0, 1.0, 0.3])
    n /= np.linalg.norm(n)
    e2 = np.cross(n, e1 / 2.0) * 1.5
    corner = np.array([-1.2, -0.73, -1.2])
    for cut in (False, True):
        k = 8
        v = [corner + e1 * i / k + e2 * j / k for i in range(k + 1) for j in range(k + 1)]
        f = []
        for i in range(k):
            for j in range(k):
                a = i * (k + 1) + j
                if not (cut and i == 0 and j == 0):
                    f += [(a, a + k + 1, a + 1), (a + 1, a + k + 1, a + k + 2)]
        obj = tmp_path / f"wall{int(cut)}.obj"
        obj.write_text("".join(f"v {p[0]:f} {p[1]:f} {p[2]:f}\n" for p in v)
                       + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f))
        doc = _scene_doc(shared_data, "lambert")
        doc["objects"].append({"name": "wall", "mesh": str(obj), "material": "floor"})
        (tmp_path / "wall.json").write_text(json.dumps(doc))
        rl = SGRelighter(load_scene(tmp_path / "wall.json"), visibility="voxels")
        wall = [o.name for o in rl.objects].index("wall")
        if cut:
            assert wall not in rl._rects()[1]
            continue
        assert wall in rl._rects()[1]
        mid = corner + 0.5 * (e1 + e2)
        p = mid + 1.0 * n
        away = -(mid - p) / np.linalg.norm(mid - p)
        top = corner + e1 * 0.5 + e2                      # the middle of its upper edge
        up = (top - p) / np.linalg.norm(top - p)
        dirs = np.stack([-away, away, up])[None]
        t = rl._trace(p[None], away[None], dirs, np.full((1, 3), 0.1), owner=np.array([-1]))
        assert t[0, 0] < 0.02, t
        assert t[0, 1] == 1.0, t
        assert 0.35 < t[0, 2] < 0.65, t

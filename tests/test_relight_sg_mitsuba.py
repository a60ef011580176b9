"""SG relighting per pixel against an independent renderer: Mitsuba 3 (``scalar_rgb``, ``direct``
integrator, box pixel filter) renders the same scene, spot.obj (Lambert) on a ground plane under
rooitou_park (a 0.5 deg sun), from the same camera, meshes and vertex normals; the project's
equirect convention is Mitsuba's ``envmap``, so the map goes in as it is.

Both images integrate each pixel's area (ours: 4 x 4 pixel-centre samples, averaged; Mitsuba:
2048 samples, ~1.1% noise per pixel measured between seeds), so shadow edges compare like for
like; silhouette pixels (a neighbour on another object or the background) are left out. Metric:
relative RMSE of luminance, sqrt(sum (Y - Y_ref)^2 / sum Y_ref^2). Measured 2026-12-06: rays 1.60%,
voxels 2.58% (the issue's target 3% for both); the same shading at the vertices, interpolated over
the triangles (what per-pixel shading avoids): 5.26% / 5.76%.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow

W, H, SS = 160, 120, 4


@pytest.fixture(scope="module")
def setup(shared_data: Path, tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    import mitsuba as mi

    from lightprobe.core.imageio import read_hdr_image
    from lightprobe.hostlink.relight.scene import load_scene
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter

    mi.set_variant("scalar_rgb")
    d = tmp_path_factory.mktemp("mitsuba")
    doc = {"version": 1,
           "materials": {"clay": {"type": "lambert", "kd": [0.6, 0.5, 0.4]}, "floor": {"type": "lambert", "kd": [0.5, 0.5, 0.5]}},
           "objects": [{"name": "spot", "mesh": str(shared_data / "meshes" / "spot.obj"), "material": "clay"}],
           "ground": {"y": "auto", "size": 3.0, "resolution": 24, "material": "floor"},
           "camera": {"position": [2.0, 1.2, 2.5], "look_at": [0, -0.2, 0.4], "fov_deg": 40, "width": W, "height": H}}
    (d / "scene.json").write_text(json.dumps(doc))
    scene = load_scene(d / "scene.json")
    env = read_hdr_image(shared_data / "envmaps" / "rooitou_park_1k.hdr").astype(np.float32)
    geo = SGRelighter(scene, visibility="rays")
    shapes = {}
    for ob, o in zip(geo.objects, scene.objects, strict=True):
        sl = slice(ob.base, ob.base + len(ob.rest))
        v, n = geo.vertices[sl], geo.normals()[sl]
        lines = ([f"v {a:.9g} {b:.9g} {c:.9g}" for a, b, c in v] + [f"vn {a:.9g} {b:.9g} {c:.9g}" for a, b, c in n]
                 + [f"f {i + 1}//{i + 1} {j + 1}//{j + 1} {k + 1}//{k + 1}" for i, j, k in ob.faces])
        (d / f"{ob.name}.obj").write_text("\n".join(lines) + "\n")
        shapes[ob.name] = {"type": "obj", "filename": str(d / f"{ob.name}.obj"),
                           "bsdf": {"type": "diffuse",
                                    "reflectance": {"type": "rgb", "value": list(scene.materials[o.material].kd)}}}
    cam = scene.camera
    ms = mi.load_dict({
        "type": "scene", "integrator": {"type": "direct"},
        "sensor": {"type": "perspective", "fov": cam.fov_deg, "fov_axis": "y",
                   "to_world": mi.ScalarTransform4f().look_at(origin=[float(x) for x in cam.position],
                                                              target=[float(x) for x in cam.look_at],
                                                              up=[float(x) for x in cam.up]),
                   "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": 2048}},
        "env": {"type": "envmap", "bitmap": mi.Bitmap(env)}, **shapes})
    ref = np.array(mi.render(ms, seed=1), np.float64)
    return scene, env, ref


def _interior(rl, cam) -> np.ndarray:  # type: ignore[no-untyped-def]
    from lightprobe.hostlink.relight.raster import rasterize

    ras = rasterize(cam, rl.vertices, rl.faces, rays=False)
    ends = np.cumsum([len(o.faces) for o in rl.objects])
    obj = np.where(ras.tri >= 0, np.searchsorted(ends, ras.tri, side="right"), -1)
    m = obj >= 0
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            m &= np.roll(np.roll(obj, dy, 0), dx, 1) == obj
    m[[0, -1], :] = False
    m[:, [0, -1]] = False
    return m


def _rel_rmse(img: np.ndarray, ref: np.ndarray, m: np.ndarray) -> float:
    from lightprobe.core.sphere import luminance

    y, yr = luminance(img[m].astype(np.float64)), luminance(ref[m])
    return float(np.sqrt(((y - yr) ** 2).sum() / (yr ** 2).sum()))


def _area(img: np.ndarray) -> np.ndarray:
    return img.reshape(H, SS, W, SS, 3).mean(axis=(1, 3))


@pytest.mark.parametrize(("visibility", "bound"), [("rays", 0.03), ("voxels", 0.03)])
def test_per_pixel_image_against_mitsuba(setup, visibility: str, bound: float) -> None:  # type: ignore[no-untyped-def]
    from lightprobe.hostlink.relight.raster import rasterize, resolve
    from lightprobe.hostlink.relight.sg.relighter import SGRelighter

    scene, env, ref = setup
    rl = SGRelighter(scene, visibility=visibility)
    rl.set_equirect(env)
    big = dataclasses.replace(scene.camera, width=W * SS, height=H * SS)
    img, _ = rl.render(big)
    m = _interior(rl, scene.camera)
    assert m.sum() > 8000
    err = _rel_rmse(_area(img), ref, m)
    # the same shading evaluated at the vertices and interpolated over each triangle
    ras = rasterize(big, rl.vertices, rl.faces, rays=False)
    per_vertex = np.zeros((H * SS, W * SS, 3), np.float32)
    resolve(ras.tri, ras.bary, rl.faces, rl.vertex_radiance(scene.camera.position), per_vertex)
    err_v = _rel_rmse(_area(per_vertex), ref, m)
    print(f"{visibility}: per pixel {err:.4f}, per vertex interpolated {err_v:.4f}")
    assert err <= bound
    assert err < err_v

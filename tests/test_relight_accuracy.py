"""Acceptance: spot.obj on a ground plane under the six shared maps, cuts vs brute force.

Error metric (stated): relative RMS over vertices of the luminance of the outgoing radiance
towards the camera, sqrt(sum (Y - Y_ref)^2 / sum Y_ref^2). The reference is independent of the
cuts (:mod:`lightprobe.bench.relight_reference`): its own quadrature of each map (2^15 cells, each at
its light's centroid), one Embree ray per direction, its own BRDF loop (Phong on the cow, Lambert
floor). It therefore also sees what the cuts' 2^15 directions cannot resolve: a lamp smaller than a
direction cell casts its shadow edge from the cell's direction, up to half a cell (0.7 deg) off.
Subsampled: every 5th of the 3,555 vertices (711) enter the comparison; the SVC precompute
covers all of them (once per module, cached in a tmp dir).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow

MAPS = ["studio_small_03_1k.hdr", "rooitou_park_1k.hdr", "potsdamer_platz_1k.hdr", "lebombo_1k.hdr",
        "dikhololo_night_1k.hdr", "interior_blender.exr"]


@pytest.fixture(scope="module")
def spot_setup(shared_data: Path, envmap_paths: dict[str, Path], tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    from lightprobe.bench.relight_reference import relighter_reference
    from lightprobe.core.imageio import read_hdr_image
    from lightprobe.hostlink.relight.cuts.lighting import leaf_light_from_equirect
    from lightprobe.hostlink.relight.cuts.precompute import DEFAULT_TAU, precompute
    from lightprobe.hostlink.relight.cuts.render import Relighter
    from lightprobe.hostlink.relight.scene import load_scene

    d = tmp_path_factory.mktemp("spot")
    doc = {"version": 1,
           "materials": {"clay": {"type": "phong", "kd": [0.6, 0.5, 0.4], "ks": [0.2, 0.2, 0.2], "exponent": 20},
                         "floor": {"type": "lambert", "kd": [0.5, 0.5, 0.5]}},
           "objects": [{"name": "spot", "mesh": str(shared_data / "meshes" / "spot.obj"), "material": "clay"}],
           "ground": {"y": "auto", "size": 3.0, "resolution": 24, "material": "floor"},
           "camera": {"position": [2.0, 1.2, 2.5], "look_at": [0, -0.2, 0.4], "fov_deg": 40}}
    (d / "spot.json").write_text(json.dumps(doc))
    scene = load_scene(d / "spot.json")
    pre = precompute(scene, tau=DEFAULT_TAU, cache_dir=d / "cache", progress=False)
    rl = Relighter(scene, pre)
    maps = [read_hdr_image(envmap_paths[m]) for m in MAPS]
    leaf = np.stack([leaf_light_from_equirect(m) for m in maps])
    vidx = np.arange(0, len(pre.vertices), 5)
    ref = relighter_reference(rl, maps, scene.camera.position, vidx)
    return scene, pre, rl, leaf, vidx, ref


def _rel_rms(rl, leaf: np.ndarray, eye: np.ndarray, vidx: np.ndarray, ref: np.ndarray) -> float:  # type: ignore[no-untyped-def]
    from lightprobe.core.sphere import luminance

    rl.set_leaf_light(leaf)
    b, _ = rl.vertex_radiance(eye, vidx)
    y, yr = luminance(b), luminance(ref)
    return float(np.sqrt(((y - yr) ** 2).sum() / (yr ** 2).sum()))


@pytest.mark.parametrize("k", range(len(MAPS)), ids=MAPS)
def test_spot_per_vertex_error_against_an_independent_reference(spot_setup, k: int) -> None:  # type: ignore[no-untyped-def]
    """Within 2.5%: measured 0.35-1.6% on five maps, 2.4% on interior_blender, whose lamp (5
    pixels above half its peak) is smaller than a direction cell: 2.3 points of it are the
    2^15-direction resolution of the shadow edge on the floor (a brute force on the cuts' own
    cells is as far off), not the clustering."""
    scene, pre, rl, leaf, vidx, ref = spot_setup
    assert len(pre.vertices) == 3555
    rl.moment = True
    err = _rel_rms(rl, leaf[k], scene.camera.position, vidx, ref[k])
    print(f"{MAPS[k]}: relative RMS luminance error {err:.4f}")
    assert err <= 0.025
    assert err > 0          # the cuts do approximate: an exact match would mean a broken test


def test_cuts_are_valid_and_smaller_than_leaves(spot_setup) -> None:  # type: ignore[no-untyped-def]
    from lightprobe.hostlink.relight.cuts.coding import is_cut

    _, pre, *_ = spot_setup
    lens = np.diff(pre.svc_offsets)
    assert 30 < lens.mean() < 4000
    for i in range(0, len(lens), 50):
        assert is_cut(pre.svc_heights[pre.svc_offsets[i]:pre.svc_offsets[i + 1]])


def test_height_coded_vcf_at_most_45_percent_of_index_coded(shared_data: Path) -> None:
    from lightprobe.hostlink.relight.cuts.coding import decode_height, encode_height, encode_index
    from lightprobe.hostlink.relight.cuts.precompute import compute_vcf
    from lightprobe.hostlink.relight.scene import load_obj

    mesh = load_obj(shared_data / "meshes" / "spot.obj")
    f = compute_vcf(mesh.vertices, mesh.faces, (4, 8, 1.2, 10.0), lambda n: None)
    hb = ib = 0
    for k in range(len(f.offsets) - 1):
        h, v = f.heights[f.offsets[k]:f.offsets[k + 1]], f.values[f.offsets[k]:f.offsets[k + 1]]
        data = encode_height(h, v, "binary")
        hb += len(data)
        ib += len(encode_index(h, v, "binary")) - 4
        if k % 97 == 0:
            h2, v2 = decode_height(data, "binary")
            assert np.array_equal(h2, h)
            assert np.array_equal(v2, v)
    print(f"VCF height-coded {hb} B, index-coded {ib} B, ratio {hb / ib:.3f}")
    assert hb <= 0.45 * ib

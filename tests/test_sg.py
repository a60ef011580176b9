"""Spherical-Gaussian lighting on the probe (#17, first part): the fit's energy, residual, irradiance
and peaks, the closed forms, and ``GET /api/v1/sg`` / the stream subscription."""

from __future__ import annotations

import asyncio
import itertools
import json
import math
from pathlib import Path

import aiohttp
import numpy as np
import pytest
from service_harness import running_service, service_config

from device.core.imageio import read_hdr_image
from device.core.lightset import LightSet
from device.core.sg import SGLighting, lobe_integral, sharpness_from_resultant, triple_integral
from device.core.sgfit import fit_sg
from device.core.sphere import (
    coarse_equirect,
    equirect_directions,
    equirect_integral,
    equirect_row_solid_angle,
)
from device.sampling.metrics import ErrorReference

ENVMAPS = ["studio_small_03_1k.hdr", "rooitou_park_1k.hdr", "potsdamer_platz_1k.hdr", "lebombo_1k.hdr",
           "dikhololo_night_1k.hdr", "interior_blender.exr"]
Y = np.array([0.2126, 0.7152, 0.0722])


def _load(shared_data: Path, name: str) -> np.ndarray:
    m = read_hdr_image(shared_data / "envmaps" / name)
    return coarse_equirect(np.where(np.isfinite(m) & (m > 0), m, 0).astype(np.float32), 256)


def as_lights(sg: SGLighting, height: int = 128) -> LightSet:
    """The SG lighting as lights the samplers' metric reads: each peak lobe (sharp) as a light of its
    energy on its axis, the residual lobes' radiance summed at every pixel centre of a 128-row map."""
    peak = np.array([k == "peak" for k in sg.kinds], bool)
    d = equirect_directions(height).reshape(-1, 3)
    om = np.repeat(equirect_row_solid_angle(height), 2 * height)
    res = SGLighting(sg.axes[~peak], sg.sharpness[~peak], sg.amplitude[~peak], [k for k in sg.kinds if k != "peak"])
    rad = res.radiance(d)
    return LightSet(np.concatenate([d, sg.axes[peak]]), np.concatenate([rad * om[:, None], sg.energy()[peak]]),
                    np.concatenate([om, np.zeros(int(peak.sum()))]))


# ---- closed forms -----------------------------------------------------------------------------
def test_closed_forms_against_quadrature() -> None:
    d = equirect_directions(512).reshape(-1, 3)
    om = np.repeat(equirect_row_solid_angle(512), 1024)
    rng = np.random.default_rng(2)
    for lam in (0.5, 5.0, 60.0):
        p = rng.normal(size=3)
        p /= np.linalg.norm(p)
        num = float(np.exp(lam * (d @ p - 1)) @ om)
        assert abs(float(lobe_integral(np.array(lam))) / num - 1) < 1e-3
    # eq. 4: three lobes (paper's triple product), against the sum over the sphere
    ps = rng.normal(size=(3, 3))
    ps /= np.linalg.norm(ps, axis=1, keepdims=True)
    lams, mus = np.array([3.0, 8.0, 2.0]), np.array([1.5, 0.7, 2.0])
    num = float(np.prod([m * np.exp(la * (d @ p - 1)) for p, la, m in zip(ps, lams, mus, strict=True)], axis=0) @ om)
    got = float(triple_integral(ps[0], lams[0], mus[0:1], ps[1], lams[1], mus[1:2], ps[2], lams[2], mus[2:3])[0])
    assert abs(got / num - 1) < 1e-3
    # sharpness from the mean resultant length is the inverse of coth(l) - 1/l
    lam = np.array([0.1, 1.0, 10.0, 1e3, 1e5])
    r = 1 / np.tanh(lam) - 1 / lam
    assert np.allclose(sharpness_from_resultant(r), lam, rtol=1e-6)


# ---- the fit on the shared maps ----------------------------------------------------------------
@pytest.mark.parametrize("name", ENVMAPS)
def test_sg_fit_keeps_energy_shrinks_the_residual_and_reproduces_irradiance(shared_data: Path, name: str) -> None:
    m = _load(shared_data, name)
    sg = fit_sg(m)
    total = equirect_integral(m) @ Y
    assert abs(float(sg.energy().sum(axis=0) @ Y) / total - 1) <= 0.01
    res = [1.0] + [lv["residual_l2"] for lv in sg.levels]
    assert all(b <= a + 1e-12 for a, b in itertools.pairwise(res)), res  # never grows
    ref = ErrorReference(m)
    lights = as_lights(sg)
    diffuse, glossy = ref.error("diffuse", lights), ref.error("glossy", lights)
    print(f"{name}: {len(sg)} lobes ({sg.kinds.count('peak')} peak), diffuse {100 * diffuse:.2f}%, "
          f"glossy {100 * glossy:.2f}%, residual {res[-1]:.3f}")
    assert diffuse <= 0.02
    assert glossy <= 0.05


@pytest.mark.parametrize("scenario", ["switch", "flashlight"])
def test_peak_lobe_finds_the_lamp(shared_data: Path, scenario: str) -> None:
    from sim.scenarios import load_scene

    scene = load_scene(scenario, shared_data=shared_data)
    checked = 0
    for t in (2.0, 6.5, 11.0):
        m = coarse_equirect(np.asarray(scene.radiance_equirect(t), np.float32), 256)
        sg = fit_sg(m)
        peaks = [i for i, k in enumerate(sg.kinds) if k == "peak"]
        for lamp in scene.lights:
            e_true = float(lamp.energy(t) @ Y) * scene.scale
            if e_true <= 0:
                continue
            d = lamp.direction_at(t)
            near = [i for i in peaks if math.degrees(math.acos(np.clip(sg.axes[i] @ d, -1, 1))) < 5.0]
            assert near, f"{scenario} t={t}: no peak lobe near the lamp"
            e = sg.energy()[near] @ Y
            axis = e @ sg.axes[near]
            angle = math.degrees(math.acos(np.clip(axis @ d / np.linalg.norm(axis), -1, 1)))
            assert angle <= 0.5, angle
            assert abs(float(e.sum()) / e_true - 1) <= 0.02
            checked += 1
    assert checked >= 2


def test_degenerate_maps() -> None:
    black = fit_sg(np.zeros((128, 256, 3), np.float32))
    assert float(np.abs(black.energy()).sum()) == 0.0
    nan = np.full((128, 256, 3), np.nan, np.float32)
    assert float(np.abs(fit_sg(nan).energy()).sum()) == 0.0
    sun = np.full((128, 256, 3), 1e-3, np.float32)
    sun[20:22, 60:62] = 1e3  # 1e6 : 1 in float32
    sg = fit_sg(sun)
    assert sg.kinds.count("peak") >= 1
    assert abs(float(sg.energy().sum(axis=0) @ Y) / float(equirect_integral(sun) @ Y) - 1) <= 0.01
    from device.core.errors import InputError

    with pytest.raises(InputError, match="equirect"):
        fit_sg(np.zeros((100, 100, 3), np.float32))


def test_json_round_trip(shared_data: Path) -> None:
    sg = fit_sg(_load(shared_data, "studio_small_03_1k.hdr"), probe="p1", frame=3)
    back = SGLighting.from_json(json.loads(json.dumps(sg.to_json())))
    assert back.kinds == sg.kinds
    assert np.allclose(back.axes, sg.axes, atol=1e-6)
    assert np.allclose(back.amplitude, sg.amplitude)
    from device.core.errors import InputError

    with pytest.raises(InputError):
        SGLighting.from_json({"version": 2, "lobes": []})


# ---- the service ------------------------------------------------------------------------------
async def test_service_serves_sg_and_streams_it_on_request(tmp_path: Path) -> None:
    cfg = service_config(tmp_path, pipeline={"fps": 10.0, "light_count": 64})
    async with running_service(cfg) as s, aiohttp.ClientSession() as c:
        loop = asyncio.get_running_loop()
        t_end = loop.time() + 120
        while True:
            async with c.get(s.api + "/sg") as r:
                if r.status == 200:
                    body = await r.json()
                    break
            assert loop.time() < t_end
            await asyncio.sleep(0.2)
        assert body["kind"] == "sg"
        assert body["version"] == 1
        assert body["lobes"]
        assert np.asarray(body["pose"]["rotation"]).shape == (3, 3)      # as beside a light set
        assert len(body["pose"]["position"]) == 3
        lobe = body["lobes"][0]
        assert set(lobe) == {"axis", "sharpness", "amplitude", "kind"}
        assert lobe["kind"] in ("peak", "residual")
        async with c.get(s.api + "/sg?x=1") as r:
            assert r.status == 400
        from hostlink.client import ProbeClient

        async with ProbeClient(s.url, timeout=60) as cl:
            typed = await cl.sg()
            assert len(typed) > 0
            assert typed.probe == "probetest0001"
        async with c.ws_connect(s.api + "/stream") as ws:
            await ws.send_str(json.dumps({"subscribe": ["sg"]}))
            kinds = []
            for _ in range(8):
                m = json.loads((await ws.receive(timeout=60)).data)
                kinds.append(m.get("kind", "lights"))
            assert "sg" in kinds
            assert "lights" in kinds
            assert "sh" not in kinds

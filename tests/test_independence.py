"""The simulator is its own implementation: it shares no lens, vignetting, mounting or response
model with the probe, so a convention error in one is not cancelled by the same one in the other.

Two halves: the simulator's sources import none of the probe's models (checked on the source and on
a fresh interpreter's loaded modules), and its own models agree with the probe's and with OpenCV's
``cv2.fisheye`` where they describe the same thing.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from lightprobe.core.calibration import Calibration, FisheyeModel, Vignetting
from lightprobe.core.sphere import CAMERA_TO_PROBE, directions_from_angles, equirect_row_solid_angle
from lightprobe.drivers.base import PixelFormat
from lightprobe.sim.camera import SimCamera
from lightprobe.sim.lens import make_lens
from lightprobe.sim.optics import MOUNT, Kb4Lens, RadialFalloff, direction, equirect_row_omega
from lightprobe.sim.sensor import SensorModel

SIM = Path(__file__).resolve().parent.parent / "sim"
# The probe's models the simulator must not use (wherever they live), and the modules that hold
# the probe's geometry, calibration and pipeline.
FORBIDDEN_NAMES = {"FisheyeModel", "Vignetting", "Response", "CAMERA_TO_PROBE"}
FORBIDDEN_MODULES = ("lightprobe.core.sphere", "lightprobe.calibration", "lightprobe.device",
                     "lightprobe.hostlink")


def _imports(path: Path) -> list[tuple[str, set[str]]]:
    """(module, imported names) of every import statement in ``path``, relative ones resolved."""
    out: list[tuple[str, set[str]]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, set()) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                mod = ".".join(["lightprobe", "sim"][: 3 - node.level] + ([mod] if mod else []))
            out.append((mod, {a.name for a in node.names}))
    return out


def test_the_simulator_imports_none_of_the_probes_models() -> None:
    offences = []
    for path in sorted(SIM.glob("*.py")):
        for mod, names in _imports(path):
            if mod.startswith(FORBIDDEN_MODULES):
                offences.append(f"{path.name}: imports {mod}")
            if names & FORBIDDEN_NAMES:
                offences.append(f"{path.name}: imports {sorted(names & FORBIDDEN_NAMES)} from {mod}")
        # ... nor reaches them as attributes (``calibration.FisheyeModel(...)``)
        tree = ast.parse(path.read_text())
        attrs = {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)} & FORBIDDEN_NAMES
        if attrs:
            offences.append(f"{path.name}: uses {sorted(attrs)}")
    assert not offences, offences


def test_a_fresh_interpreter_running_the_simulator_loads_no_probe_geometry() -> None:
    code = ("import sys, lightprobe.sim.camera, lightprobe.sim.board, lightprobe.sim.v4l2_fake, "
            "lightprobe.sim.scenarios;"
            "print(sorted(m for m in sys.modules if m.startswith('lightprobe')))")
    loaded = json.loads(subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                                       text=True).stdout.replace("'", '"'))
    assert [m for m in loaded if m.startswith(FORBIDDEN_MODULES)] == []
    assert "lightprobe.sim.optics" in loaded  # the test would pass vacuously if nothing loaded


# ---- agreement where both describe the same thing ----------------------------------------------
def _camera_directions(theta_max_deg: float) -> np.ndarray:
    th = np.radians(np.linspace(0.0, theta_max_deg, 47))
    ph = np.linspace(0.0, 2 * np.pi, 37, endpoint=False)
    T, P = np.meshgrid(th, ph)
    return np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1).reshape(-1, 3)


def test_the_simulated_lens_projects_as_opencv_fisheye() -> None:
    sim = make_lens(640, 480).fisheye
    skewed = Kb4Lens((640, 480), sim.K + np.array([[0, 0.3, 0], [0, 0, 0], [0, 0, 0]]), sim.D)
    d = _camera_directions(85.0)
    for lens in (sim, skewed):
        K = lens.K
        ref, _ = cv2.fisheye.projectPoints(d[:, None, :].astype(np.float64), np.zeros(3), np.zeros(3),
                                           K, lens.D, alpha=K[0, 1] / K[0, 0])
        np.testing.assert_allclose(lens.project(d), ref[:, 0], atol=1e-6)


def test_the_simulated_lens_agrees_with_the_probes_model_past_90_degrees() -> None:
    sim = make_lens(1280, 960).fisheye
    probe = FisheyeModel(sim.image_size, sim.K, sim.D, fov_deg=sim.fov_deg)
    d = _camera_directions(sim.fov_deg / 2)
    np.testing.assert_allclose(sim.project(d), probe.project(d), atol=1e-9)
    px = probe.project(d)
    np.testing.assert_allclose(sim.unproject(px), probe.unproject(px), atol=2e-7)
    # Its own unprojection inverts its projection (the table is within 1e-8 rad)
    np.testing.assert_allclose(sim.unproject(sim.project(d)), d, atol=2e-7)


def test_the_mounting_and_sphere_conventions_match_the_probes() -> None:
    np.testing.assert_array_equal(MOUNT, CAMERA_TO_PROBE)
    rng = np.random.default_rng(3)
    theta, phi = rng.uniform(0, np.pi, 500), rng.uniform(0, 2 * np.pi, 500)
    np.testing.assert_allclose(direction(theta, phi), directions_from_angles(theta, phi), atol=1e-15)
    for h in (1, 7, 64, 512):
        np.testing.assert_allclose(equirect_row_omega(h), equirect_row_solid_angle(h), rtol=1e-12, atol=1e-18)


def test_the_simulated_falloff_is_the_calibration_files_vignetting() -> None:
    fall = RadialFalloff((319.5, 239.5), 236.0, (-0.25, -0.1, 0.02))
    probe = Vignetting.from_json(fall.calibration_section())
    u, v = np.meshgrid(np.linspace(0, 639, 33), np.linspace(0, 479, 25))
    np.testing.assert_allclose(fall.factor(u, v), probe.factor(u, v), rtol=1e-12)


@pytest.mark.parametrize("fmt", [PixelFormat.RGB8, PixelFormat.RAW10, PixelFormat.RAW12])
def test_the_truth_calibration_is_the_simulators_models_read_through_the_file_schema(fmt: PixelFormat) -> None:
    cam = SimCamera(scene="room")
    mode = next(m for m in cam.capabilities.modes if m.format is fmt)
    cal = cam.truth_calibration(mode)
    lens = cam.lens_for(mode)
    assert cal.source == "truth"
    assert cal.fisheye is not None
    assert cal.vignetting is not None
    np.testing.assert_array_equal(cal.fisheye.K, lens.fisheye.K)
    np.testing.assert_array_equal(cal.fisheye.D, lens.fisheye.D)
    assert cal.fisheye.fov_deg == lens.fov_deg
    # The response decodes the simulator's own digitisation: a code's x is within half a code of
    # the exposure that made it (8-bit curve) or exact (raw, linear)
    sensor = SensorModel()
    x = np.repeat(np.linspace(0.0, 0.999, 400)[:, None], 3, axis=1)
    codes = sensor.digitise(x * sensor.full_well, 1.0, fmt).astype(np.int64)
    assert cal.response is not None
    back = cal.response.inverse[codes, np.arange(3)]
    step = np.diff(cal.response.inverse, axis=0).max()
    assert np.abs(back - x).max() <= step
    # And the file round-trips: what the service saves is what the simulator handed out
    assert Calibration.from_json(json.loads(json.dumps(cal.to_json()))).id == cal.id


# ---- the references share no function with the code they check ---------------------------------
def _function_imports(path: Path, function: str | None = None) -> set[str]:
    """Modules imported by ``path`` (only inside ``function`` when given)."""
    tree = ast.parse(path.read_text())
    if function is not None:
        tree = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name == function)
    mods = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            mods |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            mods.add(node.module)
    return mods


def test_the_relighting_reference_uses_nothing_of_the_relighting() -> None:
    mods = _function_imports(SIM.parent / "bench" / "relight_reference.py")
    assert {m for m in mods if m.startswith("lightprobe")} == set()
    assert "embreex" in mods  # its own rays


def test_the_cube_map_reference_uses_nothing_of_the_filter() -> None:
    mods = _function_imports(SIM.parent / "bench" / "formats.py", "ggx_reference")
    assert not [m for m in mods if m.startswith(("lightprobe.device", "lightprobe.hostlink"))]


def _albedo_at_normal_incidence(kind: int, p: float) -> float:
    """Directional albedo of a lobe seen along the normal, by 1-D quadrature over the polar angle
    (the half vector of w and n = w_o is at theta / 2)."""
    from scipy.integrate import quad

    lobes = {
        0: lambda t: 1.0 / np.pi,
        1: lambda t: (p + 2) / (2 * np.pi) * np.cos(t) ** p,
        2: lambda t: (p + 8) / (8 * np.pi) * np.cos(t / 2) ** p,
        3: lambda t: np.exp(-np.tan(t / 2) ** 2 / p**2) / (4 * np.pi * p * p * np.sqrt(max(np.cos(t), 1e-2))),
    }
    return float(quad(lambda t: 2 * np.pi * np.sin(t) * np.cos(t) * lobes[kind](t), 0, np.pi / 2, limit=200)[0])


@pytest.mark.parametrize(("kind", "p"), [(0, 1.0), (1, 20.0), (1, 200.0), (2, 40.0), (3, 0.2), (3, 0.05)])
def test_the_relighting_references_brdfs_hold_the_white_furnace(kind: int, p: float) -> None:
    """A patch facing up, seen from straight above, under radiance 1 from every direction and
    nothing to shadow it reflects its lobe's albedo (1 for Lambert and normalised Phong)."""
    from lightprobe.bench.relight_reference import brute_force_radiance, equirect_quadrature

    pos = np.array([[0.0, 0.0, 0.0], [1e-3, 0.0, 0.0], [0.0, 0.0, 1e-3]])
    faces = np.array([[0, 2, 1]])
    normals = np.tile([0.0, 1.0, 0.0], (3, 1))
    kd, ks = (1.0, 0.0) if kind == 0 else (0.0, 1.0)
    mats = np.array([[kind, kd, kd, kd, ks, ks, ks, p]])
    light = equirect_quadrature([np.ones((512, 1024, 3), np.float32)], height=512)
    out = brute_force_radiance(pos, faces, normals, np.zeros(3, np.int64), mats, *light,
                               eye=np.array([0.0, 10.0, 0.0]), vidx=np.array([0]))
    expect = _albedo_at_normal_incidence(kind, p)
    assert kind > 1 or expect == pytest.approx(1.0, rel=1e-6)
    np.testing.assert_allclose(out[0, 0], expect, rtol=5e-3)

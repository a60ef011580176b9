"""``lightprobe bench room [--quick]``: frame times of the real-room relighting (lightprobe.hostlink.relight.room,
Loscos et al. 1999) at 640 x 480; its accuracy against Mitsuba 3 is asserted in
``tests/test_room.py`` (96 x 72 there: Mitsuba's path tracing is the cost).

The room: the shared Cornell box in metres, the camera of the tests through its open front,
640 x 480. Its captures (6 lamp positions) are rendered by ``Room.render`` itself with the true
per-surface albedo (this benchmark times the work, it does not score it). Timed, wall min /
median over the repetitions and process CPU min: recovery from the 6 captures (construction,
form factors, the three passes), a light's power changed, a light added at a new position (its
rays traced), ``spot.obj`` inserted, the inserted cow moved (a new pose every frame), and the
short block removed (what it hid refilled, its shadows and links redone).
"""

from __future__ import annotations

import json
import math
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from lightprobe.bench.relight_scenes import SHARED, timeit

ALBEDO = {"white": [0.7, 0.7, 0.7], "red": [0.63, 0.065, 0.05], "green": [0.14, 0.45, 0.09],
          "light": [0.78, 0.78, 0.78]}
LAMPS = [[0.15, 0.45, 0.20], [0.42, 0.45, 0.20], [0.28, 0.30, 0.10], [0.12, 0.20, 0.40], [0.45, 0.25, 0.45],
         [0.30, 0.40, 0.35]]
EYE, TARGET, FOV = np.array([0.278, 0.273, -0.80]), np.array([0.278, 0.273, 0.28]), 39.3


def _lamp(p: list[float], rgb: list[float]) -> dict[str, Any]:
    return {"position": p, "radius": 0.02, "rgb": rgb}


def build_room(d: Path, width: int, height: int) -> dict[str, str]:
    """room.obj (the Cornell box, mm -> m) and camera.json in ``d``; returns group -> material."""
    lines, mats, cur = [], {}, ""
    for line in (SHARED / "meshes" / "cornell_box.obj").read_text().splitlines():
        p = line.split("#", 1)[0].split()
        if not p:
            continue
        if p[0] == "v":
            lines.append(f"v {float(p[1]) / 1000} {float(p[2]) / 1000} {float(p[3]) / 1000}")
        elif p[0] == "o":
            cur = p[1]
            lines.append(f"o {cur}")
        elif p[0] == "usemtl":
            mats[cur] = p[1]
        elif p[0] == "f":
            lines.append(" ".join(p))
    (d / "room.obj").write_text("\n".join(lines) + "\n")
    f = (TARGET - EYE) / np.linalg.norm(TARGET - EYE)
    x = np.cross(f, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(f, x), f])
    fy = (height / 2) / math.tan(math.radians(FOV) / 2)
    (d / "camera.json").write_text(json.dumps({"K": [[fy, 0, width / 2 - 0.5], [0, fy, height / 2 - 0.5], [0, 0, 1]],
                                               "R": R.tolist(), "t": (-R @ EYE).tolist(),
                                               "width": width, "height": height}))
    return mats


def perturb_room(d: Path, out: Path, *, sigma: float = 0.004, shift: float = 0.01, seed: int = 0) -> None:
    """A copy of ``d``'s room.obj in ``out`` as a photogrammetric model would have it: every
    vertex moved by N(0, ``sigma``) per axis (the same for coincident vertices, so corners stay
    closed) and each block shifted sideways by ``shift`` (world units, m). camera.json copied."""
    rng = np.random.default_rng(seed)
    moved: dict[tuple[float, ...], np.ndarray] = {}
    lines, cur = [], ""
    for line in (d / "room.obj").read_text().splitlines():
        p = line.split()
        if p and p[0] == "o":
            cur = p[1]
            off = np.zeros(3)
            if "block" in cur:
                a = rng.uniform(0, 2 * math.pi)
                off = shift * np.array([math.cos(a), 0.0, math.sin(a)])
        if p and p[0] == "v":
            v = np.array([float(x) for x in p[1:4]])
            key = tuple(np.round(v, 5))
            if key not in moved:
                moved[key] = rng.normal(0.0, sigma, 3)
            jit = moved[key] * (np.array([1.0, 0.0, 1.0]) if v[1] == 0.0 else 1.0)   # the floor stays on the floor
            v = v + jit + off
            line = f"v {v[0]:.6f} {v[1]:.6f} {v[2]:.6f}"
        lines.append(line)
    out.mkdir(parents=True, exist_ok=True)
    (out / "room.obj").write_text("\n".join(lines) + "\n")
    (out / "camera.json").write_text((d / "camera.json").read_text())


def _captures(d: Path, mats: dict[str, str]) -> None:
    from lightprobe.core.imageio import write_exr
    from lightprobe.hostlink.relight.room.io import Light
    from lightprobe.hostlink.relight.room.room import Room

    (d / "captures").mkdir(exist_ok=True)
    room = Room(d)
    g = room.true_groups()
    refl = np.zeros((room.cam.height, room.cam.width, 3))
    for k, name in enumerate(room.group_names):
        if mats.get(name) in ALBEDO:
            refl[g == k] = ALBEDO[mats[name]]
    room.use_reflectance(refl, (g >= 0).astype(np.float64))
    for k, pos in enumerate(LAMPS):
        lamp = _lamp(pos, [2.0, 2.0, 2.0])
        write_exr(d / "captures" / f"c{k}.exr", room.render([Light(tuple(pos), 0.02, (2.0, 2.0, 2.0))]))  # type: ignore[arg-type]
        (d / "captures" / f"c{k}.json").write_text(json.dumps({"lights": [lamp]}))


def run(out_dir: Path, quick: bool) -> dict[str, Any]:
    from lightprobe.hostlink.relight.room.io import Light, VirtualObject
    from lightprobe.hostlink.relight.room.room import Room
    from lightprobe.hostlink.relight.scene import load_obj, rotation_matrix

    out_dir.mkdir(parents=True, exist_ok=True)
    reps = 3 if quick else 7
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        mats = build_room(d, 640, 480)
        _captures(d, mats)
        t0, c0 = time.perf_counter(), time.process_time()
        room = Room(d)
        room.recover()
        rows: dict[str, Any] = {"recover_6_captures": {"s": round(time.perf_counter() - t0, 2),
                                                       "cpu_s": round(time.process_time() - c0, 2)},
                                "room_pixels": int(room.cover.sum()), "patches": len(room.f)}
        base = [Light(tuple(LAMPS[0]), 0.02, (2.0, 2.0, 2.0)), Light(tuple(LAMPS[1]), 0.02, (2.0, 2.0, 2.0))]  # type: ignore[arg-type]
        room.render(base)
        state = {"k": 0}

        def power() -> None:
            state["k"] += 1
            room.render([base[0], Light(base[1].position, 0.02, (1.0 + state["k"] % 3,) * 3)])  # type: ignore[arg-type]

        def add() -> None:
            state["k"] += 1     # a position never lit before: its rays are traced
            room.render([*base, Light((0.1 + 0.01 * state["k"], 0.3, 0.15), 0.02, (1.0, 1.5, 2.0))])

        spot = load_obj(SHARED / "meshes" / "spot.obj")

        def cow(k: int) -> VirtualObject:
            v = (0.1 * spot.vertices) @ rotation_matrix(np.array([0.0, -20.0 + 5 * (k % 5), 0.0])).T
            return VirtualObject("spot", v + np.array([0.45 - 0.004 * (k % 5), 0.0737, 0.11]), spot.faces, (0.5, 0.6, 0.4))

        rows["light_power_change"] = timeit(power, reps)
        rows["light_added"] = timeit(add, reps)
        t0, c0 = time.perf_counter(), time.process_time()
        room.render(base, objects=[cow(0)])
        rows["object_inserted"] = {"ms": round((time.perf_counter() - t0) * 1e3, 1),
                                   "cpu_ms": round((time.process_time() - c0) * 1e3, 1)}

        def move() -> None:
            state["k"] += 1
            room.render(base, objects=[cow(state["k"])])

        rows["object_moved"] = timeit(move, reps)
        rows["object_pixels"] = int(room.object_mask.sum()) if room.object_mask is not None else 0
        rows["block_removed"] = timeit(lambda: room.render(base, remove=["short_block"]), reps)
        # the objects of a +-2% model moved to where the captures put them (Room.aligned), then recovered
        d2 = d / "perturbed"
        perturb_room(d, d2, sigma=0.004, shift=0.01)
        (d2 / "captures").symlink_to(d / "captures")
        t0, c0 = time.perf_counter(), time.process_time()
        aligned = Room.aligned(d2)
        rows["align_perturbed"] = {"s": round(time.perf_counter() - t0, 2), "cpu_s": round(time.process_time() - c0, 2),
                                   "offsets_mm": {k: [round(1e3 * x, 1) for x in v] for k, v in aligned.offsets.items()},
                                   "misfit_before_after": aligned.align_misfit}
    summary = {k: (v.get("median", v.get("ms", v.get("s"))) if isinstance(v, dict) else v) for k, v in rows.items()}
    result = {"summary": summary, "frames": rows}
    (out_dir / "room.json").write_text(json.dumps(result, indent=1))
    return result

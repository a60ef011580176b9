"""Scene files of the probe's lighting: glTF 2.0 and USD, with the probe's pose applied.

glTF (``environment.gltf``)
- The primary light as a ``KHR_lights_punctual`` directional light on a node whose local -Z
  points along the light's travel (glTF lights shine along local -Z): ``color`` the light's
  chromaticity, ``intensity`` its irradiance at normal incidence (the map's unit; lux once the
  probe is photometrically calibrated).
- The rest as ``EXT_lights_image_based``: ``irradianceCoefficients`` are *irradiance* SH,
  ``E_i = A_l c_i`` on the canonical basis of :mod:`.sh` (``E(n) = sum_i E_i Y_i(n)``; the
  extension leaves the normalisation open and Babylon.js reads them as irradiance),
  ``specularImages`` the GGX mips of the ambient map (:mod:`.cubemap`), faces +X..-Z, PNG in
  Babylon's RGBD encoding (``rgb = gamma(c D)``, ``alpha = D``, ``D = floor(max(255 / max(c), 1)) /
  255``; decode ``linear(rgb) / alpha``), ``rotation`` the pose. The scene points at it.
- Images are separate files beside the ``.gltf`` (``environment/...png``), as the service and
  ``lightprobe export`` write them.

USD (``environment.usda``)
- ``upAxis = "Y"``, metres; an ``Xform`` carrying the probe's pose, holding a ``DomeLight``
  (``texture:format = "latlong"``) whose texture is the probe's equirect map unchanged: the
  probe frame's equirect layout *is* the OpenEXR latitude-longitude layout UsdLux specifies
  (top-left pixel latitude +pi/2, longitude +pi; longitude 0 towards +Z, pi/2 towards +X; the
  probe's ``phi = 2 pi u`` and ``d = (sin t sin phi, cos t, -sin t cos phi)`` give the same
  directions), so no rotation is needed.
- A variant set ``lighting``: ``dome`` (default: all light in the dome) and ``dome_and_sun``
  (the ambient map in the dome plus a ``DistantLight`` for the primary light, for sharp shadows).
  ``DistantLight`` emits along its local -Z, like glTF's.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from lightprobe.core.sh import ZONAL_IRRADIANCE
from lightprobe.device.formats.sh_primary import Environment

from .cubemap import FACE_NAMES, FACES, Cubemap

__all__ = ["gltf_environment", "rgbd_encode", "usd_environment"]



def rgbd_encode(rgb: np.ndarray) -> np.ndarray:
    """Babylon.js's RGBD packing of linear HDR (..., 3) into 8-bit RGBA (..., 4) uint8."""
    c = np.maximum(np.nan_to_num(np.asarray(rgb, np.float64)), 0.0)
    mx = np.maximum(c.max(axis=-1), 1e-8)
    d = np.clip(np.floor(np.maximum(255.0 / mx, 1.0)) / 255.0, 0.0, 1.0)
    g = np.clip(c * d[..., None], 0.0, 1.0) ** (1.0 / 2.2)
    out = np.empty((*c.shape[:-1], 4), np.uint8)
    out[..., :3] = np.round(g * 255.0)
    out[..., 3] = np.round(d * 255.0)
    return out


def _png(rgba: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return bytes(buf)


def _quat_from_matrix(r: np.ndarray) -> list[float]:
    """Unit quaternion [x, y, z, w] of a rotation matrix (glTF order)."""
    m = np.asarray(r, np.float64)
    t = np.trace(m)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    n = math.sqrt(sum(v * v for v in q))
    return [v / n for v in q]


def _frame_towards(d: np.ndarray) -> np.ndarray:
    """A rotation whose local +Z is ``d`` (so local -Z, where lights shine, is ``-d``)."""
    z = np.asarray(d, np.float64) / np.linalg.norm(d)
    up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.99 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _pose(env: Environment) -> tuple[np.ndarray, np.ndarray]:
    pose = env.pose or {}
    r = np.asarray(pose.get("rotation", np.eye(3)), np.float64).reshape(3, 3)
    t = np.asarray(pose.get("position", [0.0, 0.0, 0.0]), np.float64).reshape(3)
    return r, t


def _light_colour(rgb: np.ndarray) -> tuple[list[float], float]:
    rgb = np.maximum(np.asarray(rgb, np.float64), 0.0)
    peak = float(rgb.max())
    return ([float(v / peak) for v in rgb] if peak > 0 else [1.0, 1.0, 1.0]), peak


def gltf_environment(env: Environment, cubemap: Cubemap, image_dir: str = "environment"
                     ) -> tuple[dict[str, Any], dict[str, bytes]]:
    """The glTF document (JSON object) and its images ``{relative uri: PNG bytes}``."""
    rot, pos = _pose(env)
    images: list[dict[str, Any]] = []
    files: dict[str, bytes] = {}
    spec: list[list[int]] = []
    for m, mip in enumerate(cubemap.mips):
        row = []
        for f, name in enumerate(FACE_NAMES):
            uri = f"{image_dir}/specular_{m}_{name}.png"
            files[uri] = _png(rgbd_encode(mip[f]))
            row.append(len(images))
            images.append({"uri": uri, "mimeType": "image/png", "name": f"specular mip {m} {FACES[f]}"})
        spec.append(row)
    irr = np.asarray(env.ambient, np.float64) * ZONAL_IRRADIANCE[:, None]
    ibl = {"name": "lightprobe ambient", "rotation": _quat_from_matrix(rot), "intensity": 1.0,
           "irradianceCoefficients": [[float(v) for v in c] for c in irr],
           "specularImageSize": int(cubemap.size), "specularImages": spec}
    nodes: list[dict[str, Any]] = []
    punctual: list[dict[str, Any]] = []
    if env.primary is not None:
        colour, intensity = _light_colour(env.primary.rgb)
        punctual.append({"type": "directional", "name": "lightprobe primary light",
                         "color": colour, "intensity": intensity})
        d_world = rot @ env.primary.direction
        nodes.append({"name": "primary_light", "rotation": _quat_from_matrix(_frame_towards(d_world)),
                      "translation": [float(v) for v in pos],
                      "extensions": {"KHR_lights_punctual": {"light": 0}}})
    scene: dict[str, Any] = {"name": "lightprobe environment", "nodes": list(range(len(nodes))),
                             "extensions": {"EXT_lights_image_based": {"light": 0}}}
    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "lightprobe",
                  "extras": {"probe": env.probe, "frame": int(env.frame), "timestamp": float(env.timestamp),
                             **({} if env.captured is None else {"captured": float(env.captured)}),
                             "unit": env.unit, "irradiance_sh": "E_i = A_l c_i, canonical basis (lightprobe docs)"}},
        "extensionsUsed": ["EXT_lights_image_based"] + (["KHR_lights_punctual"] if punctual else []),
        "extensions": {"EXT_lights_image_based": {"lights": [ibl]}},
        "images": images, "scene": 0, "scenes": [scene]}
    if punctual:
        doc["extensions"]["KHR_lights_punctual"] = {"lights": punctual}
        doc["nodes"] = nodes
    return doc, files


def gltf_bytes(doc: dict[str, Any]) -> bytes:
    return json.dumps(doc, indent=1).encode()


def _matrix4d(rot: np.ndarray, pos: np.ndarray) -> str:
    """USD's row-vector matrix of ``x_world = rot x + pos``."""
    m = np.eye(4)
    m[:3, :3] = rot.T
    m[3, :3] = pos
    rows = ", ".join("(" + ", ".join(f"{v:.9g}" for v in row) + ")" for row in m)
    return f"( {rows} )"


def usd_environment(env: Environment, dome_file: str = "environment_latlong.exr",
                    ambient_file: str = "environment_ambient_latlong.exr") -> str:
    """The ``.usda`` text; the two latlong EXR files (all light, ambient) are written beside it."""
    rot, pos = _pose(env)
    xf = _matrix4d(rot, pos)
    sun = ""
    if env.primary is not None:
        colour, intensity = _light_colour(env.primary.rgb)
        # a disc of the primary's solid angle: angle is the full apex angle in degrees
        half = math.acos(max(-1.0, 1.0 - float(env.primary.solid_angle) / (2 * math.pi)))
        sun_rot = _frame_towards(env.primary.direction)
        sun = f'''
                def DistantLight "PrimaryLight" (
                    doc = "the probe's primary light (towards {[round(float(v), 6) for v in env.primary.direction]} in the probe frame)"
                )
                {{
                    float inputs:angle = {math.degrees(2 * half):.6g}
                    color3f inputs:color = ({colour[0]:.9g}, {colour[1]:.9g}, {colour[2]:.9g})
                    float inputs:intensity = {intensity:.9g}
                    matrix4d xformOp:transform = {_matrix4d(sun_rot, np.zeros(3))}
                    uniform token[] xformOpOrder = ["xformOp:transform"]
                }}'''
    return f'''#usda 1.0
(
    defaultPrim = "Environment"
    doc = "lightprobe environment: probe {env.probe}, frame {int(env.frame)}, unit {env.unit}"
    metersPerUnit = 1
    upAxis = "Y"
)

def Xform "Environment" (
    variants = {{
        string lighting = "dome"
    }}
    prepend variantSets = "lighting"
)
{{
    matrix4d xformOp:transform = {xf}
    uniform token[] xformOpOrder = ["xformOp:transform"]

    variantSet "lighting" = {{
        "dome" {{
            def DomeLight "Dome"
            {{
                asset inputs:texture:file = @{dome_file}@
                token inputs:texture:format = "latlong"
                float inputs:intensity = 1
            }}
        }}
        "dome_and_sun" {{
            def DomeLight "Dome"
            {{
                asset inputs:texture:file = @{ambient_file}@
                token inputs:texture:format = "latlong"
                float inputs:intensity = 1
            }}{sun}
        }}
    }}
}}
'''

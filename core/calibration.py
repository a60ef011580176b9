"""The calibration object: everything the pipeline needs to turn pixels into radiance on the sphere.

One :class:`Calibration` holds the fisheye geometry (OpenCV fisheye / Kannala-Brandt KB4), the
camera response, the vignetting fall-off, the photometric scale and the mounting pose. The JSON
form is the contract in CONVENTIONS.md; sections that were not calibrated are ``None`` here and
absent in the file, never filled with made-up values. Until a technician calibrates a unit the
simulator's ground truth fills it (``lightprobe.sim.camera.SimCamera.truth_calibration``).

Frames: the fisheye model maps *camera-frame* directions (OpenCV: x right, y down, z along the
optical axis) to pixels; ``lightprobe.core.sphere.CAMERA_TO_PROBE`` takes camera directions to the probe
frame (+y up).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Any

import numpy as np

from lightprobe.core.errors import InputError

__all__ = [
    "Calibration",
    "FisheyeModel",
    "LensMask",
    "Photometric",
    "Pose",
    "Response",
    "Vignetting",
    "repair_inverse",
]


def _arr(x: Any, shape: tuple[int, ...] | None, name: str) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"calibration field {name!r} is not numeric", param=name) from e
    if shape is not None and a.shape != shape:
        raise InputError(f"calibration field {name!r} has shape {a.shape}, expected {shape}", param=name)
    if not np.all(np.isfinite(a)):
        raise InputError(f"calibration field {name!r} has non-finite values", param=name)
    return a


@dataclass(frozen=True)
class FisheyeModel:
    """OpenCV fisheye (KB4): theta_d = theta (1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8),
    (u, v) = (fx a theta_d / r + cx, fy b theta_d / r + cy) for a camera direction (a, b, c)."""

    image_size: tuple[int, int]  # (width, height)
    K: np.ndarray  # 3x3
    D: np.ndarray  # (4,)
    fov_deg: float = 185.0
    rms_px: float | None = None
    views_used: int | None = None
    views_rejected: tuple[str, ...] = ()

    def distort_theta(self, theta: np.ndarray) -> np.ndarray:
        t2 = theta * theta
        k1, k2, k3, k4 = self.D
        return theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def undistort_theta(self, theta_d: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Invert ``distort_theta`` by Newton's method (theta_d >= 0)."""
        theta = np.array(theta_d, dtype=np.float64, copy=True)
        k1, k2, k3, k4 = self.D
        for _ in range(iterations):
            t2 = theta * theta
            f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
            df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            theta = theta - f / np.where(np.abs(df) > 1e-12, df, 1e-12)
        return theta

    def project(self, dirs_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates (..., 2) of camera-frame directions (..., 3); works past 90 deg."""
        d = np.asarray(dirs_cam, dtype=np.float64)
        r = np.hypot(d[..., 0], d[..., 1])
        theta = np.arctan2(r, d[..., 2])
        theta_d = self.distort_theta(theta)
        scale = np.where(r > 1e-15, theta_d / np.where(r > 1e-15, r, 1.0), 1.0)
        K = self.K
        u = K[0, 0] * d[..., 0] * scale + K[0, 1] * d[..., 1] * scale + K[0, 2]
        v = K[1, 1] * d[..., 1] * scale + K[1, 2]
        return np.stack([u, v], axis=-1)

    def unproject(self, pixels: np.ndarray) -> np.ndarray:
        """Unit camera-frame directions (..., 3) of pixel coordinates (..., 2)."""
        p = np.asarray(pixels, dtype=np.float64)
        K = self.K
        my = (p[..., 1] - K[1, 2]) / K[1, 1]
        mx = (p[..., 0] - K[0, 2] - K[0, 1] * my) / K[0, 0]
        theta_d = np.hypot(mx, my)
        theta = self.undistort_theta(theta_d)
        s = np.where(theta_d > 1e-15, np.sin(theta) / np.where(theta_d > 1e-15, theta_d, 1.0), 1.0)
        return np.stack([mx * s, my * s, np.cos(theta)], axis=-1)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "model": "opencv-fisheye",
            "image_size": [int(self.image_size[0]), int(self.image_size[1])],
            "K": self.K.tolist(),
            "D": [float(x) for x in self.D],
            "fov_deg": float(self.fov_deg),
        }
        if self.rms_px is not None:
            out["rms_px"] = float(self.rms_px)
        if self.views_used is not None:
            out["views_used"] = int(self.views_used)
        out["views_rejected"] = list(self.views_rejected)
        return out

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> FisheyeModel:
        if d.get("model") != "opencv-fisheye":
            raise InputError(f"fisheye.model {d.get('model')!r} is not 'opencv-fisheye'", param="fisheye.model")
        size = d.get("image_size")
        if not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)):
            raise InputError("fisheye.image_size must be [width, height]", param="fisheye.image_size")
        return cls(
            image_size=(size[0], size[1]),
            K=_arr(d.get("K"), (3, 3), "fisheye.K"),
            D=_arr(d.get("D"), (4,), "fisheye.D"),
            fov_deg=float(d.get("fov_deg", 185.0)),
            rms_px=d.get("rms_px"),
            views_used=d.get("views_used"),
            views_rejected=tuple(d.get("views_rejected", ())),
        )


def repair_inverse(table: np.ndarray) -> np.ndarray:
    """The one repair rule for an inverse response table: a finite, non-negative,
    non-decreasing (levels, 3) float64 copy.

    Solvers can return NaN/Inf for codes no sample constrained (OpenCV 5's ``CalibrateRobertson``
    for the darkest codes; Debevec on sparse stacks): those entries are interpolated from their
    finite neighbours (the nearest finite value beyond the ends), negatives clipped to 0, then a
    running maximum makes the table monotone. A channel with no finite entry is a failed solve:
    :class:`InputError` (the stack was not static or not exposed). A 1-D table applies to all
    three channels. Normalisation is the caller's (:meth:`Response.normalised`).
    """
    t = np.array(table, dtype=np.float64, copy=True)
    if t.ndim == 1:
        t = np.repeat(t[:, None], 3, axis=1)
    if t.ndim != 2 or t.shape[1] != 3 or t.shape[0] < 2:
        raise InputError(f"response table must be (levels, 3), got {t.shape}", param="response")
    idx = np.arange(t.shape[0])
    for c in range(3):
        col = t[:, c]
        ok = np.isfinite(col)
        if not ok.any():
            raise InputError(f"response solve returned no finite values in channel {c} "
                             "(is the bracket static and exposed?)", param="response")
        col = np.interp(idx, idx[ok], col[ok]) if not ok.all() else col
        t[:, c] = np.maximum.accumulate(np.clip(col, 0.0, None))
    return t


@dataclass(frozen=True)
class Response:
    """Camera response: pixel value -> relative linear exposure (irradiance x time, per channel).

    ``inverse`` has shape (levels, 3): ``inverse[z, c]`` is the linear exposure that gives value
    ``z`` in channel ``c`` (Debevec-Malik's exp(g(z))), strictly increasing. For RAW output the
    response is linear after black-level subtraction: ``model == "linear"`` and ``inverse`` is
    ``(z - black) / (white - black)`` clipped at 0.

    ``log_sigma`` (levels, 3), optional: how far a single sample at code ``z`` scatters in log
    exposure, as measured on the calibration bracket (sensor and JPEG noise, quantisation and the
    response's own misfit together). When present the HDR merge weights and the deghosting use it
    instead of the generic sensor noise model (:mod:`lightprobe.device.hdr.fusion`); a truth or linear
    response has none. ``log_sigma_core`` (same shape, optional): the typical sample's spread (the
    68.3% half-width of the same disagreements) where ``log_sigma`` is their root mean square: the
    merge weights by the core and tests consistency and sums variances with ``log_sigma``
    (:func:`lightprobe.calibration.response.code_scatter`); without it the merge weights by ``log_sigma``.
    """

    model: str  # "table" (processed output) or "linear" (raw)
    bits: int
    inverse: np.ndarray  # (2**bits, 3) float64
    method: str = ""  # how it was measured: "truth", "debevec", "robertson"
    log_sigma: np.ndarray | None = None  # (2**bits, 3) float64, log-exposure scatter per code (rms)
    log_sigma_core: np.ndarray | None = None  # (2**bits, 3) float64, the same, its 68.3% half-width

    @classmethod
    def linear(cls, bits: int, black_level: float = 0.0, white_level: float | None = None) -> Response:
        white = float((1 << bits) - 1) if white_level is None else float(white_level)
        z = np.arange(1 << bits, dtype=np.float64)
        lin = np.clip((z - black_level) / (white - black_level), 0.0, None)
        return cls("linear", bits, np.repeat(lin[:, None], 3, axis=1), "linear")

    def normalised(self) -> Response:
        """The same response scaled so the largest channel's full-scale code maps to 1 (the
        exposure that saturates), as :meth:`linear` is: the convention every solver returns.
        ``log_sigma`` and ``log_sigma_core`` are scale-free and kept."""
        top = float(np.max(self.inverse[-1]))
        return Response(self.model, self.bits, self.inverse / (top if top > 0 else 1.0), self.method,
                        self.log_sigma, self.log_sigma_core)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"model": self.model, "bits": self.bits, "method": self.method,
                               "inverse": np.round(self.inverse.T, 12).tolist()}
        if self.log_sigma is not None:
            out["log_sigma"] = np.round(self.log_sigma.T, 6).tolist()
        if self.log_sigma_core is not None:
            out["log_sigma_core"] = np.round(self.log_sigma_core.T, 6).tolist()
        return out

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Response:
        bits = d.get("bits")
        if not isinstance(bits, int) or not 1 <= bits <= 16:
            raise InputError("response.bits must be an integer in [1, 16]", param="response.bits")
        inv = _arr(d.get("inverse"), (3, 1 << bits), "response.inverse").T.copy()
        if np.any(np.diff(inv, axis=0) < 0):
            raise InputError("response.inverse must be non-decreasing", param="response.inverse")
        sig: dict[str, np.ndarray | None] = {}
        for key in ("log_sigma", "log_sigma_core"):
            table = None
            if d.get(key) is not None:
                table = _arr(d.get(key), (3, 1 << bits), f"response.{key}").T.copy()
                if np.any(table < 0):
                    raise InputError(f"response.{key} must be non-negative", param=f"response.{key}")
            sig[key] = table
        return cls(str(d.get("model", "table")), bits, inv, str(d.get("method", "")), **sig)


@dataclass(frozen=True)
class Vignetting:
    """Radial fall-off V(r) = 1 + a1 r^2 + a2 r^4 + a3 r^6, r = |p - center| / radius_px.

    Measured pixel values are ``V(r) x`` the unvignetted ones; the pipeline divides by V.
    """

    center: tuple[float, float]
    radius_px: float
    coeffs: tuple[float, float, float]

    def factor(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        r2 = ((u - self.center[0]) ** 2 + (v - self.center[1]) ** 2) / self.radius_px**2
        a1, a2, a3 = self.coeffs
        return 1 + r2 * (a1 + r2 * (a2 + r2 * a3))

    def to_json(self) -> dict[str, Any]:
        return {"model": "radial-poly6", "center": list(map(float, self.center)),
                "radius_px": float(self.radius_px), "coeffs": list(map(float, self.coeffs))}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Vignetting:
        c = _arr(d.get("center"), (2,), "vignetting.center")
        k = _arr(d.get("coeffs"), (3,), "vignetting.coeffs")
        r = float(_arr(d.get("radius_px"), (), "vignetting.radius_px"))
        if r <= 0:
            raise InputError("vignetting.radius_px must be positive", param="vignetting.radius_px")
        return cls((c[0], c[1]), r, (k[0], k[1], k[2]))


@dataclass(frozen=True)
class Photometric:
    """Fused value x scale = radiance in ``unit`` ("nit" once measured with a meter)."""

    scale: float = 1.0
    unit: str = "relative"

    def to_json(self) -> dict[str, Any]:
        return {"scale": float(self.scale), "unit": self.unit}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Photometric:
        s = float(_arr(d.get("scale"), (), "photometric.scale"))
        if s <= 0:
            raise InputError("photometric.scale must be positive", param="photometric.scale")
        unit = d.get("unit", "relative")
        if unit not in ("relative", "nit"):
            raise InputError(f"photometric.unit {unit!r} is not 'relative' or 'nit'", param="photometric.unit")
        return cls(s, unit)


@dataclass(frozen=True)
class Pose:
    """Probe frame -> room frame: x_room = rotation @ x_probe + position (metres)."""

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def to_json(self) -> dict[str, Any]:
        return {"rotation": np.asarray(self.rotation).tolist(), "position": np.asarray(self.position).tolist()}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Pose:
        R = _arr(d.get("rotation"), (3, 3), "pose.rotation")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise InputError("pose.rotation is not a rotation matrix", param="pose.rotation")
        return cls(R, _arr(d.get("position"), (3,), "pose.position"))


@dataclass(frozen=True)
class LensMask:
    """Valid image circle: pixels farther than ``radius_px`` from ``center`` (the housing ring,
    frame reflections) are masked and filled before sampling (``lightprobe.calibration.mask``)."""

    center: tuple[float, float]
    radius_px: float

    def to_json(self) -> dict[str, Any]:
        return {"center": list(map(float, self.center)), "radius_px": float(self.radius_px)}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> LensMask:
        c = _arr(d.get("center"), (2,), "mask.center")
        r = float(_arr(d.get("radius_px"), (), "mask.radius_px"))
        if r <= 0:
            raise InputError("mask.radius_px must be positive", param="mask.radius_px")
        return cls((float(c[0]), float(c[1])), r)


_SECTIONS: dict[str, Any] = {
    "fisheye": FisheyeModel,
    "response": Response,
    "vignetting": Vignetting,
    "photometric": Photometric,
    "pose": Pose,
    "mask": LensMask,
}


@dataclass(frozen=True)
class Calibration:
    """All calibrated sections of one probe; absent sections are ``None``."""

    fisheye: FisheyeModel | None = None
    response: Response | None = None
    vignetting: Vignetting | None = None
    photometric: Photometric | None = None
    pose: Pose | None = None
    created: str = ""
    source: str = ""  # "truth" for the simulator's ground truth, else how it was made
    mask: LensMask | None = None  # appended last: positional construction stays compatible

    VERSION = 1

    def body(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name in _SECTIONS:
            sec = getattr(self, name)
            if sec is not None:
                out[name] = sec.to_json()
        return out

    @property
    def id(self) -> str:
        """Content hash of the calibrated sections (not of the creation time)."""
        blob = json.dumps(self.body(), sort_keys=True, separators=(",", ":")).encode()
        return hashlib.sha256(blob).hexdigest()[:16]

    def to_json(self) -> dict[str, Any]:
        created = self.created or datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
        out: dict[str, Any] = {"version": self.VERSION, "id": self.id, "created": created}
        if self.source:
            out["source"] = self.source
        out.update(self.body())
        return out

    @classmethod
    def from_json(cls, d: Any) -> Calibration:
        if not isinstance(d, dict):
            raise InputError("calibration must be a JSON object")
        if d.get("version") != cls.VERSION:
            raise InputError(f"calibration version {d.get('version')!r} is not {cls.VERSION}", param="version")
        kw: dict[str, Any] = {}
        for name, typ in _SECTIONS.items():
            if name in d:
                if not isinstance(d[name], dict):
                    raise InputError(f"calibration section {name!r} must be an object", param=name)
                kw[name] = typ.from_json(d[name])
        cal = cls(**kw, created=str(d.get("created", "")), source=str(d.get("source", "")))
        if "id" in d and d["id"] != cal.id:
            raise InputError(f"calibration id {d['id']!r} does not match its content ({cal.id})", param="id")
        return cal

    def with_(self, **changes: Any) -> Calibration:
        return replace(self, **changes)

"""The live output's geometry, derived once per calibration and output size: the equirect table's
upper-hemisphere rows, per output pixel constants (solid angle, mean inverse gain), the coarse
blocks of the change test, the fusion LUTs per exposure, and the published maps' buffers."""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

from lightprobe.core.calibration import Calibration
from lightprobe.core.sphere import equirect_row_solid_angle
from lightprobe.drivers.base import Frame

COARSE_BLOCKS = (8, 16)  # blocks of the upper hemisphere for the change test (rows, columns)


MAX_MAPS = 8  # published maps' buffers kept for reuse (1.5 MB each at 256 rows)


SEEN_WHOLE = 0.999  # a lens that sees this share of the upper hemisphere sees all of it


class OutputGeometry:
    """What the pipeline derives once per calibration and output size: the equirect table's
    upper-hemisphere rows, per output pixel constants (solid angle, mean inverse gain), the
    coarse blocks of the change test and the fusion LUTs per exposure."""

    def __init__(self, projector: Any, calibration: Calibration, height: int) -> None:
        from lightprobe.device.projection import sample_sharing

        self.projector = projector
        self.calibration = calibration
        self.height = height
        self.table = projector.table("equirect")
        self.inv_gain = np.ascontiguousarray(projector.inverse_gain, np.float64)
        self.rows = height // 2 * 2 * height  # the upper hemisphere's output pixels
        t = self.table
        ip = np.asarray(t.indptr[: self.rows + 1])
        row_of = np.repeat(np.arange(self.rows), np.diff(ip))
        d = np.asarray(t.data[: ip[-1]], np.float64)
        ig = self.inv_gain[np.asarray(t.indices[: ip[-1]])]
        geo_w = np.bincount(row_of, d * ig, self.rows)
        self.inv_gain_out = np.where(geo_w > 0, np.bincount(row_of, d * ig * ig, self.rows) / np.maximum(geo_w, 1e-300), 0.0)
        self.mean_gain = np.where(geo_w > 0, np.bincount(row_of, d, self.rows) / np.maximum(geo_w, 1e-300), 0.0)
        self.geo_n = (d * ig).astype(np.float32)  # each entry's geometric weight (data / gain)
        self.sharing = sample_sharing(ip, t.indices, d * ig, self.rows, row_of, geo_w)  # (for the lamp tracker)
        omega = equirect_row_solid_angle(height)[: height // 2]
        self.solid_angle_out = np.repeat(omega, 2 * height)
        # what the lens sees of the upper hemisphere: 1 for a probe's fisheye; a camera that is
        # not one (a recording of photographs) leaves the rest unseen, which is not black
        cov = np.asarray(projector.coverage_equirect, np.float32)
        self.seen = float((cov[: height // 2].reshape(-1) * self.solid_angle_out).sum() / self.solid_angle_out.sum())
        self.coverage = cov if self.seen < SEEN_WHOLE else None  # (H, 2H): each pixel's seen share
        resp = calibration.response
        assert resp is not None
        self.full_scale = float(np.max(resp.inverse[-1]))
        self._luts: dict[tuple[Any, ...], tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]] = {}
        self._maps: list[np.ndarray] = []  # the published maps' buffers (see equirect_map)
        self._lum: np.ndarray | None = None  # the change tests' per-pixel energy (see weighted_luminance)

    def equirect_map(self, fused: np.ndarray) -> np.ndarray:
        """A new (H, 2H, 3) map: ``fused`` in the upper half, zeros below.

        Each frame publishes one, and results outlive their frame (the latest result, a request
        encoding it, a subscriber's queue), so a map is never written again while anything refers
        to it. A fresh 1.5 MB array costs its page faults every frame (0.37 ms against 0.03 ms
        for a resident buffer, measured with the service's allocator settings), so the buffers
        are kept and one is reused once nothing but this list holds it: its reference count says
        so (a view of it, a memoryview, or any other holder counts). At most ``MAX_MAPS`` are kept."""
        buf = None
        for b in self._maps:
            if sys.getrefcount(b) <= 3:  # this list, the loop variable, the call's argument
                buf = b
                break
        if buf is None:
            buf = np.empty((self.height, 2 * self.height, 3), np.float32)
            if len(self._maps) < MAX_MAPS:
                self._maps.append(buf)
        half = self.height // 2
        buf[:half] = fused.reshape(half, 2 * self.height, 3)
        buf[half:] = 0.0
        return buf

    def lut(self, exposure: float, gain: float, fmt: Any, black: float = 0.0, white: float = 255.0
            ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """The fusion LUT of one exposure and its bounds (:func:`lightprobe.device.hdr.rolling.lut_bounds`),
        memoised per (exposure, gain, format, levels): a live probe repeats a few exposures, and
        the fusion module's own memo hashes the response per call."""
        key = (float(exposure), float(gain), fmt, float(black), float(white))
        hit = self._luts.get(key)
        if hit is None:
            if len(self._luts) >= 64:
                self._luts.clear()
            hit = self._luts[key] = self._build_lut(exposure, gain, fmt, black, white)
        return hit

    def _build_lut(self, exposure: float, gain: float, fmt: Any, black: float, white: float
                   ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        from lightprobe.device.hdr.fusion import FusionSettings, packed_lut, sanitized_inverse
        from lightprobe.device.hdr.rolling import lut_bounds

        st = FusionSettings()
        resp = self.calibration.response
        assert resp is not None
        if fmt.is_raw:
            levels = 1 << fmt.bit_depth
            z = np.arange(levels, dtype=np.float64)
            inv = np.repeat(np.clip((z - black) / max(white - black, 1.0), 0.0, None)[:, None], 3, axis=1)
            lut = packed_lut(inv, exposure, gain, black=black, sat=white, settings=st)
        else:
            inv = sanitized_inverse(resp.inverse)
            lut = packed_lut(inv, exposure, gain, black=0.0, sat=float(inv.shape[0] - 1), settings=st,
                             log_sigma=resp.log_sigma, log_sigma_core=resp.log_sigma_core, black_floor=True)
        dark, top = lut_bounds(lut)
        if not fmt.is_raw and resp.log_sigma is not None:
            # A measured response is least sure at its top (highlight roll-off, JPEG ringing): a
            # saturated sample is at least the threshold code's value less three of its scatter.
            # Taken at face value, a real bracket's longer frame said "at least 374" where its
            # shortest measured 310 a lamp's pixels, and the live merge took it for the lamp
            # brightening (piccante replayed: +4-5% energy for one frame in every cycle)
            k = np.argmax(lut[:-1, :, 3] > 0, axis=0)
            sig = np.asarray(resp.log_sigma, np.float64)[np.minimum(k, len(resp.log_sigma) - 1), np.arange(3)]
            top = top * np.exp(-3.0 * sig)
        return lut, (dark, top)

    def weighs_by_response(self, fmt: Any) -> bool:
        """Whether the rolling merge fuses its slots by the LUTs' weights (``RollingMerge``'s
        ``by_response``): for a response with measured scatter (a JPEG/YUV camera's, fitted to
        its own bracket), whose LUTs hold the black floor in their variances."""
        resp = self.calibration.response
        return not fmt.is_raw and resp is not None and resp.log_sigma is not None

    def weighted_luminance(self, fused: np.ndarray) -> np.ndarray:
        """Luminance x solid angle of each upper-hemisphere output pixel (rows,) float64: what
        the change tests compare, computed once per frame into one buffer that the next call
        overwrites (a fresh 512 kB array a frame paid its page faults under the service's
        allocator settings, as the maps did)."""
        from lightprobe.device.hdr.rolling import weighted_luminance

        if self._lum is None or self._lum.shape[0] != fused.shape[0]:
            self._lum = np.empty(fused.shape[0], np.float64)
        return weighted_luminance(fused, self.solid_angle_out, self._lum)

    def coarse_energy(self, lum_w: np.ndarray) -> np.ndarray:
        """:meth:`weighted_luminance` summed in COARSE_BLOCKS blocks of the upper hemisphere."""
        r, c = COARSE_BLOCKS
        h, w = self.height // 2, 2 * self.height
        if h % r or w % c:
            return np.asarray([float(lum_w.sum())])
        return lum_w.reshape(r, h // r, c, w // c).sum(axis=(1, 3)).ravel()

    def linear_frame(self, frame: Frame, lut: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A frame's linear radiance (h, w, 3) float32 through its LUT (x pixel gain) and the
        lens mask: the fisheye preview's input."""
        codes = np.asarray(frame.data)
        h, w = codes.shape[:2]
        vals = np.stack([lut[codes[..., c].astype(np.intp), c, 0] for c in range(3)], axis=-1)
        gain = (np.where(self.inv_gain > 0, 1.0 / np.maximum(self.inv_gain, 1e-300), 0.0)).reshape(h, w)
        return (vals * gain[..., None]).astype(np.float32), self.projector.lens_mask

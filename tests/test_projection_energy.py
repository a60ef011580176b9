"""Energy acceptance (issue 2), end to end with the simulator's ground truth.

For each of the six shared maps used as the scene: the simulator renders the noise-free sensor
radiance (area-correct lens render), the camera's vignetting and photometric scale are applied as
a real fused frame would carry them, and the projector built from the simulator's truth
calibration maps it to the sphere. The integral of radiance x solid angle of the polar map and of
the HEALPix map over the upper hemisphere must be within 1% of the true map's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lightprobe.core.healpix import equirect_to_healpix, npix, pix2vec_nest
from lightprobe.core.sphere import equirect_row_solid_angle
from lightprobe.device.projection import Projector
from lightprobe.sim.camera import SimCamera

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def projector(shared_data: Path) -> Projector:
    cam = SimCamera("room", shared_data=shared_data)
    return Projector(cam.truth_calibration())


def _upper_weights(nside: int) -> np.ndarray:
    """HEALPix weights of the upper hemisphere: 1 above the equator ring, 1/2 on it.

    Equatorial-ring pixels have their east/west corners on z = 0 and are symmetric about it
    (equal area above and below); pixels of the next ring touch z = 0 with their south corner.
    """
    z = pix2vec_nest(nside, np.arange(npix(nside)))[:, 1]
    return np.where(z > 1e-12, 1.0, np.where(np.abs(z) <= 1e-12, 0.5, 0.0))


def _errors(projector: Projector, path: Path, shared_data: Path) -> dict[str, float]:
    """Relative energy errors (max over channels) of one scene's maps over the upper hemisphere."""
    cam = SimCamera(path, shared_data=shared_data)
    cal = cam.truth_calibration()
    assert cal.fisheye is not None
    assert cal.fisheye.image_size == (640, 480)
    assert cal.vignetting is not None
    assert cal.photometric is not None
    radiance = cam.render_radiance_image(0.0)
    vig = cam.lens.vignetting_image()[..., None]
    fused = (radiance * vig / cal.photometric.scale).astype(np.float32)
    maps = projector.project(fused)
    assert np.isfinite(maps.equirect).all()

    truth = cam.truth_radiance(0.0).astype(np.float64)
    h = truth.shape[0]
    upper = np.tensordot(equirect_row_solid_angle(h)[: h // 2], truth[: h // 2].sum(axis=1),
                         axes=(0, 0))
    polar = (projector.solid_angle("polar")[:, None] * maps.polar.reshape(-1, 3)).sum(axis=0)
    w = _upper_weights(maps.nside) * projector.solid_angle("healpix")
    hp = (w[:, None] * maps.healpix).sum(axis=0)
    # Same region on both sides: the truth resampled to HEALPix (area-correct)
    hp_truth = (w[:, None] * equirect_to_healpix(truth.astype(np.float32), maps.nside)).sum(axis=0)
    return {"polar": float(np.max(np.abs(polar / upper - 1))),
            "healpix": float(np.max(np.abs(hp / upper - 1))),
            "healpix_vs_truth_healpix": float(np.max(np.abs(hp / hp_truth - 1)))}


def test_energy_of_polar_and_healpix_maps_matches_the_truth(
        projector: Projector, envmap_paths: dict[str, Path], shared_data: Path) -> None:
    errors = {name: _errors(projector, path, shared_data) for name, path in envmap_paths.items()}
    assert len(errors) == 6
    worst = {name: max(e.values()) for name, e in errors.items()}
    assert max(worst.values()) < 0.01, errors

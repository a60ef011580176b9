"""``lightprobe sample``: the light-set JSON and exit codes (run as a real subprocess)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lightprobe.core.imageio import read_hdr_image, write_exr
from lightprobe.core.lightset import LightSet
from lightprobe.core.sphere import equirect_integral
from lightprobe.device.sampling.metrics import lights_total

ROOT = Path(__file__).resolve().parent.parent


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "lightprobe.cli", "sample", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=120, check=False)


@pytest.mark.parametrize("method", ["pharr", "hemigon", "median-cut"])
def test_sample_writes_conventions_json(method: str, envmap_paths: dict[str, Path],
                                        tmp_path: Path) -> None:
    src = envmap_paths["lebombo_1k.hdr"]
    out = tmp_path / "lights.json"
    r = _run(str(src), "--method", method, "--count", "32", "--out", str(out))
    assert r.returncode == 0, r.stderr
    data = json.loads(out.read_text())
    assert data["version"] == 1
    assert data["method"] == method
    assert data["unit"] == "relative"
    assert 1 <= len(data["lights"]) <= 32
    assert set(data["lights"][0]) >= {"direction", "rgb", "solid_angle"}
    ls = LightSet.from_json(data)
    np.testing.assert_allclose(lights_total(ls), equirect_integral(read_hdr_image(src)),
                               rtol=1e-6)


def test_bad_inputs_exit_2_naming_the_culprit(tmp_path: Path) -> None:
    out = str(tmp_path / "x.json")
    garbage = tmp_path / "garbage.hdr"
    garbage.write_bytes(b"not an image at all")
    r = _run(str(garbage), "--count", "4", "--out", out)
    assert r.returncode == 2
    assert "garbage.hdr" in r.stderr
    missing = tmp_path / "missing.exr"
    r = _run(str(missing), "--count", "4", "--out", out)
    assert r.returncode == 2
    assert "missing.exr" in r.stderr
    square = tmp_path / "square.exr"
    write_exr(square, np.ones((16, 16, 3), np.float32))
    r = _run(str(square), "--count", "4", "--out", out)
    assert r.returncode == 2
    assert "square.exr" in r.stderr
    assert "equirect" in r.stderr
    ok = tmp_path / "ok.exr"
    write_exr(ok, np.ones((16, 32, 3), np.float32))
    for count in ("0", "-3"):
        r = _run(str(ok), "--count", count, "--out", out)
        assert r.returncode == 2
        assert "--count" in r.stderr
    r = _run(str(ok), "--count", "many", "--out", out)  # argparse: exit 2
    assert r.returncode == 2
    r = _run(str(ok), "--method", "nope", "--count", "4", "--out", out)
    assert r.returncode == 2
    assert "--method" in r.stderr
    assert not Path(out).exists()
    assert "Traceback" not in r.stderr

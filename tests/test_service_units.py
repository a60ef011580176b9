"""Small pure parts of the service: the tone mapper (lightprobe.device.tonemap, both previews), sd_notify,
token file, TOML writer."""

from __future__ import annotations

import socket
import stat
import tomllib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lightprobe.device.service.auth import check_bearer, load_or_create_token, read_token
from lightprobe.device.service.config import SCHEMA, ServiceConfig, dump_toml
from lightprobe.device.service.notify import Notifier
from lightprobe.device.tonemap import log_average_key, tone_map


def test_tonemap_degenerate_inputs() -> None:
    black = np.zeros((8, 16, 3), np.float32)
    assert tone_map(black).max() == 0
    nan = np.full((8, 16, 3), np.nan, np.float32)
    assert tone_map(nan).max() == 0  # NaN from a sensor is treated as 0
    hot = black.copy()
    hot[3, 5] = 1e6
    out = tone_map(hot)
    assert out.dtype == np.uint8
    assert out[3, 5].min() > 0
    assert out.sum() == out[3, 5].sum()
    neg = np.full((8, 16, 3), -1e-6, np.float32)  # lossy EXR negatives
    assert tone_map(neg).max() == 0
    ramp = np.linspace(0, 1e4, 8 * 16 * 3, dtype=np.float32).reshape(8, 16, 3)
    t = tone_map(ramp)[..., 1].ravel()
    assert np.all(np.diff(t.astype(int)) >= 0)  # monotone


def test_tonemap_preserves_hue_and_ignores_a_sun_in_the_key() -> None:
    """Luminance Reinhard scales all channels of a pixel alike (hue kept); the trimmed
    log-average key does not let 0.5% of very bright pixels darken the rest of the view."""
    rng = np.random.default_rng(3)
    sky = (rng.uniform(0.2, 2.0, (64, 128, 1)) * np.array([0.3, 0.5, 1.0])).astype(np.float32)
    out = tone_map(sky).astype(np.float64)
    lin = np.where(out / 255 <= 0.04045, out / 255 / 12.92, ((out / 255 + 0.055) / 1.055) ** 2.4)
    ok = (out > 20).all(axis=-1) & (out < 250).all(axis=-1)
    ratio = lin[ok] / lin[ok][:, 2:3]
    np.testing.assert_allclose(ratio, np.broadcast_to([0.3, 0.5, 1.0], ratio.shape), rtol=0.06)
    sunny = sky.copy()
    sunny.reshape(-1, 3)[rng.choice(sunny.shape[0] * sunny.shape[1], 40, replace=False)] = 1e6
    k0 = log_average_key(sky @ np.array([0.2126, 0.7152, 0.0722], np.float32))
    k1 = log_average_key(sunny @ np.array([0.2126, 0.7152, 0.0722], np.float32))
    assert abs(np.log(k1 / k0)) < 0.05, (k0, k1)
    assert np.abs(tone_map(sunny).astype(int) - tone_map(sky).astype(int))[sunny[..., 0] < 1e5].max() <= 8


def test_notifier_abstract_socket_and_watchdog_interval() -> None:
    name = f"lp-unit-{id(object())}"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind("\0" + name)
    s.settimeout(2)
    try:
        n = Notifier({"NOTIFY_SOCKET": "@" + name, "WATCHDOG_USEC": "3000000"})
        assert n.enabled
        assert n.watchdog_interval == pytest.approx(1.5)
        assert n.ready("serving")
        assert s.recv(100) == b"READY=1\nSTATUS=serving"
        assert n.watchdog()
        assert s.recv(100) == b"WATCHDOG=1"
    finally:
        s.close()
    off = Notifier({})
    assert not off.enabled
    assert off.watchdog_interval is None
    assert off.ready() is False
    other_pid = Notifier({"NOTIFY_SOCKET": "@x", "WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "1"})
    assert other_pid.watchdog_interval is None  # the watchdog is meant for another process
    gone = Notifier({"NOTIFY_SOCKET": "@no-such-socket-here"})
    assert gone.send("STATUS=x") is False  # logged, never raised


def test_token_file(tmp_path: Path) -> None:
    assert read_token(tmp_path / "s") is None
    tok = load_or_create_token(tmp_path / "s")
    assert stat.S_IMODE((tmp_path / "s" / "token").stat().st_mode) == 0o600
    assert load_or_create_token(tmp_path / "s") == tok == read_token(tmp_path / "s")
    assert check_bearer(f"Bearer {tok}", tok)
    assert not check_bearer(f"Bearer {tok}x", tok)
    assert not check_bearer(tok, tok)
    assert not check_bearer(None, tok)
    assert not check_bearer("Bearer \udcff", tok)
    assert [p.name for p in (tmp_path / "s").iterdir()] == ["token"]


printable = st.text(st.characters(min_codepoint=32, max_codepoint=0x2FFF, exclude_characters="\x7f."), max_size=30)


@settings(max_examples=200, deadline=None)
@given(name=printable, fps=st.floats(0.1, 60, allow_nan=False), count=st.integers(1, 4096),
       origins=st.lists(st.text(max_size=20), max_size=4))
def test_toml_writer_roundtrips(name: str, fps: float, count: int, origins: list[str]) -> None:
    cfg = ServiceConfig().with_patch({"probe": {"name": name}, "pipeline": {"fps": fps, "light_count": count},
                                      "service": {"cors_origins": origins}})
    back = tomllib.loads(dump_toml(cfg.data))
    assert ServiceConfig().with_patch(back).data == cfg.data


def test_schema_defaults_are_valid() -> None:
    defaults = {t: {k: spec[1] for k, spec in keys.items()} for t, keys in SCHEMA.items()}
    assert ServiceConfig().with_patch(defaults).data == ServiceConfig().data


def test_every_api_route_is_documented(tmp_path: Path) -> None:
    import json

    from service_harness import sim_factories

    from lightprobe.device.service.app import create_app

    app = create_app(ServiceConfig(), *sim_factories(tmp_path), token="t", probe_id="p")
    doc = json.loads((Path(__file__).resolve().parent.parent / "device/service/static/openapi.json").read_text())
    routes = {r.canonical.removeprefix("/api/v1") for r in app.router.resources() if r.canonical.startswith("/api/v1/")}
    assert routes == set(doc["paths"]), routes ^ set(doc["paths"])


def test_mdns_interfaces_follow_the_listen_address() -> None:
    from lightprobe.device.service.app import _mdns_interfaces

    assert _mdns_interfaces([], "127.0.0.1") == ["127.0.0.1"]  # make run: never advertise elsewhere
    assert _mdns_interfaces([], "0.0.0.0") == []  # all interfaces
    assert _mdns_interfaces([], "probe.local") == []
    assert _mdns_interfaces(["192.168.1.5"], "0.0.0.0") == ["192.168.1.5"]  # configured wins


def test_numba_cache_goes_to_the_state_dir_only_when_the_package_is_read_only(tmp_path: Path) -> None:
    from lightprobe.cli.serve import numba_cache_dir

    state = tmp_path / "state"
    read_only = tmp_path / "missing-package"  # os.access(..., W_OK) is False (root ignores modes)
    assert numba_cache_dir({}, state, read_only) == str(state / "cache" / "numba")
    assert numba_cache_dir({"NUMBA_CACHE_DIR": "/elsewhere"}, state, read_only) is None  # the unit's wins
    writable = tmp_path / "pkg"
    (writable / "__pycache__").mkdir(parents=True)
    assert numba_cache_dir({}, state, writable) is None  # numba's in-tree cache works


def test_one_blas_thread_unless_set() -> None:
    from lightprobe.cli.serve import single_blas_thread

    env: dict[str, str] = {}
    single_blas_thread(env)
    assert env == {"OPENBLAS_NUM_THREADS": "1"}
    env = {"OPENBLAS_NUM_THREADS": "2"}
    single_blas_thread(env)
    assert env == {"OPENBLAS_NUM_THREADS": "2"}  # an explicit setting wins


def test_first_frame_kernels_load_with_the_tables_not_after_the_burst(tmp_path: Path) -> None:
    """``Pipeline._build_tables`` (run beside the first burst) loads every numba kernel the first
    frame's fusion and (full build + incremental) sampling use; the first frame then loads none."""
    import asyncio

    import numba.core.caching as caching

    from lightprobe.device.pipeline import Pipeline, PipelineConfig
    from lightprobe.sim.camera import SimCamera

    loaded: list[str] = []
    orig = caching.Cache.load_overload

    def spy(self, *a, **k):  # type: ignore[no-untyped-def]
        # the probe's kernels only: the simulated camera's own (its lens, built at its first
        # capture when no earlier test in the process loaded it) are not the probe's start
        if not str(getattr(self._py_func, "__module__", "")).startswith("lightprobe.sim"):
            loaded.append(self._name)
        return orig(self, *a, **k)

    async def run() -> tuple[list[str], list[str]]:
        cam = SimCamera("flashlight", cache_dir=tmp_path)
        pipe = Pipeline(cam, cam.truth_calibration(), PipelineConfig(cache_dir=str(tmp_path)))
        await pipe.start()
        try:
            await pipe._ensure_tables()
            warm = list(loaded)
            loaded.clear()
            await pipe.step()
            return warm, list(loaded)
        finally:
            await pipe.stop()

    caching.Cache.load_overload = spy  # type: ignore[method-assign]
    try:
        _, first = asyncio.run(run())
    finally:
        caching.Cache.load_overload = orig  # type: ignore[method-assign]
    assert first == [], first


def test_service_packages_never_import_healpy() -> None:
    """healpy (GPL) is a test-only reference: no shipped module may import it."""
    import re

    root = Path(__file__).resolve().parents[1]
    offenders = [str(f.relative_to(root)) for pkg in ("core", "cli", "device", "drivers", "sim", "calibration", "hostlink", "bench")
                 for f in (root / pkg).rglob("*.py")
                 if re.search(r"^\s*(import|from)\s+healpy\b", f.read_text(), re.M)]
    assert offenders == []


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_numba_cache_dir_really_caches_the_service_kernels(tmp_path: Path) -> None:
    """With NUMBA_CACHE_DIR (what the unit file and a read-only install get), the projection
    kernel is compiled once into that directory and loaded from it by the next process."""
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parent.parent
    code = ("import numpy as np\n"
            "from lightprobe.device.projection.sparse import spmv_rgb\n"
            "out = np.zeros((1, 3), np.float32)\n"
            "spmv_rgb(np.array([0, 1], np.int32), np.array([0], np.int32), np.array([2.0], np.float32),"
            " np.ones((1, 3), np.float32), out)\n"
            "assert out[0, 0] == 2.0\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "NUMBA_DEBUG_CACHE": "1",
           "PYTHONPATH": str(root)}
    runs = [subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True,
                           timeout=200) for _ in range(2)]
    for r in runs:
        assert r.returncode == 0, r.stderr[-2000:]
    files = [p.name for p in (tmp_path / "numba").rglob("*") if p.suffix in (".nbi", ".nbc")]
    assert any(f.startswith("sparse.spmv_rgb") for f in files), files
    assert "data saved" in runs[0].stdout, runs[0].stdout[-2000:]
    assert "data loaded" in runs[1].stdout, runs[1].stdout[-2000:]
    assert "data saved" not in runs[1].stdout, runs[1].stdout[-2000:]

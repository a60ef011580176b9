"""Record and replay (issue 45): a unit's frames saved as they came, replayed as a camera.

- the file format: round trip, truncation (replayed up to the last whole frame, and said), a
  changed byte (refused, the file and frame named), an unknown version (refused, named);
- ``lightprobe record --camera sim`` then ``lightprobe run-pipeline --camera replay:FILE``: the
  same light sets, byte for byte (``--jsonl``), and a second replay the same again;
- a recording made through the API while the service runs, then a service on
  ``--camera replay:FILE``: the light sets equal the recorded run's, frame for frame;
- a replay camera that fails (corrupted file) leaves the service up, saying why.
"""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lightprobe.drivers.base import Controls, Frame, FrameMetadata, PixelFormat
from lightprobe.drivers.recording import MAGIC, RecordingReader, RecordingWriter
from tests.service_harness import running_service, service_config

ROOT = Path(__file__).resolve().parents[1]


def _frames(n: int, shape: tuple[int, int] = (24, 32)) -> list[Frame]:
    rng = np.random.default_rng(5)
    out = []
    for i in range(n):
        data = rng.integers(0, 4096, (*shape, 3)).astype(np.uint16)
        meta = FrameMetadata(exposure_s=1e-3 * (i + 1), gain=1.5, timestamp_s=100.0 + i / 30, sequence=10 + 2 * i)
        out.append(Frame(data, meta, PixelFormat.RAW12, black_level=256.0, white_level=4095.0,
                         extra={"sim_time_s": i / 30, "skip": object()}))
    return out


def _header() -> dict[str, Any]:
    from lightprobe.drivers.base import Capabilities, Mode
    from lightprobe.drivers.recording import capabilities_to_json

    caps = Capabilities((1e-5, 0.5), (1.0, 8.0), (Mode(32, 24, PixelFormat.RAW12),), True, 2, model="m")
    return {"kind": "stream", "source": "test", "camera": capabilities_to_json(caps),
            "mode": {"width": 32, "height": 24, "format": "raw12", "max_fps": 30.0}, "calibration": None}


def _write(path: Path, frames: list[Frame], calibration: Any = None) -> None:
    w = RecordingWriter(path, {**_header(), "calibration": calibration})
    for k, f in enumerate(frames):
        assert w.append(f, delivered_s=50.0 + k / 30, requested=Controls(exposure_s=1e-3))
    w.close()
    assert w.error is None
    assert w.lost == 0


def test_round_trip_keeps_pixels_and_metadata(tmp_path: Path) -> None:
    frames = _frames(5)
    path = tmp_path / "a.lprec"
    _write(path, frames)
    with RecordingReader(path) as r:
        assert not r.truncated
        assert r.capabilities.model == "m"
        assert r.mode.format is PixelFormat.RAW12
        got = list(r)
    assert len(got) == 5
    for a, b in zip(frames, got, strict=True):
        assert np.array_equal(a.data, b.data)
        assert b.data.dtype == np.uint16
        assert b.data.flags.writeable
        assert a.meta == b.meta
        assert (b.format, b.black_level, b.white_level) == (a.format, a.black_level, a.white_level)
        assert b.extra["sim_time_s"] == a.extra["sim_time_s"]
        assert "skip" not in b.extra


def test_truncated_recording_replays_its_whole_frames_and_says_so(tmp_path: Path, caplog: Any) -> None:
    path = tmp_path / "a.lprec"
    _write(path, _frames(4))
    size = path.stat().st_size
    with RecordingReader(path) as r:
        cut = r.frames[3].offset + 100  # inside the last frame's metadata
    with path.open("r+b") as f:
        f.truncate(cut)
    with RecordingReader(path) as r:
        assert r.truncated
        assert len(r.frames) == 3
        assert r.leftover_bytes > 0
        r.verify()
        assert [f.meta.sequence for f in r] == [10, 12, 14]
    assert "truncated inside frame 3" in caplog.text
    assert str(path) in caplog.text
    assert size > cut


def test_changed_byte_and_unknown_version_are_refused_naming_the_file(tmp_path: Path) -> None:
    from lightprobe.core.errors import InputError

    path = tmp_path / "a.lprec"
    _write(path, _frames(3))
    with RecordingReader(path) as r:
        where = r.frames[1].offset + r.frames[1].meta_len + 7  # a pixel byte of frame 1
    raw = bytearray(path.read_bytes())
    raw[where] ^= 0x01
    bad = tmp_path / "bad.lprec"
    bad.write_bytes(bytes(raw))
    with RecordingReader(bad) as r, pytest.raises(InputError, match=r"bad\.lprec: frame 1 fails its checksum"):
        r.verify()
    v2 = bytearray(path.read_bytes())
    v2[len(MAGIC)] = 2
    newer = tmp_path / "newer.lprec"
    newer.write_bytes(bytes(v2))
    with pytest.raises(InputError, match=r"newer\.lprec: recording format version 2 is not supported"):
        RecordingReader(newer)
    junk = tmp_path / "junk.lprec"
    junk.write_bytes(b"P6\n32 24\n255\n" + bytes(100))
    with pytest.raises(InputError, match=r"junk\.lprec: not a lightprobe recording"):
        RecordingReader(junk)


def _cli(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-m", "lightprobe.cli", *args], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=600)
    if check:
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    return r


def test_cli_record_then_replay_gives_the_same_light_sets_bit_for_bit(tmp_path: Path) -> None:
    rec, out = tmp_path / "sim.lprec", tmp_path / "latest.exr"
    r = _cli("record", "--camera", "sim", "--scene", "flashlight", "--seconds", "1.5", "--out", str(rec),
             "--jsonl", str(tmp_path / "recorded.jsonl"))
    assert "energy" in r.stdout
    assert rec.is_file()
    assert not Path(str(rec) + ".part").exists()
    recorded = (tmp_path / "recorded.jsonl").read_text().splitlines()
    assert len(recorded) >= 30  # 1.5 s at 30 fps, less what the start's first frames dropped
    for run in ("a", "b"):
        r = _cli("run-pipeline", "--camera", f"replay:{rec}", "--frames", "0", "--out", str(out),
                 "--jsonl", str(tmp_path / f"{run}.jsonl"))
        lines = [ln for ln in r.stdout.splitlines() if ln.startswith("frame ")]
        assert len(lines) == len(recorded)
        assert all("energy" in ln for ln in lines)
        assert f"the recording ended after {len(recorded)} frames" in r.stdout
        assert (tmp_path / f"{run}.jsonl").read_text().splitlines() == recorded  # bit for bit
    # the moving flashlight moved: a replay that froze would repeat one set
    assert len({json.dumps(json.loads(x)["lights"][:3]) for x in recorded}) > len(recorded) // 2


def test_cli_record_and_replay_errors_exit_2_naming_the_problem(tmp_path: Path) -> None:
    r = _cli("run-pipeline", "--camera", f"replay:{tmp_path / 'none.lprec'}", check=False)
    assert r.returncode == 2
    assert "none.lprec" in r.stderr
    bad = tmp_path / "bad.lprec"
    bad.write_bytes(b"not a recording at all")
    r = _cli("run-pipeline", "--camera", f"replay:{bad}", check=False)
    assert r.returncode == 2
    assert "bad.lprec: not a lightprobe recording" in r.stderr
    r = _cli("record", "--camera", "sim", "--seconds", "0", "--out", str(tmp_path / "x.lprec"), check=False)
    assert r.returncode == 2
    assert "--seconds" in r.stderr
    r = _cli("record", "--stack", str(tmp_path / "missing.jpg"), "--times", "0.01", "--calibration",
             str(tmp_path / "cal.json"), "--out", str(tmp_path / "y.lprec"), check=False)
    assert r.returncode == 2


def _lights_json(lights: Any) -> str:
    d = lights.to_json()
    d.pop("timestamp", None)
    return json.dumps(d, sort_keys=True)


async def _record_through_the_api(tmp_path: Path, seconds: float) -> tuple[Path, dict[int, str]]:
    import aiohttp

    sets: dict[int, str] = {}
    cfg = service_config(tmp_path / "rec", pipeline={"fps": 30.0, "light_count": 64})
    (tmp_path / "rec").mkdir()
    async with running_service(cfg, scene="flashlight") as s, aiohttp.ClientSession() as c:
        t0 = time.monotonic()
        while s.state.runner.frames < 20 and time.monotonic() - t0 < 120:  # noqa: ASYNC110 - the service is running
            await asyncio.sleep(0.1)
        fresh: list[Any] = []
        s.state.runner.listeners.append(lambda lights, result: fresh.append(lights))
        async with c.post(s.api + "/recordings", json={"seconds": seconds}, headers=s.auth) as r:
            assert r.status == 202, await r.text()
            rid = (await r.json())["id"]
        async with c.post(s.api + "/recordings", json={"seconds": seconds}, headers=s.auth) as r:
            assert r.status == 409  # one at a time
        async with c.get(s.api + "/recordings") as r:
            assert r.status == 401  # an image of the room: the token
        state = ""
        while state != "done" and time.monotonic() - t0 < 180:
            await asyncio.sleep(0.2)
            async with c.get(s.api + "/recordings", headers=s.auth) as r:
                state = next(i for i in (await r.json())["recordings"] if i["id"] == rid)["state"]
        assert state == "done"
        async with c.get(s.api + f"/recordings/{rid}", headers=s.auth) as r:
            assert r.status == 200
            path = tmp_path / f"{rid}.lprec"
            path.write_bytes(await r.read())
        async with c.get(s.api + "/recordings/../../token", headers=s.auth) as r:
            assert r.status in (400, 404)
        # the rebuilt pipeline's sets, from its first frame (frame numbers start again at 1)
        start = max(i for i, li in enumerate(fresh) if li.frame == 1)
        for li in fresh[start:]:
            sets.setdefault(li.frame, _lights_json(li))
        async with c.delete(s.api + f"/recordings/{rid}", headers=s.auth) as r:
            assert r.status == 204
    return path, sets


async def _replay_service(tmp_path: Path, path: Path, frames: int) -> dict[int, str]:
    from lightprobe.device.bootstrap import camera_factory, pipeline_factory

    sets: dict[int, str] = {}
    state = tmp_path / "replay"
    state.mkdir()
    cfg = service_config(state, pipeline={"fps": 30.0, "light_count": 64})
    async with running_service(cfg, camera_factory(f"replay:{path}"), pipeline_factory(state, "probetest0001")) as s:
        s.state.runner.listeners.append(lambda lights, result: sets.setdefault(lights.frame, _lights_json(lights)))
        t0 = time.monotonic()
        while len(sets) < frames and time.monotonic() - t0 < 180:  # noqa: ASYNC110 - polling the listener's sets
            await asyncio.sleep(0.2)
        while s.state.runner.camera_state != "reconnecting" and time.monotonic() - t0 < 200:  # noqa: ASYNC110 - the runner's state
            await asyncio.sleep(0.2)  # the end of the recording: stale lights, and why
        assert "recording ended" in (s.state.runner.last_error or "")
    return sets


@pytest.mark.timeout(600)
def test_api_recording_replayed_by_a_service_equals_the_recorded_run(tmp_path: Path) -> None:
    path, recorded = asyncio.run(_record_through_the_api(tmp_path, 3.0))
    with RecordingReader(path) as r:
        n = len(r.frames)
        assert r.header["calibration"] is not None
        assert r.header["probe"] == "probetest0001"
        assert not r.truncated
        seqs = [f.meta["sequence"] for f in r.frames]
        span = r.frames[-1].meta["delivered_s"] - r.frames[0].meta["delivered_s"]
    # 3 s at 30 fps, less what a loaded machine dropped (the sequence gaps mark them)
    assert 2.7 <= span <= 3.0
    assert seqs[-1] - seqs[0] >= 80
    assert n >= 30
    replayed = asyncio.run(_replay_service(tmp_path, path, n))
    assert sorted(replayed) == list(range(1, n + 1))
    same = [k for k in range(1, n + 1) if recorded.get(k) == replayed[k]]
    diff = [k for k in range(1, n + 1) if k not in same]
    if diff:
        a, b = json.loads(recorded.get(diff[0], "{}")), json.loads(replayed[diff[0]])
        keys = [key for key in set(a) | set(b) if a.get(key) != b.get(key)]
        pytest.fail(f"frames differing: {diff[:10]}; frame {diff[0]} differs in {keys}")


async def _service_on(tmp_path: Path, spec: str) -> dict[str, Any]:
    import aiohttp

    from lightprobe.device.bootstrap import camera_factory, pipeline_factory

    state = tmp_path / "svc"
    state.mkdir()
    cfg = service_config(state)
    async with running_service(cfg, camera_factory(spec), pipeline_factory(state, "probetest0001")) as s, \
            aiohttp.ClientSession() as c:
        t0 = time.monotonic()
        # the runner's state: its retries keep the last error
        while "checksum" not in (s.state.runner.last_error or "") and time.monotonic() - t0 < 60:  # noqa: ASYNC110
            await asyncio.sleep(0.1)
        async with c.get(s.api + "/healthz") as r:
            health = r.status
        async with c.get(s.api + "/status") as r:
            status = await r.json()
        async with c.get(s.api + "/lights") as r:
            lights = r.status
    return {"health": health, "status": status, "lights": lights}


def test_a_failing_replay_camera_leaves_the_service_up_saying_why(tmp_path: Path) -> None:
    from lightprobe.sim.camera import SimCamera

    path = tmp_path / "a.lprec"
    _write(path, _frames(3), SimCamera("flashlight").truth_calibration().to_json())
    raw = bytearray(path.read_bytes())
    raw[-5] ^= 0xFF  # a pixel of the last frame
    bad = tmp_path / "changed.lprec"
    bad.write_bytes(bytes(raw))
    out = asyncio.run(_service_on(tmp_path, f"replay:{bad}"))
    assert out["health"] in (200, 503)
    assert out["lights"] == 503
    cam = out["status"]["camera"]
    assert cam["state"] in ("reconnecting", "starting")  # retrying, the last error kept
    assert "changed.lprec: frame 2 fails its checksum" in cam["error"]

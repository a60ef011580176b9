"""``lightprobe bench replay``: what recording costs a running probe, and how fast a recording replays.

1. **The recorder while the service runs** (the target: < 1 ms of CPU per frame, no frame
   dropped at 30 fps, VGA): ``lightprobe serve --camera sim`` paced at 30 fps, warm; 10 s of
   sets without a recording, then ``POST /api/v1/recordings`` for 10 s. Reported: the writer's
   CPU per frame (queueing on the event loop plus the CRC and the write in its own thread:
   ``cpu_ms_per_frame``), frames the writer could not keep (``lost_frames``), the sensor frames
   the pipeline missed while recording (sequence gaps in the file) against the same count before
   (``/status``'s ``pipeline.frames_drained``), and light sets per second before and during.
2. **Replay as fast as it goes**: the recording read back (every frame's CRC checked), frames per
   second; then the live pipeline on it unpaced (``run-pipeline --camera replay:FILE``), frames per
   second and whether its light sets equal the recorded run's (they must, bit for bit).

Writes ``replay.json``.
"""

from __future__ import annotations

import asyncio
import json
import tempfile
import time
from pathlib import Path
from typing import Any

__all__ = ["run"]


async def _status(session: Any, url: str) -> dict[str, Any]:
    async with session.get(url + "/api/v1/status") as r:
        return dict(await r.json())


async def _record_while_serving(url: str, token: str, seconds: float) -> dict[str, Any]:
    import aiohttp

    auth = {"Authorization": f"Bearer {token}"}
    async with aiohttp.ClientSession() as s:
        s0 = await _status(s, url)
        t0 = time.monotonic()
        await asyncio.sleep(seconds)
        s1 = await _status(s, url)
        t1 = time.monotonic()
        before = {"sets_per_s": (s1["frames"] - s0["frames"]) / (t1 - t0),
                  "frames_drained": s1["pipeline"].get("frames_drained", 0) - s0["pipeline"].get("frames_drained", 0)}
        async with s.post(url + "/api/v1/recordings", json={"seconds": seconds}, headers=auth) as r:
            assert r.status == 202, await r.text()
            rid = (await r.json())["id"]
        f0, t0 = s1["frames"], time.monotonic()
        item: dict[str, Any] = {}
        last: dict[str, Any] = {}
        while item.get("state") not in ("done", "failed"):
            await asyncio.sleep(0.25)
            async with s.get(url + "/api/v1/recordings", headers=auth) as r:
                listing = await r.json()
            item = next(i for i in listing["recordings"] if i["id"] == rid)
            if item.get("cpu_ms_per_frame") is not None:
                last = item
        s2 = await _status(s, url)
        during = {"sets_per_s": (s2["frames"] - f0) / (time.monotonic() - t0)}
    return {"id": rid, "before": before, "during": during, "recording": {**last, "state": item["state"]}}


def _gaps(path: Path) -> dict[str, Any]:
    from lightprobe.drivers.recording import RecordingReader

    with RecordingReader(path) as r:
        seq = [int(f.meta["sequence"]) for f in r.frames]
        lost = sum(int(f.meta.get("lost_before", 0)) for f in r.frames)
        span = r.frames[-1].meta["delivered_s"] - r.frames[0].meta["delivered_s"]
    return {"frames": len(seq), "sensor_frames": seq[-1] - seq[0] + 1, "sequence_gaps": seq[-1] - seq[0] + 1 - len(seq),
            "gaps_at_frames": [k for k in range(1, len(seq)) if seq[k] - seq[k - 1] > 1],
            "lost_by_writer": lost, "seconds": span}


def _read_rate(path: Path) -> dict[str, Any]:
    from lightprobe.drivers.recording import RecordingReader

    t0 = time.perf_counter()
    with RecordingReader(path) as r:
        n = sum(1 for _ in r)
        size = path.stat().st_size
    dt = time.perf_counter() - t0
    return {"frames": n, "frames_per_s": n / dt, "mb_per_s": size / 1e6 / dt}


async def _replay_pipeline(path: Path) -> dict[str, Any]:
    from lightprobe.device.pipeline import Pipeline, PipelineConfig
    from lightprobe.drivers.replay import RecordingEnded, ReplayCamera

    cam = ReplayCamera(path, pace=False)
    await cam.open()
    pipe = Pipeline(cam, cam.factory_calibration(), PipelineConfig(sampler="q2tree", light_count=256))
    await pipe.start()
    lines, t_first = [], None
    try:
        while True:
            try:
                r = await pipe.step()
            except RecordingEnded:
                break
            lines.append(r.lights.comparable_json())
            t_first = t_first or time.perf_counter()
    finally:
        await pipe.stop()
    dt = time.perf_counter() - t_first if t_first else 0.0
    return {"frames": len(lines), "frames_per_s": (len(lines) - 1) / dt if dt > 0 else None, "lines": lines}


def run(out_dir: Path, quick: bool = False) -> dict[str, Any]:
    import subprocess
    import sys

    from lightprobe.bench.service_startup import (
        ROOT,
        start_serve,
        stop_service,
        wait_for_api,
        write_config,
    )

    seconds = 4.0 if quick else 10.0
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="lightprobe-replay-") as tmp:
        state = Path(tmp) / "state"
        state.mkdir()
        cfg = write_config(state, 30.0, 256)
        log = (state / "serve.log").open("w")
        p, url = start_serve("sim", "flashlight", state, cfg, {}, log)
        try:
            import aiohttp

            async def ready() -> None:
                async with aiohttp.ClientSession() as s:
                    await wait_for_api(s, url)
                    while (await _status(s, url))["frames"] < 90:  # noqa: ASYNC110 - warm: three seconds of sets
                        await asyncio.sleep(0.2)

            asyncio.run(ready())
            token = (state / "token").read_text().strip()
            out["while_serving"] = asyncio.run(_record_while_serving(url, token, seconds))
        finally:
            stop_service(p)
            log.close()
        path = state / "recordings" / f"{out['while_serving']['id']}.lprec"
        out["while_serving"]["file"] = _gaps(path)
        # the CLI's own recording: its light sets are the reference the replay must equal
        rec, jsonl = Path(tmp) / "cli.lprec", Path(tmp) / "recorded.jsonl"
        subprocess.run([sys.executable, "-m", "lightprobe.cli", "record", "--camera", "sim", "--seconds",
                        str(seconds), "--out", str(rec), "--jsonl", str(jsonl)], cwd=ROOT, check=True,
                       capture_output=True, env={**__import__("os").environ, "PYTHONPATH": str(ROOT)})
        out["read"] = _read_rate(rec)
        rep = asyncio.run(_replay_pipeline(rec))
        recorded = jsonl.read_text().splitlines()
        out["replay"] = {"frames": rep["frames"], "frames_per_s": rep["frames_per_s"],
                         "identical_to_recorded_run": rep["lines"] == recorded,
                         "recorded_frames": len(recorded), "mb": rec.stat().st_size / 1e6}
    from lightprobe.bench.machine import machine_info

    doc = {**out, "machine": machine_info()}
    (out_dir / "replay.json").write_text(json.dumps(doc, indent=1))
    ws = out["while_serving"]
    summary = {"recorder_cpu_ms_per_frame": ws["recording"].get("cpu_ms_per_frame"),
               "recorder_lost_frames": ws["recording"].get("lost_frames"),
               "sequence_gaps_while_recording": ws["file"]["sequence_gaps"],
               "gaps_at_frames": ws["file"]["gaps_at_frames"],
               "frames_drained_before": ws["before"]["frames_drained"],
               "sets_per_s_before": round(ws["before"]["sets_per_s"], 2),
               "sets_per_s_during": round(ws["during"]["sets_per_s"], 2),
               "read_frames_per_s": round(out["read"]["frames_per_s"], 1),
               "replay_pipeline_frames_per_s": round(out["replay"]["frames_per_s"] or 0.0, 1),
               "replay_identical": out["replay"]["identical_to_recorded_run"]}
    return {**doc, "summary": summary}

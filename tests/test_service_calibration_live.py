"""Live calibration through the real service on the simulator: a simulated technician holds a
checkerboard (lightprobe.sim.board.BoardSchedule via SimCamera.show_board), the HTTP API runs the session,
commit stores a calibration and the pipeline resumes on it. Bad input gets 4xx naming the
parameter and never disturbs the calibration in use."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from service_harness import running_service, service_config

from lightprobe.calibration.store import CalibrationStore
from lightprobe.core.errors import InputError
from lightprobe.device.service.routes.calibration import image_circle, parse_start

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

BOARD = {"cols": 9, "rows": 6, "square": 0.04}


def fast_schedule() -> Any:
    """The technician's sweep with short holds (virtual time: 9 frames still, 3 moving)."""
    from lightprobe.sim.board import BoardSchedule

    return BoardSchedule.technician(hold_s=0.3, move_s=0.1)


def sim_factories(tmp_path: Path) -> tuple[Any, Any]:
    from lightprobe.device.bootstrap import camera_factory, pipeline_factory

    return camera_factory("sim", "flashlight"), pipeline_factory(tmp_path / "state", "calprobe0001")


async def wait_for(fn: Any, limit_s: float, what: str, every: float = 0.3) -> Any:
    t0 = time.monotonic()
    last = None
    while time.monotonic() - t0 < limit_s:
        last = await fn()
        if last:
            return last
        await asyncio.sleep(every)
    raise AssertionError(f"timed out after {limit_s} s waiting for {what} (last: {last!r})")


async def status(c: aiohttp.ClientSession, api: str) -> dict[str, Any]:
    async with c.get(api + "/status") as r:
        return dict(await r.json())


async def fresh_lights_on(c: aiohttp.ClientSession, api: str, cal_id: str) -> bool:
    st = await status(c, api)
    async with c.get(api + "/lights") as r:
        lights = await r.json() if r.status == 200 else {"stale": True}
    return st["calibration_id"] == cal_id and not st["stale"] and not lights["stale"]


def test_parse_start_names_the_field_at_fault() -> None:
    ok = parse_start({"board": BOARD, "targets": {"min_views": 8}})
    assert (ok["cols"], ok["rows"], ok["min_views"], ok["timeout_s"]) == (9, 6, 8, 900.0)
    # a square board calibrates the intrinsics as well (the CLI takes one too); 6.0 is an integer
    assert parse_start({"board": {"cols": 7, "rows": 7.0}})["rows"] == 7
    assert parse_start({"board": BOARD, "exposure_s": None})["exposure_s"] is None  # null: meter once
    for body, param in [({}, "board"), ({"board": {"cols": 1, "rows": 6}}, "board.cols"),
                        ({"board": {"cols": 9, "rows": "6"}}, "board.rows"),
                        ({"board": BOARD, "targets": None}, "targets"),  # found by schemathesis
                        ({"board": BOARD, "idle_timeout_s": None}, "idle_timeout_s"),
                        ({"board": {"cols": 9, "rows": 6, "square": -1}}, "board.square"),
                        ({"board": BOARD, "targets": {"coverage": 2}}, "targets.coverage"),
                        ({"board": BOARD, "timeout_s": float("nan")}, "timeout_s"),
                        ({"board": BOARD, "colour": 1}, "colour"), ([1], "body")]:
        with pytest.raises(InputError) as e:
            parse_start(body)
        assert e.value.param == param, (body, e.value.param)


def test_image_circle_from_mask_fisheye_or_frame() -> None:
    from lightprobe.sim.camera import SimCamera

    truth = SimCamera("room").truth_calibration()
    assert truth.mask is not None
    assert truth.fisheye is not None
    assert image_circle(truth, (640, 480)) == (*truth.mask.center, truth.mask.radius_px)
    _cx, _cy, r = image_circle(truth.with_(mask=None), (640, 480))
    assert abs(r - truth.mask.radius_px) < 3.0, r  # the clean field of view's edge
    assert image_circle(None, (640, 480)) == (320, 240, 240)


async def test_live_calibration_over_http(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = service_config(tmp_path, pipeline={"fps": 5.0, "light_count": 64})
    make_camera, make_pipeline = sim_factories(tmp_path)
    async with running_service(cfg, make_camera, make_pipeline) as s, aiohttp.ClientSession() as c:
        api, live = s.api, s.api + "/calibration/live"
        truth = (await s.state.ensure_camera()).truth_calibration()
        await wait_for(lambda: fresh_lights_on(c, api, truth.id), 300, "first fresh lights")
        async with c.get(api + "/calibration") as r:
            info = await r.json()
        assert r.status == 200
        assert info["current"]["id"] == truth.id
        assert info["history"] == []
        # Bad input: no token, bad board, not JSON, nothing to show yet
        async with c.post(live, json={"board": BOARD}) as r:
            assert r.status == 401
        async with c.post(live, json={"board": {"cols": 1, "rows": 6}}, headers=s.auth) as r:
            assert r.status == 400
            assert (await r.json())["param"] == "board.cols"
        async with c.post(live, data=b"{", headers={**s.auth, "Content-Type": "application/json"}) as r:
            assert r.status == 400
            assert (await r.json())["param"] == "body"
        for method in ("GET", "DELETE"):
            async with c.request(method, live, headers=s.auth) as r:
                assert r.status == 404
                assert (await r.json())["param"] == "session"

        # A session the technician abandons: commit is refused, cancel resumes the old calibration
        async with c.post(live, json={"board": BOARD}, headers=s.auth) as r:
            assert r.status == 201, await r.text()
        async with c.post(live, json={"board": BOARD}, headers=s.auth) as r:
            assert r.status == 409
            assert (await r.json())["param"] == "session"
        async with c.post(live + "/commit", headers=s.auth) as r:
            assert r.status == 409
            assert (await r.json())["param"] == "good_enough"
        st = await status(c, api)
        assert st["camera"]["state"] == "calibrating"
        assert st["stale"]
        # nobody stands in front of a simulated lens: the simulated technician holds the board
        assert s.state.camera.board_schedule is not None
        async with c.get(api + "/lights") as r:
            assert (await r.json())["stale"] is True
        async with c.delete(live) as r:
            assert r.status == 401
        async with c.delete(live, headers=s.auth) as r:
            assert r.status == 200
            assert (await r.json())["state"] == "cancelled"
        await wait_for(lambda: fresh_lights_on(c, api, truth.id), 120, "lights after cancel")
        assert s.state.camera.board_schedule is None  # and leaves with the session
        assert CalibrationStore(tmp_path / "state").versions() == []

        # The technician sweeps the board: the session reaches good enough, commit stores it
        s.state.camera.show_board(fast_schedule())
        async with c.post(live, json={"board": BOARD, "targets": {"min_views": 8, "coverage": 0.7}},
                          headers=s.auth) as r:
            assert r.status == 201, await r.text()

        async def progress() -> dict[str, Any] | None:
            async with c.get(live) as r:
                p = await r.json()
            assert p["state"] not in ("failed", "expired"), p
            return p if p["good_enough"] else None

        p = await wait_for(progress, 300, "good enough", every=1.0)
        assert p["views"] >= 8
        assert p["coverage"]["percent"] >= 70
        assert p["rms_px"] <= 0.5
        assert len(p["coverage"]["grid"]) == 4
        assert p["exposure_s"] > 0
        async with c.get(live + "/frame.jpg", headers=s.auth) as r:
            assert r.status == 200
            assert (await r.read())[:2] == b"\xff\xd8"
        async with c.post(live + "/commit", headers=s.auth) as r:
            done = await r.json()
            assert r.status == 200, done
        new_id = done["committed"]["id"]
        cur = CalibrationStore(tmp_path / "state").load_current()
        assert cur.id == new_id != truth.id
        assert cur.source == "live"
        assert cur.fisheye is not None
        assert truth.fisheye is not None
        err = [cur.fisheye.K[i, i] / truth.fisheye.K[i, i] - 1 for i in (0, 1)]
        print(f"live: {p['views']} views, coverage {p['coverage']['percent']:.0f}%, rms {p['rms_px']:.3f} px, "
              f"focal error {100 * err[0]:+.3f}% / {100 * err[1]:+.3f}%")
        assert max(abs(e) for e in err) <= 0.01, err
        assert cur.body().keys() == truth.body().keys()  # the other sections are kept as they were
        assert cur.with_(fisheye=truth.fisheye, source=truth.source).id == truth.id
        await wait_for(lambda: fresh_lights_on(c, api, new_id), 120, "lights on the new calibration")
        async with c.get(api + "/calibration") as r:
            info = await r.json()
        assert info["current"]["id"] == new_id
        assert [h["id"] for h in info["history"]] == [new_id]
        async with c.post(live + "/commit", headers=s.auth) as r:  # nothing to commit any more
            assert r.status == 404

        # A commit whose write fails (disk full) keeps the calibration in use serving
        async with c.post(live, json={"board": BOARD, "targets": {"coverage": 0.3}}, headers=s.auth) as r:
            assert r.status == 201
        await wait_for(progress, 300, "good enough again", every=1.0)

        def disk_full(self: CalibrationStore, cal: Any) -> Any:
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(CalibrationStore, "save", disk_full)
        async with c.post(live + "/commit", headers=s.auth) as r:
            body = await r.json()
        assert r.status == 500
        assert body["param"] == "commit"
        assert "No space left" in body["error"]
        monkeypatch.undo()
        await wait_for(lambda: fresh_lights_on(c, api, new_id), 120, "lights after a failed commit")
        assert len(CalibrationStore(tmp_path / "state").versions()) == 1

        # A forgotten session ends by itself and the pipeline resumes
        async with c.post(live, json={"board": BOARD, "idle_timeout_s": 2}, headers=s.auth) as r:
            assert r.status == 201
        await asyncio.sleep(4.0)
        async with c.get(live) as r:
            assert (await r.json())["state"] == "expired"
        await wait_for(lambda: fresh_lights_on(c, api, new_id), 120, "lights after an expired session")
        s.state.camera.show_board(None)

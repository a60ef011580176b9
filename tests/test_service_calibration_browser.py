"""The live calibration page in a real browser: Playwright drives Debian's chromium against the
real service on the simulator while a simulated technician sweeps a checkerboard. The session
reaches good enough, commit stores a calibration within 1% of the simulator's focal length and
the pipeline resumes with fresh lights on it. Saves test-artifacts/calibrate.png."""

from __future__ import annotations

from pathlib import Path

import aiohttp
import pytest
from service_harness import running_service, service_config
from test_service_calibration_live import fast_schedule, fresh_lights_on, sim_factories, wait_for

from lightprobe.calibration.store import CalibrationStore

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(600)]

CHROMIUM = next((p for p in ("/usr/lib/chromium/chromium", "/usr/bin/chromium") if Path(p).exists()), None)
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run"]


@pytest.mark.skipif(CHROMIUM is None, reason="Debian chromium not installed (apt-get install chromium)")
async def test_calibration_page_session_to_commit(tmp_path: Path, artifacts_dir: Path) -> None:
    from playwright.async_api import async_playwright

    cfg = service_config(tmp_path, pipeline={"fps": 5.0, "light_count": 64})
    make_camera, make_pipeline = sim_factories(tmp_path)
    async with running_service(cfg, make_camera, make_pipeline) as s, async_playwright() as p, \
            aiohttp.ClientSession() as c:
        truth = (await s.state.ensure_camera()).truth_calibration()
        await wait_for(lambda: fresh_lights_on(c, s.api, truth.id), 300, "first fresh lights")
        browser = await p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            page = await browser.new_page(viewport={"width": 1440, "height": 900})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            await page.goto(s.url + "/")
            await page.click("a[href='/calibrate']")  # the dashboard links to the page
            await page.wait_for_selector("#start-form")
            # A wrong token is refused and names the header
            await page.fill("#token-input", "not-the-token")
            await page.click("#start-button")
            await page.wait_for_selector("#cal-msg.err", timeout=5_000)
            assert "wrong bearer token" in (await page.text_content("#cal-msg") or "")
            s.state.camera.show_board(fast_schedule())
            await page.fill("#token-input", s.token)
            await page.fill("#min-views", "8")
            await page.fill("#target-cover", "70")
            await page.click("#start-button")
            await page.wait_for_selector("#cal-msg.ok", timeout=5_000)
            assert await page.is_disabled("#commit-button")
            # Corners are drawn over the live frame while the board is found
            await page.wait_for_function("+document.getElementById('cal-overlay').dataset.corners === 54",
                                         timeout=60_000)
            # the live frame shows (it reloads every poll: wait for a loaded one)
            await page.wait_for_function("document.getElementById('cal-frame').naturalWidth === 640",
                                         timeout=30_000)
            await page.wait_for_function("document.getElementById('good-enough').dataset.state === 'yes'",
                                         timeout=300_000)
            assert not await page.is_disabled("#commit-button")
            cells = int(await page.eval_on_selector("#coverage", "e => +e.dataset.cells"))
            missing = int(await page.eval_on_selector("#coverage", "e => +e.dataset.missing"))
            assert cells == 32
            assert missing <= 32 * 0.3, (cells, missing)
            await page.screenshot(path=str(artifacts_dir / "calibrate.png"), full_page=True)
            await page.click("#commit-button")
            await page.wait_for_function("document.getElementById('good-enough').dataset.state === 'committed'",
                                         timeout=60_000)
            cur = CalibrationStore(tmp_path / "state").load_current()
            assert cur.fisheye is not None
            assert truth.fisheye is not None
            assert cur.id in (await page.text_content("#cal-msg") or "")
            err = max(abs(cur.fisheye.K[i, i] / truth.fisheye.K[i, i] - 1) for i in (0, 1))
            assert err <= 0.01, f"focal error {100 * err:.3f}%"
            await wait_for(lambda: fresh_lights_on(c, s.api, cur.id), 120, "lights on the new calibration")
            await page.wait_for_function(f"document.getElementById('serving').textContent === '{cur.id}'",
                                         timeout=10_000)
            await page.screenshot(path=str(artifacts_dir / "calibrate_committed.png"), full_page=True)
            assert not errors, errors
        finally:
            await browser.close()

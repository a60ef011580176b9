"""The installer dashboard in a real browser: Playwright drives Debian's chromium against the real
service on 127.0.0.1. Saves test-artifacts/dashboard.png."""

from __future__ import annotations

import shutil
from pathlib import Path

import aiohttp
import pytest
from service_harness import running_service, service_config, sim_factories

pytestmark = pytest.mark.browser

CHROMIUM = next((p for p in ("/usr/lib/chromium/chromium", "/usr/bin/chromium") if Path(p).exists()), None)
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run"]




@pytest.mark.skipif(CHROMIUM is None, reason="Debian chromium not installed (apt-get install chromium)")
@pytest.mark.timeout(600)
async def test_dashboard_live_view_lights_status_and_rename(tmp_path: Path, artifacts_dir: Path) -> None:
    from playwright.async_api import async_playwright

    assert shutil.which("chromium") or CHROMIUM
    cfg = service_config(tmp_path, probe={"name": "Lobby probe"}, pipeline={"fps": 5.0, "light_count": 64})
    make_camera, make_pipeline = sim_factories(tmp_path, "dashprobe001")
    first_frame_s = 300.0
    async with running_service(cfg, make_camera, make_pipeline) as s, async_playwright() as p:
        browser = await p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            page = await browser.new_page(viewport={"width": 1440, "height": 900})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            await page.goto(s.url + "/")
            # without the token the lights are drawn, but the room's pictures are not shown
            await page.wait_for_function("+document.getElementById('lights').dataset.count === 64",
                                         timeout=first_frame_s * 1000)
            await page.wait_for_selector("#image-hint", state="visible", timeout=10_000)
            assert await page.eval_on_selector("#preview", "e => e.dataset.loaded || ''") == ""
            # the URL `make run` prints carries the token in its fragment: taken, kept, hidden
            await page.goto(s.url + "/#token=" + s.token)
            await page.wait_for_function("document.getElementById('pano').dataset.loaded === '1' && "
                                         "document.getElementById('preview').dataset.loaded === '1'",
                                         timeout=60_000)
            assert "#token" not in page.url
            assert await page.evaluate("localStorage.getItem('lightprobe.token')") == s.token
            for img in ("pano", "preview"):
                assert await page.eval_on_selector(f"#{img}", "e => e.naturalWidth") > 0
            await page.wait_for_function("+document.getElementById('lights').dataset.count === 64", timeout=10_000)
            painted = await page.evaluate("""() => { const c = document.getElementById('lights');
                const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
                let n = 0; for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++; return n; }""")
            assert painted > 500
            await page.wait_for_function("document.getElementById('health').textContent === 'ok'", timeout=20_000)
            assert await page.text_content("#camera-state") == "running"
            assert await page.text_content("#probe-name") == "Lobby probe"
            assert await page.text_content("#calibration") not in ("", "—")
            assert len(await page.query_selector_all("#exposures .chip")) >= 1
            assert len(await page.query_selector_all("#timings .row")) == 5
            # rename: a wrong token is refused, the right one saves
            await page.fill("#name-input", "Atrium east")
            await page.fill("#token-input", "not-the-token")
            await page.click("#rename-button")
            await page.wait_for_selector("#rename-msg.err", timeout=5_000)
            assert "wrong bearer token" in (await page.text_content("#rename-msg") or "")
            await page.fill("#token-input", s.token)
            await page.click("#rename-button")
            await page.wait_for_selector("#rename-msg.ok", timeout=5_000)
            await page.wait_for_function("document.getElementById('probe-name').textContent === 'Atrium east'",
                                         timeout=5_000)
            async with aiohttp.ClientSession() as c, c.get(s.api + "/config") as r:
                assert (await r.json())["config"]["probe"]["name"] == "Atrium east"
            # the Record button: a recording of the camera's frames, listed with its download link
            await page.fill("#record-seconds", "1")
            await page.click("#record-button")
            await page.wait_for_selector("#record-msg.ok", timeout=10_000)
            await page.wait_for_selector("#recordings a[download]", timeout=60_000)
            href = await page.eval_on_selector("#recordings a[download]", "a => a.href")
            async with aiohttp.ClientSession() as c, c.get(href) as r:
                assert r.status == 200
                assert (await r.read())[:8] == b"LPREC\r\n\x1a"
            await page.wait_for_timeout(1200)  # one more frame + status poll for the screenshot
            await page.screenshot(path=str(artifacts_dir / "dashboard.png"), full_page=True)
            assert not errors, errors
        finally:
            await browser.close()

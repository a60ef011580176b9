// lightprobe live calibration page: no build step, no dependencies.
// Polls GET /api/v1/calibration/live twice a second while a session runs; draws the latest frame
// with the detected corners and the image circle, and the coverage grid (rings x sectors).
"use strict";
(() => {
  const API = "/api/v1";
  const LIVE = API + "/calibration/live";
  const $ = (id) => document.getElementById(id);
  const tokenKey = "lightprobe.token";
  let token = localStorage.getItem(tokenKey) || "";
  let last = null;          // the last progress JSON
  let shownFrame = -1;      // frames count of the image on screen
  let polling = null;

  const authHeaders = () => (token ? { Authorization: "Bearer " + token } : {});
  const withToken = (url) => (token ? url + (url.includes("?") ? "&" : "?") + "access_token=" + encodeURIComponent(token) : url);
  const fmt = (v, d) => (v === null || v === undefined ? "—" : Number(v).toFixed(d));

  function say(text, ok) {
    const m = $("cal-msg");
    m.textContent = text;
    m.className = "msg " + (ok ? "ok" : "err");
  }

  async function errorText(r) {
    try { const b = await r.json(); return b.error + (b.param ? " (" + b.param + ")" : ""); } catch (e) { return r.status + " " + r.statusText; }
  }

  // ---- drawing --------------------------------------------------------------------------------------
  function drawOverlay() {
    const canvas = $("cal-overlay"), img = $("cal-frame");
    const w = img.clientWidth, h = img.clientHeight;
    if (!w || !h || !last) return;
    const dpr = window.devicePixelRatio || 1;
    canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr);
    const ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    const sx = w / last.image_size[0], sy = h / last.image_size[1];
    const [cx, cy, r] = last.image_circle;
    ctx.strokeStyle = "rgba(242,179,61,.8)"; ctx.lineWidth = 1.5;
    ctx.beginPath(); ctx.ellipse(cx * sx, cy * sy, r * sx, r * sy, 0, 0, 2 * Math.PI); ctx.stroke();
    const pts = last.last_corners || [];
    ctx.fillStyle = "#3ec28f"; ctx.strokeStyle = "rgba(62,194,143,.7)"; ctx.lineWidth = 1;
    const cols = last.board.cols;
    for (let i = 0; i < pts.length; i++) {
      const [x, y] = pts[i];
      ctx.beginPath(); ctx.arc(x * sx, y * sy, 2.5, 0, 2 * Math.PI); ctx.fill();
      if (i % cols !== cols - 1 && i + 1 < pts.length) {  // the board's rows as polylines
        ctx.beginPath(); ctx.moveTo(x * sx, y * sy); ctx.lineTo(pts[i + 1][0] * sx, pts[i + 1][1] * sy); ctx.stroke();
      }
    }
    canvas.dataset.corners = String(pts.length);
  }

  function drawCoverage() {
    const canvas = $("coverage");
    const ctx = canvas.getContext("2d");
    const W = canvas.width, H = canvas.height, R = Math.min(W, H) / 2 - 6;
    ctx.clearRect(0, 0, W, H);
    if (!last) return;
    const grid = last.coverage.grid, rings = last.coverage.rings, sectors = last.coverage.sectors;
    let missing = 0, inside = 0;
    for (let i = 0; i < rings; i++) {
      // equal-area rings: radii R sqrt(i / rings) .. R sqrt((i + 1) / rings) (lightprobe.calibration.fisheye)
      const r0 = R * Math.sqrt(i / rings), r1 = R * Math.sqrt((i + 1) / rings);
      for (let j = 0; j < sectors; j++) {
        const n = grid[i][j];
        const a0 = (2 * Math.PI * j) / sectors, a1 = (2 * Math.PI * (j + 1)) / sectors;
        ctx.beginPath();
        ctx.arc(W / 2, H / 2, r1, a0, a1); ctx.arc(W / 2, H / 2, r0, a1, a0, true); ctx.closePath();
        if (n < 0) { ctx.fillStyle = "#1b1f25"; } else if (n === 0) { ctx.fillStyle = "#6b2a2a"; missing++; inside++; }
        else { ctx.fillStyle = "rgba(62,194,143," + (0.35 + 0.65 * Math.min(1, n / 12)) + ")"; inside++; }
        ctx.fill(); ctx.strokeStyle = "#0f1216"; ctx.lineWidth = 2; ctx.stroke();
      }
    }
    canvas.dataset.missing = String(missing);
    canvas.dataset.cells = String(inside);
  }

  // ---- state ----------------------------------------------------------------------------------------
  function render(p) {
    last = p;
    const pill = $("cal-state");
    pill.textContent = p.state;
    pill.className = "pill " + (p.state === "committed" ? "pill-ok" : p.state === "failed" || p.state === "expired" ? "pill-degraded" : "pill-starting");
    $("last-event").textContent = p.active ? (p.last_event || p.state) : p.state;
    $("views").textContent = p.views;
    $("rejected").textContent = p.views_rejected;
    $("rms").textContent = p.rms_px === null ? "—" : fmt(p.rms_px, 3) + " px";
    $("focal").textContent = p.focal_px === null ? "—" : fmt(p.focal_px, 2) + " px";
    $("frames").textContent = p.frames;
    $("exposure").textContent = p.exposure_s ? fmt(p.exposure_s * 1000, 2) + " ms" : "metering…";
    $("expires").textContent = p.active ? fmt(p.expires_in_s, 0) + " s" : "—";
    $("coverage-pct").textContent = fmt(p.coverage.percent, 0) + "%";
    $("missing").textContent = p.coverage.missing.length ? "Still missing: " + p.coverage.missing.join("; ") : "Every region has corners.";
    $("t-views").textContent = p.targets.min_views;
    $("t-cover").textContent = Math.round(p.targets.coverage * 100);
    const mv = $("m-views"), mc = $("m-cover");
    mv.style.width = Math.min(100, (100 * p.views) / p.targets.min_views) + "%";
    mv.classList.toggle("ok", p.views >= p.targets.min_views);
    mc.style.width = Math.min(100, p.coverage.percent / p.targets.coverage) + "%";
    mc.classList.toggle("ok", p.coverage.percent >= 100 * p.targets.coverage);
    const b = $("good-enough");
    if (p.state === "committed") {
      b.className = "banner done"; b.dataset.state = "committed";
      b.textContent = "Committed: calibration " + p.committed.id + " (version " + p.committed.version + ") is in use";
    } else if (!p.active) {
      b.className = "banner failed"; b.dataset.state = p.state;
      b.textContent = "Session " + p.state + (p.error ? ": " + p.error : "") + " — the previous calibration stays in use";
    } else if (p.good_enough) {
      b.className = "banner yes"; b.dataset.state = "yes";
      b.textContent = "Good enough: commit now, or add views near the rim to refine it";
    } else {
      b.className = "banner"; b.dataset.state = "no";
      b.textContent = "Not good enough yet: " + p.views + "/" + p.targets.min_views + " views, coverage " + fmt(p.coverage.percent, 0) +
        "% of " + Math.round(p.targets.coverage * 100) + "%" + (p.rms_px === null ? "" : ", RMS " + fmt(p.rms_px, 2) + " px");
    }
    $("commit-button").disabled = !(p.active && p.good_enough);
    $("cancel-button").disabled = !p.active;
    $("start-button").disabled = p.active;
    if (p.frames !== shownFrame && p.frames > 0) refreshFrame(p.frames);
    drawOverlay();
    drawCoverage();
  }

  function refreshFrame(frames) {
    const img = $("cal-frame");
    if (img.dataset.loading === "1") return;
    img.dataset.loading = "1";
    const next = new Image();
    next.onload = () => { img.src = next.src; img.dataset.loading = "0"; img.dataset.loaded = "1"; shownFrame = frames; drawOverlay(); };
    next.onerror = () => { img.dataset.loading = "0"; };
    next.src = withToken(LIVE + "/frame.jpg?t=" + Date.now());
  }

  async function poll() {
    try {
      const r = await fetch(LIVE, { headers: authHeaders(), cache: "no-store" });
      if (r.status === 200) {
        const p = await r.json();
        render(p);
        if (!p.active) stopPolling();
      }
    } catch (e) { /* the service restarts: keep polling */ }
  }

  async function serving() {
    try {
      const r = await fetch(API + "/status", { headers: authHeaders(), cache: "no-store" });
      if (r.ok) { const s = await r.json(); $("serving").textContent = (s.calibration_id || "—") + (s.stale ? " (paused)" : ""); }
    } catch (e) { /* ignore */ }
  }

  function startPolling() { if (!polling) polling = setInterval(poll, 500); poll(); }
  function stopPolling() { if (polling) { clearInterval(polling); polling = null; } }

  // ---- actions --------------------------------------------------------------------------------------
  function readToken() {
    token = $("token-input").value.trim();
    if (token) localStorage.setItem(tokenKey, token);
  }

  $("token-input").value = token;
  $("start-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    readToken();
    const body = {
      board: { cols: +$("cols").value, rows: +$("rows").value, square: +$("square").value },
      targets: { min_views: +$("min-views").value, rms_px: +$("target-rms").value, coverage: +$("target-cover").value / 100 },
    };
    const r = await fetch(LIVE, { method: "POST", headers: { ...authHeaders(), "Content-Type": "application/json" }, body: JSON.stringify(body) });
    if (r.status !== 201) { say(await errorText(r), false); return; }
    say("Session started: hold the board still in the regions still marked red.", true);
    shownFrame = -1;
    render(await r.json());
    startPolling();
  });

  $("commit-button").addEventListener("click", async () => {
    readToken();
    $("commit-button").disabled = true;
    say("Solving and storing…", true);
    const r = await fetch(LIVE + "/commit", { method: "POST", headers: authHeaders() });
    if (r.status !== 200) { say(await errorText(r), false); poll(); return; }
    const p = await r.json();
    render(p);
    stopPolling();
    say("Stored calibration " + p.committed.id + " (version " + p.committed.version + ", RMS " + fmt(p.committed.rms_px, 3) +
        " px); the pipeline restarts on it.", true);
  });

  $("cancel-button").addEventListener("click", async () => {
    readToken();
    const r = await fetch(LIVE, { method: "DELETE", headers: authHeaders() });
    if (r.status !== 200) { say(await errorText(r), false); return; }
    render(await r.json());
    stopPolling();
    say("Cancelled: the pipeline resumes with the calibration in use.", true);
  });

  window.addEventListener("resize", drawOverlay);
  setInterval(serving, 1000);
  serving();
  poll().then(() => { if (last && last.active) startPolling(); });
})();

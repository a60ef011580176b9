// lightprobe installer dashboard: no build step, no dependencies.
// Status is polled once a second, lights arrive on the WebSocket, previews refresh per frame.
"use strict";
(() => {
  const API = "/api/v1";
  const $ = (id) => document.getElementById(id);
  const tokenKey = "lightprobe.token";
  let token = localStorage.getItem(tokenKey) || "";
  // `make run` prints the dashboard URL with #token=...: take it, keep it, and drop it from the
  // address bar (a fragment never reaches the server or its logs)
  function takeTokenFromHash() {
    const fromHash = new URLSearchParams(location.hash.slice(1)).get("token");
    if (!fromHash) return;
    token = fromHash; localStorage.setItem(tokenKey, token);
    history.replaceState(null, "", location.pathname + location.search);
    const input = document.getElementById("token-input");
    if (input) input.value = token;
  }
  takeTokenFromHash();
  window.addEventListener("hashchange", takeTokenFromHash);
  let lastLights = null;
  let lastFrameShown = -1;
  let nameDirty = false;

  const authHeaders = () => (token ? { Authorization: "Bearer " + token } : {});
  const withToken = (url) => (token ? url + (url.includes("?") ? "&" : "?") + "access_token=" + encodeURIComponent(token) : url);

  // ---- images: swap only once the new one has loaded (no flicker) --------------------------------
  function refreshImage(img, url) {
    if (img.dataset.loading === "1") return;
    img.dataset.loading = "1";
    const next = new Image();
    next.onload = () => {
      img.src = next.src; img.dataset.loading = "0"; img.dataset.loaded = "1"; drawLights();
      const hint = $("image-hint");
      if (hint) hint.hidden = true;
    };
    next.onerror = () => {
      img.dataset.loading = "0";
      // camera images need the token (the room is private): say so where the picture would be
      const hint = $("image-hint");
      if (hint) hint.hidden = !!token;
    };
    next.src = withToken(url + (url.includes("?") ? "&" : "?") + "t=" + Date.now());
  }

  // ---- lights on the equirect view (CONVENTIONS.md: theta from +y, phi = atan2(x, -z)) --------------
  // Show only the upper hemisphere when no light lies below the horizon (the usual case: the
  // fisheye sees the upper hemisphere and the pipeline zeroes the rest).
  function setCrop(upper) {
    const wrap = $("pano-wrap");
    if (wrap.classList.contains("upper") === upper) return;
    wrap.classList.toggle("upper", upper);
    $("label-bottom").textContent = upper ? "horizon" : "nadir";
    $("label-mid").hidden = upper;
  }

  function drawLights() {
    const canvas = $("lights"), img = $("pano");
    const w = img.clientWidth, h = img.clientHeight;  // the full equirect image (2:1)
    if (!w || !h) return;
    const dpr = window.devicePixelRatio || 1;
    const shownH = $("pano-wrap").classList.contains("upper") ? h / 2 : h;
    canvas.style.height = shownH + "px";
    canvas.width = Math.round(w * dpr); canvas.height = Math.round(shownH * dpr);
    const ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    if (!lastLights) { canvas.dataset.count = "0"; return; }
    const ls = lastLights.lights;
    const lum = ls.map((l) => 0.2126 * l.rgb[0] + 0.7152 * l.rgb[1] + 0.0722 * l.rgb[2]);
    const maxLum = Math.max(1e-30, ...lum);
    const order = lum.map((v, i) => i).sort((a, b) => lum[b] - lum[a]);
    const ringed = new Set(order.slice(0, 8));
    let drawn = 0;
    for (const i of order.slice().reverse()) {
      const d = ls[i].direction;
      const theta = Math.acos(Math.max(-1, Math.min(1, d[1])));
      let phi = Math.atan2(d[0], -d[2]); if (phi < 0) phi += 2 * Math.PI;
      const x = (phi / (2 * Math.PI)) * w, y = (theta / Math.PI) * h;
      const r = Math.max(2, Math.min(16, 16 * Math.sqrt(lum[i] / maxLum)));
      const m = Math.max(...ls[i].rgb, 1e-30);
      const c = ls[i].rgb.map((v) => Math.round(80 + 175 * Math.max(0, v) / m));
      ctx.beginPath(); ctx.arc(x, y, r, 0, 2 * Math.PI);
      ctx.fillStyle = `rgba(${c[0]},${c[1]},${c[2]},0.85)`; ctx.fill();
      ctx.lineWidth = ringed.has(i) ? 2 : 1;
      ctx.strokeStyle = ringed.has(i) ? "#f2b33d" : "rgba(0,0,0,0.6)"; ctx.stroke();
      drawn++;
    }
    canvas.dataset.count = String(drawn);
  }

  function showLights(d) {
    lastLights = d;
    const lumOf = (l) => 0.2126 * l.rgb[0] + 0.7152 * l.rgb[1] + 0.0722 * l.rgb[2];
    const total = d.lights.reduce((a, l) => a + Math.max(0, lumOf(l)), 0);
    const below = d.lights.filter((l) => l.direction[1] < -0.1).reduce((a, l) => a + Math.max(0, lumOf(l)), 0);
    setCrop(total > 0 && below <= 1e-3 * total);
    $("light-count").textContent = d.lights.length;
    $("light-method").textContent = d.method || "—";
    $("light-stale").hidden = !d.stale;
    drawLights();
    if (d.frame !== lastFrameShown) {
      lastFrameShown = d.frame;
      refreshImage($("pano"), API + "/preview.jpg?view=equirect");
      refreshImage($("preview"), API + "/preview.jpg?view=fisheye");
    }
  }

  function connectStream() {
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    const ws = new WebSocket(withToken(`${proto}//${location.host}${API}/stream`));
    ws.onmessage = (ev) => { try { showLights(JSON.parse(ev.data)); } catch (e) { console.error(e); } };
    ws.onclose = () => setTimeout(connectStream, 1000);
  }

  // ---- status ----------------------------------------------------------------------------------
  const fmtExposure = (s) => (s >= 0.1 ? s.toFixed(2) + " s" : s >= 1e-3 ? (s * 1e3).toFixed(2) + " ms" : (s * 1e6).toFixed(0) + " µs");
  const fmtUptime = (s) => { const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60); return `${h}h ${m}m ${Math.floor(s % 60)}s`; };

  function drawHistogram(hist) {
    const c = $("histogram"), w = c.clientWidth, h = c.clientHeight, dpr = window.devicePixelRatio || 1;
    c.width = Math.round(w * dpr); c.height = Math.round(h * dpr);
    const ctx = c.getContext("2d"); ctx.setTransform(dpr, 0, 0, dpr, 0, 0); ctx.clearRect(0, 0, w, h);
    if (!hist || !hist.length) return;
    const m = Math.max(1, ...hist.map((v) => Math.log1p(v)));
    const bw = w / hist.length;
    ctx.fillStyle = "#f2b33d";
    hist.forEach((v, i) => { const bh = (Math.log1p(v) / m) * (h - 4); ctx.fillRect(i * bw + 0.5, h - bh, Math.max(1, bw - 1), bh); });
  }

  function showTimings(t) {
    const box = $("timings"); box.textContent = "";
    // fusion and projection are one pass per frame (the rolling HDR estimate, in the output map)
    const labels = { capture: "capture", prepare: "prepare", fusion: "fusion + projection", sampling: "sampling", total: "total" };
    const keys = Object.keys(labels).filter((k) => k in t);
    const max = Math.max(1e-6, ...keys.map((k) => t[k]));
    for (const k of keys) {
      const row = document.createElement("div"); row.className = "row";
      row.innerHTML = `<span>${labels[k]}</span><span class="track"><span class="fill" style="width:${(100 * t[k] / max).toFixed(1)}%"></span></span><span class="val">${(t[k] * 1e3).toFixed(1)} ms</span>`;
      box.appendChild(row);
    }
  }

  async function pollStatus() {
    try {
      const r = await fetch(API + "/status", { headers: authHeaders(), cache: "no-store" });
      const s = await r.json();
      if (!r.ok) throw new Error(s.error || r.status);
      const health = $("health");
      health.textContent = s.health; health.dataset.health = s.health; health.className = "pill pill-" + s.health;
      $("frame").textContent = s.frame ?? "—";
      $("fps").textContent = s.fps.toFixed(1);
      $("probe-name").textContent = s.probe.name || "(unnamed probe)";
      $("probe-id").textContent = "id " + s.probe.id + " · " + s.probe.model + " " + s.probe.version;
      if (!nameDirty && document.activeElement !== $("name-input")) $("name-input").value = s.probe.name;
      const cam = $("camera-state"); cam.textContent = s.camera.state; cam.className = s.camera.state === "running" ? "good" : "bad";
      const st = $("stale"); st.textContent = s.stale ? "stale (last good set)" : "fresh"; st.className = s.stale ? "bad" : "good";
      $("sampler").textContent = `${s.sampler} × ${s.light_count}`;
      $("calibration").textContent = s.calibration_id || "—";
      $("unit").textContent = s.unit || "—";
      $("frames").textContent = s.frames;
      $("skipped").textContent = s.frames_skipped;
      $("reconnects").textContent = s.camera.reconnects;
      $("clients").textContent = s.websocket.clients;
      $("uptime").textContent = fmtUptime(s.uptime_s);
      const err = $("camera-error"); err.hidden = !s.camera.error; err.textContent = s.camera.error || "";
      const ex = $("exposures"); ex.textContent = "";
      for (const e of s.exposures) { const chip = document.createElement("span"); chip.className = "chip"; chip.textContent = fmtExposure(e); ex.appendChild(chip); }
      drawHistogram(s.histogram);
      showTimings(s.timings || {});
    } catch (e) {
      const health = $("health"); health.textContent = "offline"; health.className = "pill pill-degraded"; health.dataset.health = "offline";
    }
  }

  // ---- rename ------------------------------------------------------------------------------------
  $("token-input").value = token;
  $("token-input").addEventListener("change", () => {  // images load with the token from the next frame on
    token = $("token-input").value.trim();
    if (token) localStorage.setItem(tokenKey, token); else localStorage.removeItem(tokenKey);
  });
  $("name-input").addEventListener("input", () => { nameDirty = true; });
  $("rename-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const msg = $("rename-msg"), btn = $("rename-button");
    token = $("token-input").value.trim();
    if (token) localStorage.setItem(tokenKey, token);
    btn.disabled = true; msg.textContent = "saving…"; msg.className = "msg";
    try {
      const r = await fetch(API + "/config", {
        method: "PUT", headers: { "Content-Type": "application/json", ...authHeaders() },
        body: JSON.stringify({ probe: { name: $("name-input").value.trim() } }),
      });
      const body = await r.json();
      if (!r.ok) throw new Error(body.error || ("HTTP " + r.status));
      msg.textContent = "Saved: the probe now announces itself as “" + body.config.probe.name + "”.";
      msg.className = "msg ok"; nameDirty = false; pollStatus();
    } catch (e) {
      msg.textContent = "Not saved: " + e.message; msg.className = "msg err";
    } finally { btn.disabled = false; }
  });

  // ---- recordings (POST /api/v1/recordings; README "Recordings") -----------------------------------
  async function listRecordings() {
    const ul = $("recordings");
    if (!ul || !token) return;
    try {
      const r = await fetch(API + "/recordings", { headers: authHeaders() });
      if (!r.ok) return;
      const body = await r.json();
      ul.replaceChildren(...body.recordings.slice().reverse().map((rec) => {
        const li = document.createElement("li");
        const mb = ((rec.bytes || 0) / 1e6).toFixed(1) + " MB";
        if (rec.state === "done") {
          const a = document.createElement("a");
          a.href = withToken(API + "/recordings/" + rec.id);
          a.textContent = rec.id + ".lprec";
          a.download = rec.id + ".lprec";
          li.append(a, " " + mb);
        } else {
          li.textContent = rec.id + ": " + rec.state + (rec.frames != null ? ", " + rec.frames + " frames, " + mb : "")
            + (rec.error ? " (" + rec.error + ")" : "");
        }
        return li;
      }));
    } catch (e) { /* the next poll tries again */ }
  }
  $("record-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const msg = $("record-msg"), btn = $("record-button");
    btn.disabled = true; msg.textContent = "starting…"; msg.className = "msg";
    try {
      const r = await fetch(API + "/recordings", {
        method: "POST", headers: { "Content-Type": "application/json", ...authHeaders() },
        body: JSON.stringify({ seconds: Number($("record-seconds").value) }),
      });
      const body = await r.json();
      if (!r.ok) throw new Error(body.error || ("HTTP " + r.status));
      msg.textContent = "Recording " + body.id + " (the estimate restarts: a few sets are marked settling)";
      msg.className = "msg ok"; listRecordings();
    } catch (e) {
      msg.textContent = "Not recording: " + e.message; msg.className = "msg err";
    } finally { btn.disabled = false; }
  });
  setInterval(listRecordings, 2000);
  listRecordings();

  window.addEventListener("resize", drawLights);
  connectStream();
  pollStatus();
  setInterval(pollStatus, 1000);
})();

// lightprobe-three: a lightprobe unit's live lighting in a three.js scene.
//
//   import { connectProbe } from "http://UNIT:8080/js/lightprobe-three.js";  // or the npm package
//   const probe = connectProbe("http://UNIT:8080", { token, renderer, scene });
//
// Keeps three things up to date from the probe's WebSocket stream (SH in the three.js
// convention, every frame):
//   - probe.lightProbe: a THREE.LightProbe holding the ambient SH (the lighting without the
//     primary light; three.js radiance coefficients, so a Lambert surface of albedo 1 shows E/pi);
//   - probe.light: a THREE.DirectionalLight for the primary light (colour, intensity = its
//     irradiance at normal incidence, placed towards it from its target);
//   - scene.environment: a PMREM of the probe's GGX cube map (GET /api/v1/cubemap.ktx2, needs the
//     token), fetched again when the lighting changed (SH moved by more than `cubeChange`).
// Both lights are added to `scene` (with the light's target). Reconnects by itself (backoff
// `reconnectMs`), and marks stale lighting: `probe.stale` is true while the probe says so (its
// camera is away), while the socket is down, or when no frame came for `staleAfterMs`; a
// "stale" event fires when that changes, "update" on every frame, "state" when the connection
// state changes. `probe.captured` is when the light reached the probe's sensor (wall-clock s),
// `probe.age` how old the lighting is by this machine's clock.
//
// Axes: the probe's frame is three.js's (right-handed, +y up); the probe's pose (its
// `pose.rotation` in /api/v1/lights) is applied by rotating `probe.group` (which holds both
// lights; the environment follows `scene.environmentRotation`) when `applyPose` is set.
// Licensed Apache-2.0 (lightprobe). three.js is a peer dependency: the page maps "three" (an
// import map) to its own copy or the probe's (/js/three.module.min.js).
import * as THREE from "three";

const DEFAULTS = {
  token: "",
  renderer: null,
  scene: null,
  environment: true,   // keep scene.environment up to date (needs renderer and the token)
  cubeSize: 64,
  cubeChange: 0.02,    // refetch the cube map when any SH coefficient moved this much (of the DC term)
  cubeMinIntervalMs: 500,
  exposure: 1,         // a number, or a function (shBody) -> number, scaling every light
  staleAfterMs: 1500,
  reconnectMs: [250, 2000],
  lightDistance: 10,
  applyPose: false,
};

function baseUrl(url) {
  const u = new URL(url, globalThis.location ? globalThis.location.href : undefined);
  let path = u.pathname.replace(/\/+$/, "");
  if (path.endsWith("/api/v1")) path = path.slice(0, -"/api/v1".length);
  return { http: `${u.protocol}//${u.host}${path}`, ws: `${u.protocol === "https:" ? "wss:" : "ws:"}//${u.host}${path}` };
}

// KTX2 as the probe writes it (uncompressed RGBA16F cube, levels=1): level 0's six faces
export function parseCubeKTX2(buffer) {
  const dv = new DataView(buffer);
  const size = dv.getUint32(20, true), faces = dv.getUint32(36, true);
  if (faces !== 6) throw new Error(`cubemap.ktx2: ${faces} faces, expected 6`);
  const offset = Number(dv.getBigUint64(80, true));
  const n = size * size * 4;
  return { size, faces: Array.from({ length: 6 }, (_, f) => new Uint16Array(buffer, offset + f * n * 2, n)) };
}

// The probe's faces follow the OpenGL table in the probe's right-handed frame; three.js samples
// a CubeTexture with x mirrored (its cube maps are left-handed). Swapping +X/-X and mirroring
// every face's rows gives three.js the radiance of the direction it asks for.
export function toThreeCubeFaces(size, faces) {
  const mirror = (src) => {
    const out = new Uint16Array(src.length);
    for (let y = 0; y < size; y++) {
      for (let x = 0; x < size; x++) {
        const a = (y * size + x) * 4, b = (y * size + (size - 1 - x)) * 4;
        out[a] = src[b]; out[a + 1] = src[b + 1]; out[a + 2] = src[b + 2]; out[a + 3] = src[b + 3];
      }
    }
    return out;
  };
  return [faces[1], faces[0], faces[2], faces[3], faces[4], faces[5]].map(mirror);
}

export class ProbeConnection extends THREE.EventDispatcher {
  constructor(url, options = {}) {
    super();
    this.options = { ...DEFAULTS, ...options };
    this.url = baseUrl(url);
    this.group = new THREE.Group();
    this.group.name = "lightprobe";
    this.lightProbe = new THREE.LightProbe();
    this.light = new THREE.DirectionalLight(0xffffff, 0);
    this.light.name = "lightprobe primary light";
    this.group.add(this.lightProbe, this.light, this.light.target);
    if (this.options.scene) this.options.scene.add(this.group);
    this.environment = null;
    this.state = "connecting";
    this.stale = true;
    this.frame = -1;
    this.captured = null;
    this.timestamp = null;
    this.message = null;
    this.updates = 0;
    this._closed = false;
    this._lastAt = 0;
    this._backoff = this.options.reconnectMs[0];
    this._cube = { busy: false, at: -Infinity, sh: null };
    this._pmrem = null;
    this._envTarget = null;
    this._timer = setInterval(() => this._checkStale(), 100);
    this._connect();
  }

  get age() { return this.captured == null ? null : Date.now() / 1000 - this.captured; }

  close() {
    this._closed = true;
    clearInterval(this._timer);
    if (this._ws) this._ws.close();
    this._setState("closed");
    this._setStale(true);
  }

  dispose() {
    this.close();
    this.group.removeFromParent();
    if (this._envTarget) this._envTarget.dispose();
    if (this._pmrem) this._pmrem.dispose();
  }

  _setState(state) {
    if (state === this.state) return;
    this.state = state;
    this.dispatchEvent({ type: "state", state });
  }

  _setStale(stale) {
    if (stale === this.stale) return;
    this.stale = stale;
    this.dispatchEvent({ type: "stale", stale });
  }

  _checkStale() {
    const silent = performance.now() - this._lastAt > this.options.staleAfterMs;
    this._setStale(this.state !== "live" || silent || !!(this.message && this.message.stale));
  }

  _connect() {
    if (this._closed) return;
    const token = this.options.token;
    const ws = new WebSocket(`${this.url.ws}/api/v1/stream` + (token ? `?access_token=${encodeURIComponent(token)}` : ""));
    this._ws = ws;
    ws.onopen = () => ws.send(JSON.stringify({ subscribe: ["sh"], convention: "threejs" }));
    ws.onmessage = (ev) => {
      let msg;
      try { msg = JSON.parse(ev.data); } catch { return; }
      if (msg.kind !== "sh") return;  // the light set each SH body follows
      this._backoff = this.options.reconnectMs[0];
      this._setState("live");
      this._apply(msg);
    };
    ws.onclose = () => {
      if (this._ws !== ws) return;
      this._ws = null;
      if (this._closed) return;
      this._setState("reconnecting");
      this._setStale(true);
      setTimeout(() => this._connect(), this._backoff);
      this._backoff = Math.min(this._backoff * 2, this.options.reconnectMs[1]);
    };
  }

  _exposure(msg) {
    const e = this.options.exposure;
    return typeof e === "function" ? e(msg) : e;
  }

  _apply(msg) {
    const k = this._exposure(msg);
    this.lightProbe.sh.fromArray(msg.ambient_coefficients.flat().map((v) => v * k));
    this.lightProbe.intensity = 1;
    const p = msg.primary_light;
    if (p) {
      const peak = Math.max(p.rgb[0], p.rgb[1], p.rgb[2], 1e-30);
      this.light.color.setRGB(p.rgb[0] / peak, p.rgb[1] / peak, p.rgb[2] / peak, THREE.LinearSRGBColorSpace);
      this.light.intensity = peak * k;
      this.light.position.set(p.direction[0], p.direction[1], p.direction[2])
        .multiplyScalar(this.options.lightDistance).add(this.light.target.position);
    } else {
      this.light.intensity = 0;
    }
    if (this.options.applyPose && msg.pose && msg.pose.rotation) {
      const r = msg.pose.rotation;
      const m = new THREE.Matrix4().set(r[0][0], r[0][1], r[0][2], 0, r[1][0], r[1][1], r[1][2], 0,
        r[2][0], r[2][1], r[2][2], 0, 0, 0, 0, 1);
      this.group.quaternion.setFromRotationMatrix(m);
      if (this.options.scene) this.options.scene.environmentRotation.setFromRotationMatrix(m);
    }
    const scene = this.options.scene;
    if (scene && "environmentIntensity" in scene) scene.environmentIntensity = k;
    this.message = msg;
    this.frame = msg.frame;
    this.captured = msg.captured ?? null;
    this.timestamp = msg.timestamp ?? null;
    this._lastAt = performance.now();
    this.updates++;
    this._checkStale();
    if (this._cubeWanted(msg)) this._refreshCube(msg);
    this.dispatchEvent({ type: "update", message: msg });
  }

  _cubeWanted(msg) {
    const o = this.options;
    if (!o.environment || !o.renderer || !o.scene || this._cube.busy) return false;
    if (performance.now() - this._cube.at < o.cubeMinIntervalMs) return false;
    const prev = this._cube.sh;
    if (!prev) return true;
    const c = msg.coefficients.flat();
    const scale = Math.max(1e-30, Math.abs(c[0]) + Math.abs(c[1]) + Math.abs(c[2]));
    return c.some((v, i) => Math.abs(v - prev[i]) > o.cubeChange * scale);
  }

  async _refreshCube(msg) {
    const o = this.options;
    this._cube.busy = true;
    this._cube.at = performance.now();
    try {
      const headers = o.token ? { Authorization: `Bearer ${o.token}` } : {};
      const r = await fetch(`${this.url.http}/api/v1/cubemap.ktx2?size=${o.cubeSize}&levels=1`, { headers });
      if (!r.ok) throw new Error(`cubemap.ktx2: HTTP ${r.status}` + (r.status === 401 ? " (needs the token)" : ""));
      const { size, faces } = parseCubeKTX2(await r.arrayBuffer());
      const images = toThreeCubeFaces(size, faces).map((data) => {
        const t = new THREE.DataTexture(data, size, size, THREE.RGBAFormat, THREE.HalfFloatType);
        t.needsUpdate = true;
        return t;
      });
      const cube = new THREE.CubeTexture(images);
      cube.type = THREE.HalfFloatType;
      cube.format = THREE.RGBAFormat;
      cube.colorSpace = THREE.LinearSRGBColorSpace;
      cube.generateMipmaps = false;
      cube.minFilter = THREE.LinearFilter;
      cube.needsUpdate = true;
      if (!this._pmrem) this._pmrem = new THREE.PMREMGenerator(o.renderer);
      const next = this._pmrem.fromCubemap(cube);
      cube.dispose();
      if (this._closed) { next.dispose(); return; }
      if (this._envTarget) this._envTarget.dispose();
      this._envTarget = next;
      this.environment = next.texture;
      o.scene.environment = next.texture;
      this._cube.sh = msg.coefficients.flat();
      this.dispatchEvent({ type: "environment", texture: next.texture, frame: msg.frame });
    } catch (e) {
      this.dispatchEvent({ type: "error", error: e });
    } finally {
      this._cube.busy = false;
    }
  }
}

export function connectProbe(url, options = {}) {
  return new ProbeConnection(url, options);
}

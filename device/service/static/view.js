// Live three.js view of the probe's lighting: SH (three.js convention, ambient) + the primary light
// as a DirectionalLight + the GGX cube map's mip 0 as the environment (three.js re-filters it with
// its own PMREM). Updates on every frame from the stream's SH subscription.
import * as THREE from "/static/vendor/three.module.min.js";

const tokenKey = "lightprobe.token";
let token = localStorage.getItem(tokenKey) || "";
const fromHash = new URLSearchParams(location.hash.slice(1)).get("token");
if (fromHash) { token = fromHash; localStorage.setItem(tokenKey, token); history.replaceState(null, "", location.pathname); }
const withToken = (url) => (token ? url + (url.includes("?") ? "&" : "?") + "access_token=" + encodeURIComponent(token) : url);
const status = document.getElementById("view-status");

const canvas = document.getElementById("view");
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true });
renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
renderer.toneMapping = THREE.ACESFilmicToneMapping;
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x202020);
const camera = new THREE.PerspectiveCamera(35, 1, 0.1, 100);
camera.position.set(0, 1.2, 7);
camera.lookAt(0, 0, 0);

const probe = new THREE.LightProbe();  // ambient SH: three.js radiance coefficients
const sun = new THREE.DirectionalLight(0xffffff, 0);
scene.add(probe, sun, sun.target);

const glossy = new THREE.Mesh(new THREE.SphereGeometry(0.9, 96, 48),
  new THREE.MeshStandardMaterial({ color: 0xdddddd, roughness: 0.25, metalness: 0.0 }));
glossy.position.x = -2.2;
const lambertScene = new THREE.Mesh(new THREE.SphereGeometry(0.9, 96, 48), new THREE.MeshLambertMaterial({ color: 0xffffff }));
const knot = new THREE.Mesh(new THREE.TorusKnotGeometry(0.55, 0.2, 200, 32),
  new THREE.MeshStandardMaterial({ color: 0xffd27f, roughness: 0.35, metalness: 1.0 }));
knot.position.x = 2.2;
scene.add(glossy, lambertScene, knot);
let meshInfo = { source: "torus knot", triangles: 0 };

// The probe's [view] mesh (an OBJ file), when one is configured, takes the torus knot's place:
// positions and faces (polygons as fans; v/vt/vn and negative indices), normals from three.js.
function parseOBJ(text) {
  const v = [], idx = [];
  for (const line of text.split("\n")) {
    const p = line.trim().split(/\s+/);
    if (p[0] === "v") v.push(+p[1], +p[2], +p[3]);
    else if (p[0] === "f") {
      const n = v.length / 3;
      const k = p.slice(1).map((r) => { const i = parseInt(r, 10); return i < 0 ? n + i : i - 1; });
      for (let j = 1; j + 1 < k.length; j++) idx.push(k[0], k[j], k[j + 1]);
    }
  }
  const g = new THREE.BufferGeometry();
  g.setAttribute("position", new THREE.Float32BufferAttribute(v, 3));
  g.setIndex(idx);
  g.computeVertexNormals();
  g.computeBoundingSphere();  // centred and scaled to the knot's place
  const s = g.boundingSphere;
  g.translate(-s.center.x, -s.center.y, -s.center.z);
  g.scale(0.85 / s.radius, 0.85 / s.radius, 0.85 / s.radius);
  return { geometry: g, triangles: idx.length / 3 };
}

fetch(withToken("/view/mesh.obj")).then(async (r) => {
  if (!r.ok) return;  // none configured: the torus knot stays
  const name = (r.headers.get("Content-Disposition") || "").match(/filename="([^"]+)"/);
  const { geometry, triangles } = parseOBJ(await r.text());
  knot.geometry.dispose();
  knot.geometry = geometry;
  meshInfo = { source: name ? name[1] : "mesh.obj", triangles };
  document.getElementById("view-mesh").textContent = `${meshInfo.source} in metal (${triangles} triangles)`;
  window.lightprobeView.mesh = meshInfo;
}).catch((e) => { status.textContent += ` · view mesh: ${e}`; });

// The PBR meshes take their light from the environment (which holds the ambient light),
// the Lambert sphere from the SH light probe only: each light is counted once.
const pmrem = new THREE.PMREMGenerator(renderer);
let envTarget = null;
let exposure = 1.0;

function resize() {
  const w = canvas.clientWidth, h = canvas.clientHeight;
  renderer.setSize(w, h, false);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
}
window.addEventListener("resize", resize);
resize();

function applySH(msg) {
  const c = msg.ambient_coefficients.flat();
  const mean = Math.max(1e-9, (msg.coefficients[0][0] + msg.coefficients[0][1] + msg.coefficients[0][2]) / 3 * 0.886227 / Math.PI);
  exposure = 0.18 / mean;  // auto exposure: a grey card under the average light reads middle grey
  probe.sh.fromArray(c.map((v) => v * exposure));
  probe.intensity = 1;
  const p = msg.primary_light;
  if (p) {
    const peak = Math.max(...p.rgb, 1e-12);
    sun.color.setRGB(p.rgb[0] / peak, p.rgb[1] / peak, p.rgb[2] / peak);
    sun.intensity = peak * exposure;
    sun.position.set(p.direction[0], p.direction[1], p.direction[2]).multiplyScalar(10);
  } else {
    sun.intensity = 0;
  }
  // the PBR meshes are lit by the environment: it holds the ambient light, the sun is separate
  for (const m of [glossy.material, knot.material]) m.envMapIntensity = exposure;
  status.textContent = `frame ${msg.frame} · ${msg.stale ? "stale" : "live"}` + (p ? ` · primary light ${p.direction.map((v) => v.toFixed(2)).join(", ")}` : " · no primary light");
}

// KTX2 (uncompressed RGBA16F, as the probe writes it): level 0's six faces
function parseKTX2Level0(buf) {
  const dv = new DataView(buf);
  const w = dv.getUint32(20, true), faces = dv.getUint32(36, true);
  const off = Number(dv.getBigUint64(80, true));
  const faceBytes = w * w * 8;
  const out = [];
  for (let f = 0; f < faces; f++) out.push(new Uint16Array(buf, off + f * faceBytes, w * w * 4));
  return { size: w, faces: out };
}

let lastCubeFrame = -1, cubeBusy = false;
async function refreshCube(frame) {
  if (cubeBusy || frame === lastCubeFrame) return;
  cubeBusy = true;
  try {
    const r = await fetch(withToken("/api/v1/cubemap.ktx2?size=64&levels=1"));
    if (!r.ok) { status.textContent += ` · cube map: HTTP ${r.status}` + (r.status === 401 ? " (needs the token)" : ""); return; }
    const { size, faces } = parseKTX2Level0(await r.arrayBuffer());
    const images = faces.map((data) => {
      const t = new THREE.DataTexture(data, size, size, THREE.RGBAFormat, THREE.HalfFloatType);
      t.needsUpdate = true;
      return t;
    });
    const cube = new THREE.CubeTexture(images);
    cube.type = THREE.HalfFloatType;
    cube.format = THREE.RGBAFormat;
    cube.generateMipmaps = false;
    cube.minFilter = THREE.LinearFilter;
    cube.needsUpdate = true;
    const next = pmrem.fromCubemap(cube);
    if (envTarget) envTarget.dispose();
    envTarget = next;
    glossy.material.envMap = knot.material.envMap = envTarget.texture;
    glossy.material.needsUpdate = knot.material.needsUpdate = true;
    lastCubeFrame = frame;
  } finally {
    cubeBusy = false;
  }
}

function connect() {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  const ws = new WebSocket(withToken(`${proto}//${location.host}/api/v1/stream`));
  ws.onopen = () => ws.send(JSON.stringify({ subscribe: ["sh"], convention: "threejs" }));
  let frames = 0;
  ws.onmessage = (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.kind !== "sh") return;
    applySH(msg);
    if (frames++ % 30 === 0) refreshCube(msg.frame);  // the cube map is cached until the light changes
  };
  ws.onclose = () => { status.textContent = "reconnecting…"; setTimeout(connect, 1000); };
}
connect();

renderer.setAnimationLoop((t) => {
  knot.rotation.y = t * 0.0004;
  renderer.render(scene, camera);
});
window.lightprobeView = { scene, probe, sun, renderer, mesh: meshInfo };

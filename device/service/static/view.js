// Live three.js view of the probe's lighting, made with the three.js host module (/js/lightprobe-three.js,
// hostlink/threejs): SH (three.js convention, ambient) in a LightProbe + the primary light as a
// DirectionalLight + the GGX cube map as scene.environment (PMREM). Updates on every frame.
import * as THREE from "three";
import { connectProbe } from "/js/lightprobe-three.js";

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

function resize() {
  const w = canvas.clientWidth, h = canvas.clientHeight;
  renderer.setSize(w, h, false);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
}
window.addEventListener("resize", resize);
resize();

// auto exposure: a grey card under the average light reads middle grey
function exposure(msg) {
  const c0 = msg.coefficients[0];
  return 0.18 / Math.max(1e-9, (c0[0] + c0[1] + c0[2]) / 3 * 0.886227 / Math.PI);
}

const probe = connectProbe(location.origin, { token, renderer, scene, exposure });
function showStatus() {
  const msg = probe.message;
  if (!msg) { status.textContent = probe.state === "reconnecting" ? "reconnecting…" : "connecting…"; return; }
  const p = msg.primary_light;
  const age = probe.age == null ? "" : ` · ${(1000 * probe.age).toFixed(0)} ms old`;
  status.textContent = `frame ${msg.frame} · ${probe.stale ? "stale" : "live"}${age}` +
    (p ? ` · primary light ${p.direction.map((v) => v.toFixed(2)).join(", ")}` : " · no primary light");
}
probe.addEventListener("update", showStatus);
probe.addEventListener("stale", showStatus);
probe.addEventListener("state", showStatus);
probe.addEventListener("error", (e) => { status.textContent += ` · ${e.error.message}`; });

renderer.setAnimationLoop((t) => {
  knot.rotation.y = t * 0.0004;
  renderer.render(scene, camera);
});
window.lightprobeView = { scene, probe: probe.lightProbe, sun: probe.light, renderer, mesh: meshInfo, connection: probe };

// The 3D view: a version's mesh (decimated on the server, one binary document) drawn with
// three.js, coloured per vertex by albedo, height, slope or change since the parent version.
// When the first frame is drawn, body[data-drawn-ms] holds the time since navigation start
// (bench/console.py reads it).
import * as THREE from "/console/vendor/three.module.min.js";
import { documentOf, fmt, getDocument, getJSON, header, params, showError } from "/console/common.js";

const timings = { module: performance.now() };
header();
const holder = document.getElementById("view");
const status = document.getElementById("status");
const width = Math.min(window.innerWidth - 40, 1000);
const height = Math.round(width * 0.62);
// the context view-prefetch.js made while this module loaded
const renderer = new THREE.WebGLRenderer({ canvas: window.pwmCanvas, context: await window.pwmContext,
  antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(1);
renderer.setSize(width, height);
holder.append(renderer.domElement);
timings.context = performance.now();
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x0b0e13);
const camera = new THREE.PerspectiveCamera(35, width / height, 1e-4, 100);
scene.add(new THREE.AmbientLight(0xffffff, 0.45));
const sun = new THREE.DirectionalLight(0xffffff, 1.6);
scene.add(sun);
const material = new THREE.MeshLambertMaterial({ vertexColors: true });
let mesh = null;
let document_ = null;
const orbit = { yaw: 0, pitch: 0, distance: 1, target: new THREE.Vector3(), up: new THREE.Vector3(0, 0, 1) };

// The colours come made from the server (uint8 RGB per vertex): no per-vertex work here.
function colours(field) {
  const { header: h, arrays } = document_;
  const scale = h.colours[field];
  document.getElementById("legend").textContent = scale.min === null
    ? `${field}: unknown everywhere (grey)` + (field === "change" && h.parent === null ? ": no parent version" : "")
    : `${field}: ${fmt(scale.min)} to ${fmt(scale.max)} ${scale.unit} (` +
      (field === "change" ? "blue lower, red higher than the parent" : "2nd to 98th percentile") + "; grey: unknown)";
  return new THREE.BufferAttribute(arrays[`colour_${field}`], 3, true);
}

function place() {
  const { yaw, pitch, distance, target, up } = orbit;
  // orbit about the target: yaw about the up axis, pitch towards it
  const base = new THREE.Vector3().copy(target).normalize();
  if (base.lengthSq() === 0) base.set(1, 0, 0);
  const side = new THREE.Vector3().crossVectors(up, base).normalize();
  const eye = base.clone().applyAxisAngle(up, yaw);
  eye.applyAxisAngle(side.clone().applyAxisAngle(up, yaw), -pitch);
  camera.position.copy(target).addScaledVector(eye, distance);
  camera.up.copy(up);
  camera.lookAt(target);
  sun.position.copy(camera.position).add(new THREE.Vector3().crossVectors(eye, up).multiplyScalar(distance * 0.5));
}

function draw() {
  place();
  renderer.render(scene, camera);
}

async function show(version, responding) {
  const started = performance.now();
  status.textContent = "loading…";
  document_ = await (responding ? documentOf(responding) : getDocument(`/console/api/versions/${version}/mesh`));
  timings.fetched = performance.now();
  const { header: h, arrays } = document_;
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(arrays.vertices, 3));
  geometry.setIndex(new THREE.BufferAttribute(arrays.faces, 1));
  geometry.setAttribute("normal", new THREE.BufferAttribute(arrays.normals, 3, true));
  geometry.setAttribute("color", colours(document.getElementById("colour").value));
  geometry.computeBoundingSphere();
  if (mesh) { scene.remove(mesh); mesh.geometry.dispose(); }
  mesh = new THREE.Mesh(geometry, material);
  scene.add(mesh);
  const sphere = geometry.boundingSphere;
  // look at the finest part: the vertex-weighted centre is where the dense (refined) region is
  const centre = new THREE.Vector3();
  const v = arrays.vertices;
  for (let i = 0; i < v.length; i += 3) centre.x += v[i], centre.y += v[i + 1], centre.z += v[i + 2];
  centre.divideScalar(v.length / 3);
  const dense = centre.length() > 0.3 * sphere.radius;
  orbit.target.copy(dense ? nearestSurface(centre) : sphere.center);
  // close enough that the dense region (most of the vertices) fills the view
  orbit.distance = dense ? Math.min(sphere.radius * 0.9, 4 * nearDistance(orbit.target)) : sphere.radius * 3.2;
  camera.near = orbit.distance / 1000;
  camera.far = orbit.distance + 4 * sphere.radius;
  camera.updateProjectionMatrix();
  timings.built = performance.now();
  draw();
  renderer.getContext().finish();
  const elapsed = performance.now();
  timings.drawn = elapsed;
  document.body.dataset.timings = JSON.stringify(timings);
  document.getElementById("title").textContent =
    `3D view: version ${h.version} (${fmt(h.faces)} of ${fmt(h.faces_full)} faces)`;
  status.textContent = `drawn in ${fmt((elapsed - started) / 1000)} s`;
  if (!document.body.dataset.drawnMs) document.body.dataset.drawnMs = String(Math.round(elapsed));
  document.body.dataset.version = h.version;
}

function nearDistance(point) {
  // the 30th percentile of a sample of the vertices' distances from the point
  const v = document_.arrays.vertices;
  const step = 3 * Math.max(1, Math.floor(v.length / 3 / 5000));
  const d = [];
  for (let i = 0; i < v.length; i += step) d.push(Math.hypot(v[i] - point.x, v[i + 1] - point.y, v[i + 2] - point.z));
  d.sort((a, b) => a - b);
  return d[Math.floor(0.3 * d.length)];
}

function nearestSurface(direction) {
  // the vertex nearest the direction in angle: where the line from the centre meets the surface
  const v = document_.arrays.vertices;
  const d = direction.clone().normalize();
  let best = -Infinity, at = 0;
  for (let i = 0; i < v.length; i += 3) {
    const s = (v[i] * d.x + v[i + 1] * d.y + v[i + 2] * d.z) / Math.hypot(v[i], v[i + 1], v[i + 2]);
    if (s > best) best = s, at = i;
  }
  return new THREE.Vector3(v[at], v[at + 1], v[at + 2]);
}

let dragging = null;
renderer.domElement.addEventListener("pointerdown", (e) => { dragging = [e.clientX, e.clientY]; });
window.addEventListener("pointerup", () => { dragging = null; });
window.addEventListener("pointermove", (e) => {
  if (!dragging || !mesh) return;
  orbit.yaw -= (e.clientX - dragging[0]) * 0.005;
  orbit.pitch = Math.max(-1.5, Math.min(1.5, orbit.pitch + (e.clientY - dragging[1]) * 0.005));
  dragging = [e.clientX, e.clientY];
  draw();
});
renderer.domElement.addEventListener("wheel", (e) => {
  e.preventDefault();
  orbit.distance *= Math.exp(e.deltaY * 0.001);
  draw();
}, { passive: false });
document.getElementById("colour").addEventListener("change", (e) => {
  if (!mesh) return;
  mesh.geometry.setAttribute("color", colours(e.target.value));
  draw();
});

async function start() {
  const wanted = params().get("v") || "latest";
  const field = params().get("colour");
  if (field) document.getElementById("colour").value = field;
  const drawn = show(wanted, window.pwmFirstMesh);
  const page = await getJSON("/versions?limit=1000");
  const select = document.getElementById("version");
  for (const v of page.items) select.append(new Option(`v${v.version} (${v.kind})`, v.version));
  await drawn;
  select.value = document.body.dataset.version;
  select.addEventListener("change", () => show(select.value).catch((error) => showError(status, error)));
}

start().catch((error) => showError(status, error));

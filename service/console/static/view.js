// The 3D view: a version's mesh (decimated on the server, one binary document) drawn with
// three.js, coloured per vertex by albedo, height, slope, change since the parent version or
// height uncertainty, with the colour bar of what is coloured, a scale bar at the body's centre
// and the body's size.
// It opens on the whole body (north up, the refined region towards the viewer) and "reset view"
// goes back there. A version too big for one file is stored in tiles: its document lists them
// with each decimated face's tile, and once zoomed in so far that the decimated faces' edges
// span DETAIL_PX pixels, or where double-clicked, the tile at the view's centre (under the
// pointer) is drawn at full resolution in place of its decimated faces (body[data-tiles-loaded]
// counts them). When the first frame is drawn, body[data-drawn-ms] holds the time since
// navigation start (bench/console.py reads it), body[data-framing] how far out the mesh's
// vertices reach in the view (1: its edge).
import * as THREE from "/console/vendor/three.module.min.js";
import { documentOf, fmt, getDocument, getJSON, header, params, showError } from "/console/common.js";
import { colourBar, lengthText, scaleBar, svg } from "/console/maps.js";

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
const FOV_DEG = 35;
// the whole body's bounding sphere fills this share of the narrower side of the view
const FILL = 0.9;
const PITCH0 = 0.35; // rad above the equator, so that the north is seen a little
const camera = new THREE.PerspectiveCamera(FOV_DEG, width / height, 1e-4, 100);
scene.add(new THREE.AmbientLight(0xffffff, 0.45));
const sun = new THREE.DirectionalLight(0xffffff, 1.6);
scene.add(sun);
const material = new THREE.MeshLambertMaterial({ vertexColors: true });
let mesh = null;
let document_ = null;
const up = new THREE.Vector3(0, 0, 1);
const orbit = { yaw: 0, pitch: PITCH0, distance: 1, target: new THREE.Vector3() };
let home = { ...orbit };
const scaleHolder = svg("svg", { width: 180, height: 34, class: "corner" });
holder.append(scaleHolder);

const LABELS = { albedo: "albedo", height: "height above the mean radius", slope: "slope from the radial direction",
  change: "height change since the parent", sigma: "height uncertainty (1 sigma)" };
const NOTES = { albedo: "2nd to 98th percentile; grey: unknown", height: "2nd to 98th percentile; grey: unknown",
  slope: "2nd to 98th percentile; grey: unknown", change: "blue lower, red higher than the parent; grey: unknown",
  sigma: "2nd to 98th percentile; grey: no refined maplet" };

// The colours come made from the server (uint8 RGB per vertex): no per-vertex work here; the
// colour bar shows the colour map's samples the server sent.
function colourBarOf(field) {
  const { header: h } = document_;
  const scale = h.colours[field];
  const unknown = scale.min === null;
  const note = unknown ? "unknown everywhere (grey)" + (field === "change" && h.parent === null ? ": no parent version" : "") : NOTES[field];
  document.getElementById("colour-bar").replaceChildren(colourBar({ label: LABELS[field], unit: scale.unit,
    lo: scale.min, hi: scale.max, stops: scale.stops, width: Math.min(width, 420), note }));
  document.getElementById("legend").textContent = unknown ? `${field}: ${note}`
    : `${field}: ${fmt(scale.min)} to ${fmt(scale.max)} ${scale.unit} (${note})`;
}

function colourOf(doc, field) {
  return new THREE.BufferAttribute(doc.arrays[`colour_${field}`], 3, true);
}

function geometryOf(doc, field) {
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(doc.arrays.vertices, 3));
  geometry.setIndex(new THREE.BufferAttribute(doc.arrays.faces, 1));
  geometry.setAttribute("normal", new THREE.BufferAttribute(doc.arrays.normals, 3, true));
  geometry.setAttribute("color", colourOf(doc, field));
  geometry.computeBoundingSphere();
  return geometry;
}

// The tiles drawn at full resolution (key -> mesh), and the decimated faces still drawn (their
// numbers in the document) once some are.
const tiles = new Map();
let kept = null;
const raycaster = new THREE.Raycaster();
const DETAIL_PX = 3;
let coarseEdgeKm = 0; // the drawn document's mean edge

function meanEdgeKm() {
  const { vertices: v, faces: f } = document_.arrays;
  const step = 3 * Math.max(1, Math.floor(f.length / 3 / 5000));
  let total = 0, count = 0;
  for (let i = 0; i < f.length; i += step) {
    const [a, b] = [f[i], f[i + 1]];
    total += Math.hypot(v[3 * a] - v[3 * b], v[3 * a + 1] - v[3 * b + 1], v[3 * a + 2] - v[3 * b + 2]);
    count++;
  }
  return count ? total / count : 0;
}

function dropTiles() {
  for (const part of tiles.values()) { scene.remove(part); part.geometry.dispose(); }
  tiles.clear();
  kept = null;
  document.body.dataset.tilesLoaded = "0";
}

// The decimated faces of the tiles not drawn at full resolution.
function keepCoarse() {
  const { header: h, arrays } = document_;
  const loaded = new Set(h.tiles.map((t, i) => (tiles.has(t.key) ? i : -1)).filter((i) => i >= 0));
  const keep = [];
  for (let f = 0; f < arrays.face_tile.length; f++) if (!loaded.has(arrays.face_tile[f])) keep.push(f);
  kept = Uint32Array.from(keep);
  const index = new Uint32Array(3 * kept.length);
  kept.forEach((f, i) => index.set(arrays.faces.subarray(3 * f, 3 * f + 3), 3 * i));
  mesh.geometry.setIndex(new THREE.BufferAttribute(index, 1));
}

function describe() {
  const h = document_.header;
  const full = [...tiles.values()].reduce((n, part) => n + part.userData.faces, 0);
  document.getElementById("title").textContent = `3D view: version ${h.version} (${fmt(h.faces)} of ` +
    `${fmt(h.faces_full)} faces` + (tiles.size ? `; ${tiles.size} of ${h.tiles.length} tiles at full resolution, ` +
    `${fmt(full)} faces` : "") + ")";
  document.getElementById("tiles-note").textContent = h.tiles
    ? `Stored in ${h.tiles.length} tiles: zoom in, or double-click the surface, to draw the tile there at full resolution.`
    : "";
}

async function loadTile(number) {
  const h = document_.header;
  const { key } = h.tiles[number];
  if (tiles.has(key)) return;
  status.textContent = `loading tile ${key} at full resolution…`;
  const doc = await getDocument(`/console/api/versions/${h.version}/tiles/${key}/mesh`);
  if (document_.header !== h || tiles.has(key)) return; // another version shown meanwhile
  const part = new THREE.Mesh(geometryOf(doc, document.getElementById("colour").value), material);
  part.userData = { document: doc, faces: doc.header.faces };
  scene.add(part);
  tiles.set(key, part);
  keepCoarse();
  draw();
  describe();
  status.textContent = "";
  document.body.dataset.tilesLoaded = String(tiles.size);
}

function place() {
  const { yaw, pitch, distance, target } = orbit;
  // the eye on a sphere about the target: yaw about the spin axis (+Z), pitch above the equator
  const eye = new THREE.Vector3(Math.cos(pitch) * Math.cos(yaw), Math.cos(pitch) * Math.sin(yaw), Math.sin(pitch));
  camera.position.copy(target).addScaledVector(eye, distance);
  camera.up.copy(up);
  camera.lookAt(target);
  camera.near = distance / 1000;
  camera.far = distance + 4 * (mesh ? mesh.geometry.boundingSphere.radius : 1);
  camera.updateProjectionMatrix();
  sun.position.copy(camera.position).add(new THREE.Vector3().crossVectors(eye, up).multiplyScalar(distance * 0.5));
}

// Pixels a km spans at the target's depth.
function pxPerKm() {
  return height / (2 * orbit.distance * Math.tan(THREE.MathUtils.degToRad(FOV_DEG) / 2));
}

// A scale bar of lengths at the target's depth (km in the document; the bar in m or km).
function drawScale() {
  scaleHolder.replaceChildren(scaleBar(8, 28, 1000 / pxPerKm(), 150));
  scaleHolder.lastChild.append(svg("title", {}, "at the distance of the body's centre"));
}

function draw() {
  place();
  renderer.render(scene, camera);
  drawScale();
}

// How far out the vertices reach in the view: the largest |x| or |y| of a sample of them in
// normalised device coordinates (at most 1: the whole body is in view).
function framing() {
  const v = document_.arrays.vertices;
  const step = 3 * Math.max(1, Math.floor(v.length / 3 / 20000));
  const p = new THREE.Vector3();
  let reach = 0;
  for (let i = 0; i < v.length; i += step) {
    p.set(v[i], v[i + 1], v[i + 2]).project(camera);
    reach = Math.max(reach, Math.abs(p.x), Math.abs(p.y));
  }
  return reach;
}

function reset() {
  Object.assign(orbit, home, { target: home.target.clone() });
  draw();
  document.body.dataset.framing = framing().toFixed(3);
}

async function show(version, responding) {
  status.textContent = "loading…";
  document_ = await (responding ? documentOf(responding) : getDocument(`/console/api/versions/${version}/mesh`));
  timings.fetched = performance.now();
  const { header: h, arrays } = document_;
  const geometry = geometryOf(document_, document.getElementById("colour").value);
  coarseEdgeKm = meanEdgeKm();
  colourBarOf(document.getElementById("colour").value);
  dropTiles();
  if (mesh) { scene.remove(mesh); mesh.geometry.dispose(); }
  mesh = new THREE.Mesh(geometry, material);
  scene.add(mesh);
  const sphere = geometry.boundingSphere;
  // The whole body in view: its bounding sphere within the narrower field of view, turned so
  // that the dense (refined) region, where the vertex-weighted centre leans, faces the viewer.
  const centre = new THREE.Vector3();
  const v = arrays.vertices;
  for (let i = 0; i < v.length; i += 3) centre.x += v[i], centre.y += v[i + 1], centre.z += v[i + 2];
  centre.divideScalar(v.length / 3).sub(sphere.center);
  const half = Math.min(THREE.MathUtils.degToRad(FOV_DEG) / 2, Math.atan(Math.tan(THREE.MathUtils.degToRad(FOV_DEG) / 2) * camera.aspect));
  home = { yaw: Math.hypot(centre.x, centre.y) > 1e-3 * sphere.radius ? Math.atan2(centre.y, centre.x) : 0,
    pitch: PITCH0, distance: sphere.radius / Math.sin(half * FILL), target: sphere.center.clone() };
  Object.assign(orbit, home, { target: home.target.clone() });
  timings.built = performance.now();
  draw();
  renderer.getContext().finish();
  const elapsed = performance.now();
  timings.drawn = elapsed;
  document.body.dataset.timings = JSON.stringify(timings);
  document.body.dataset.framing = framing().toFixed(3);
  describe();
  const [sx, sy, sz] = h.extent_km.sides;
  document.getElementById("extent").textContent =
    `Body: ${lengthText(sx * 1000)} x ${lengthText(sy * 1000)} x ${lengthText(sz * 1000)} along the body-fixed x, y, z; ` +
    `${lengthText(h.extent_km.max_radius * 1000)} from the centre at most.`;
  status.textContent = "";
  if (!document.body.dataset.drawnMs) document.body.dataset.drawnMs = String(Math.round(elapsed));
  document.body.dataset.version = h.version;
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
document.getElementById("reset").addEventListener("click", () => { if (mesh) reset(); });
document.getElementById("colour").addEventListener("change", (e) => {
  if (!mesh) return;
  colourBarOf(e.target.value);
  for (const part of [mesh, ...tiles.values()]) {
    part.geometry.setAttribute("color", colourOf(part === mesh ? document_ : part.userData.document, e.target.value));
  }
  draw();
});
// The tile under the view's point (x, y) in normalised device coordinates drawn at full
// resolution, unless there is space there or a tile already drawn so.
function detailAt(x, y) {
  if (!mesh || !document_.header.tiles) return;
  raycaster.setFromCamera(new THREE.Vector2(x, y), camera);
  const hit = raycaster.intersectObjects([mesh, ...tiles.values()], false)[0];
  if (!hit || hit.object !== mesh) return;
  const face = kept ? kept[hit.faceIndex] : hit.faceIndex;
  loadTile(document_.arrays.face_tile[face]).catch((error) => showError(status, error));
}

renderer.domElement.addEventListener("dblclick", (e) => {
  const rect = renderer.domElement.getBoundingClientRect();
  detailAt(((e.clientX - rect.left) / rect.width) * 2 - 1, 1 - ((e.clientY - rect.top) / rect.height) * 2);
});
// zoomed in past what the decimated faces show: the tile at the centre, once the wheel rests
let resting = null;
renderer.domElement.addEventListener("wheel", () => {
  clearTimeout(resting);
  resting = setTimeout(() => { if (coarseEdgeKm * pxPerKm() > DETAIL_PX) detailAt(0, 0); }, 250);
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

// A site: height, slope, roughness and albedo at the finest level there and the hazard map
// (slopes above a threshold, boulders standing above the local plane), from one binary
// document the server makes (service/console.py); a profile along a line drawn on the height
// map; the site terrain product to download. Maps are drawn with +y (north) up.
import { fmt, getDocument, getJSON, header, params, range, showError, tableRow, viridis } from "/console/common.js";

header();
const status = document.getElementById("status");
const MAPS = ["height", "slope", "roughness", "albedo"];
let site = null;

function query() {
  const value = (id) => document.getElementById(id).value;
  return new URLSearchParams({ lat: value("lat"), lon: value("lon"), radius_km: value("radius"),
    baseline_m: value("baseline"), max_slope_deg: value("max-slope"), max_relief_m: value("max-relief") });
}

function paint(canvas, nx, ny, colour) {
  canvas.width = nx;
  canvas.height = ny;
  const ctx = canvas.getContext("2d");
  const image = ctx.createImageData(nx, ny);
  for (let i = 0; i < ny; i++) {
    const row = ny - 1 - i; // line i is y_i, increasing northward: drawn bottom up
    for (let j = 0; j < nx; j++) {
      const [r, g, b, a] = colour(i * nx + j);
      const k = 4 * (row * nx + j);
      image.data[k] = r; image.data[k + 1] = g; image.data[k + 2] = b; image.data[k + 3] = a;
    }
  }
  ctx.putImageData(image, 0, 0);
}

function drawMaps() {
  const { header: h, arrays } = site;
  for (const name of MAPS) {
    const values = arrays[name];
    const [lo, hi] = range(values);
    paint(document.getElementById(`map-${name}`), h.nx, h.ny, (k) => {
      const v = values[k];
      if (!Number.isFinite(v)) return [200, 200, 200, 255];
      const [r, g, b] = viridis((v - lo) / (hi - lo));
      return [255 * r, 255 * g, 255 * b, 255];
    });
  }
  const hazard = arrays.hazard;
  const slope = arrays.slope;
  paint(document.getElementById("map-hazard"), h.nx, h.ny, (k) =>
    hazard[k] ? (Number.isFinite(slope[k]) ? [200, 30, 30, 255] : [120, 120, 120, 255]) : [235, 240, 235, 255]);
  document.getElementById("hazard-caption").textContent =
    `hazard (red): slope over ${h.baseline_m} m above ${h.thresholds.max_slope_deg} deg or more than ${h.thresholds.max_relief_m} m ` +
    `above the plane over ${h.baseline_m} m; grey: unknown. ${(100 * h.hazard_fraction).toFixed(1)}% of the site`;
  const body = document.querySelector("#site-stats tbody");
  body.replaceChildren();
  const units = { height: "m", slope: "deg", roughness: "m", albedo: "", relief: "m" };
  for (const [name, extent] of Object.entries(h.statistics)) {
    const row = tableRow([`${name}${units[name] ? ` (${units[name]})` : ""}`, fmt(extent.min, 4), fmt(extent.mean, 4), fmt(extent.max, 4)], [1, 2, 3]);
    row.dataset.name = name;
    body.append(row);
  }
}

function sample(x, y) {
  // bilinear height (m) at grid coordinates (sample x, line y); NaN outside or beside a gap
  const { header: h, arrays } = site;
  const j = Math.floor(x), i = Math.floor(y);
  if (j < 0 || i < 0 || j >= h.nx - 1 || i >= h.ny - 1) return NaN;
  const fx = x - j, fy = y - i, z = arrays.height, n = h.nx;
  return (1 - fy) * ((1 - fx) * z[i * n + j] + fx * z[i * n + j + 1]) + fy * ((1 - fx) * z[(i + 1) * n + j] + fx * z[(i + 1) * n + j + 1]);
}

function profile(from, to) {
  const { header: h } = site;
  const canvas = document.getElementById("profile");
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const n = 300;
  const length = Math.hypot(to[0] - from[0], to[1] - from[1]) * h.spacing_m;
  const points = [];
  for (let k = 0; k <= n; k++) {
    const t = k / n;
    points.push([t * length, sample(from[0] + t * (to[0] - from[0]), from[1] + t * (to[1] - from[1]))]);
  }
  const heights = points.map((p) => p[1]).filter(Number.isFinite);
  if (!heights.length || length === 0) { document.getElementById("profile-info").textContent = "the line meets no data"; return; }
  const lo = Math.min(...heights), hi = Math.max(...heights) + 1e-9;
  const m = 40;
  ctx.strokeStyle = "#1d2a3a";
  ctx.beginPath();
  let pen = false;
  for (const [d, z] of points) {
    if (!Number.isFinite(z)) { pen = false; continue; }
    const px = m + (d / length) * (canvas.width - 2 * m);
    const py = canvas.height - m - ((z - lo) / (hi - lo)) * (canvas.height - 2 * m);
    if (pen) ctx.lineTo(px, py); else ctx.moveTo(px, py);
    pen = true;
  }
  ctx.stroke();
  ctx.fillStyle = "#1d232a";
  ctx.fillText(`${fmt(hi, 4)} m`, 2, m);
  ctx.fillText(`${fmt(lo, 4)} m`, 2, canvas.height - m);
  ctx.fillText(`${fmt(length, 4)} m along the line`, canvas.width - m - 120, canvas.height - 10);
  const xy = (p) => `(${fmt(h.x0_m + p[0] * h.spacing_m, 4)}, ${fmt(h.y0_m + p[1] * h.spacing_m, 4)}) m`;
  document.getElementById("profile-info").textContent =
    `from ${xy(from)} to ${xy(to)} in the site frame: ${fmt(length, 4)} m, heights ${fmt(lo, 4)} to ${fmt(hi, 4)} m`;
  document.body.dataset.profile = "1";
}

// grid coordinates (sample, line) under a pointer on a map canvas
function gridAt(canvas, event) {
  const box = canvas.getBoundingClientRect();
  const { header: h } = site;
  return [(event.clientX - box.left) / box.width * h.nx - 0.5, (1 - (event.clientY - box.top) / box.height) * h.ny - 0.5];
}

const heightCanvas = document.getElementById("map-height");
let start = null;
heightCanvas.addEventListener("pointerdown", (e) => { if (site) start = gridAt(heightCanvas, e); });
heightCanvas.addEventListener("pointerup", (e) => {
  if (site && start) profile(start, gridAt(heightCanvas, e));
  start = null;
});

async function load() {
  const version = document.getElementById("version").value;
  status.textContent = "resampling the site…";
  status.className = "status";
  const q = query();
  site = await getDocument(`/console/api/versions/${version}/site?${q}`);
  const download = document.getElementById("download");
  download.href = `/versions/${version}/export?format=site&lat=${q.get("lat")}&lon=${q.get("lon")}&radius_km=${q.get("radius_km")}`;
  document.getElementById("title").textContent =
    `Site at ${fmt(Number(q.get("lat")), 5)}°, ${fmt(Number(q.get("lon")), 5)}° of version ${site.header.version}: ` +
    `${site.header.nx} x ${site.header.ny} nodes, ${fmt(site.header.spacing_m, 3)} m apart`;
  drawMaps();
  // a first profile, west to east through the centre
  const mid = (site.header.ny - 1) / 2;
  profile([0, mid], [site.header.nx - 1, mid]);
  status.textContent = "";
  document.body.dataset.ready = "1";
}

async function startPage() {
  const p = params();
  const page = await getJSON("/versions?limit=1000");
  const select = document.getElementById("version");
  for (const v of page.items) select.append(new Option(`v${v.version} (${v.kind})`, v.version));
  if (p.get("v")) select.value = p.get("v");
  for (const [id, key] of [["lat", "lat"], ["lon", "lon"], ["radius", "radius_km"]]) {
    if (p.get(key)) document.getElementById(id).value = p.get(key);
  }
  if (!p.get("lat") || !p.get("lon")) {
    // by default, the middle of the refined maplets (all maplets when none is refined)
    const maplets = await getJSON("/console/api/coverage");
    const refined = maplets.filter((m) => m.current_revision !== null);
    const chosen = refined.length ? refined : maplets;
    if (chosen.length) {
      const mean = (f) => chosen.reduce((s, m) => s + f(m), 0) / chosen.length;
      const lon0 = chosen[0].center_lon_deg;
      document.getElementById("lat").value = mean((m) => m.center_lat_deg).toFixed(5);
      document.getElementById("lon").value = (lon0 + mean((m) => ((((m.center_lon_deg - lon0) % 360) + 540) % 360) - 180)).toFixed(5);
    }
  }
  document.getElementById("load").addEventListener("click", () => load().catch((error) => showError(status, error)));
  if (page.items.length && document.getElementById("lat").value) await load();
  else status.textContent = "no version or maplet to take a site from";
}

startPage().catch((error) => showError(status, error));

// A site: height, slope, roughness, albedo and height uncertainty at the finest level there and the hazard map
// (slopes above a threshold, boulders standing above the local plane), from one binary
// document the server makes (service/console/documents.py); a profile along a line drawn on
// the height map; the site terrain product to download. Each map has axes in metres of the
// site frame (x east, y north of the regional normal's plane), a colour bar, a scale bar, a
// north arrow (the body's spin axis in the map, from the server) and the outline of where the
// version holds refined maplets at the finest level there; without any, a warning instead of
// maps of the coarse model.
import { fmt, getDocument, getJSON, header, params, range, showError, tableRow, viridis } from "/console/common.js";
import { axes, classBar, colourBar, northArrow, scaleBar, svg, tickText, ticks, withUnit } from "/console/maps.js";

header();
const status = document.getElementById("status");
const MAPS = [
  ["height", "height", "m", "along the regional normal; drag a line for a profile"],
  ["slope", "slope", "deg", "from the regional normal, of the plane over the baseline"],
  ["roughness", "roughness", "m", "RMS about the plane over the baseline"],
  ["albedo", "albedo", "", ""],
  ["sigma", "height uncertainty", "m", "1 sigma, from how the images agree with the refined shape"],
];
const STOPS = Array.from({ length: 9 }, (_, k) => viridis(k / 8).map((c) => Math.round(255 * c)));
const UNKNOWN = [200, 200, 200];
const HAZARD = [200, 30, 30], SAFE = [235, 240, 235];
const PLOT = 300; // the map's longer side on screen (px)
const MARGIN = { left: 58, top: 8, right: 10, bottom: 40 };
let site = null;

function query() {
  const value = (id) => document.getElementById(id).value;
  return new URLSearchParams({ lat: value("lat"), lon: value("lon"), radius_km: value("radius"),
    baseline_m: value("baseline"), max_slope_deg: value("max-slope"), max_relief_m: value("max-relief") });
}

// The grid as an image (a data URL): line i is y_i, increasing northward, so drawn bottom up.
function pixels(nx, ny, colour) {
  const canvas = document.createElement("canvas");
  canvas.width = nx;
  canvas.height = ny;
  const ctx = canvas.getContext("2d");
  const image = ctx.createImageData(nx, ny);
  for (let i = 0; i < ny; i++) {
    const row = ny - 1 - i;
    for (let j = 0; j < nx; j++) {
      const [r, g, b] = colour(i * nx + j);
      const k = 4 * (row * nx + j);
      image.data[k] = r; image.data[k + 1] = g; image.data[k + 2] = b; image.data[k + 3] = 255;
    }
  }
  ctx.putImageData(image, 0, 0);
  return canvas.toDataURL();
}

// The plot box, and the map's extent in metres: each node's cell, centred on it.
function layout() {
  const { header: h } = site;
  const s = h.spacing_m;
  const extent = { x0: h.x0_m - s / 2, x1: h.x0_m + (h.nx - 0.5) * s, y0: h.y0_m - s / 2, y1: h.y0_m + (h.ny - 0.5) * s };
  const across = Math.max(h.nx, h.ny);
  const box = { left: MARGIN.left, top: MARGIN.top, width: (PLOT * h.nx) / across, height: (PLOT * h.ny) / across };
  return { box, extent, metresPerPx: (extent.x1 - extent.x0) / box.width };
}

// The outline of the fine-data mask: the cell edges between a fine node and a coarse one.
function fineOutline(box) {
  const { header: h, arrays } = site;
  const fine = arrays.fine;
  const cw = box.width / h.nx, ch = box.height / h.ny;
  const at = (i, j) => i >= 0 && j >= 0 && i < h.ny && j < h.nx && fine[i * h.nx + j] === 1;
  const parts = [];
  for (let i = 0; i < h.ny; i++) {
    for (let j = 0; j < h.nx; j++) {
      if (!at(i, j)) continue;
      const x = box.left + j * cw, y = box.top + box.height - (i + 1) * ch; // top-left of the cell
      if (!at(i + 1, j)) parts.push(`M${x} ${y}h${cw}`);
      if (!at(i - 1, j)) parts.push(`M${x} ${y + ch}h${cw}`);
      if (!at(i, j - 1)) parts.push(`M${x} ${y}v${ch}`);
      if (!at(i, j + 1)) parts.push(`M${x + cw} ${y}v${ch}`);
    }
  }
  return svg("path", { d: parts.join(""), class: "fine-outline", "data-role": "fine-outline" });
}

// One map: the image, its axes, the fine data's outline, a scale bar and a north arrow; a
// colour bar and a caption under it.
function mapFigure(name, image, bar, caption) {
  const { header: h } = site;
  const { box, extent, metresPerPx } = layout();
  const figure = document.createElement("figure");
  figure.dataset.map = name;
  const plot = svg("svg", { width: box.left + box.width + MARGIN.right, height: box.top + box.height + MARGIN.bottom,
    class: "map", id: `map-${name}` });
  const picture = svg("image", { href: image, x: box.left, y: box.top, width: box.width, height: box.height,
    preserveAspectRatio: "none", class: "pixels" });
  plot.append(picture, axes(box, { ...extent, xLabel: "x east (m, site frame)", yLabel: "y north (m)" }));
  if (h.fine.fraction > 0 && h.fine.fraction < 1) plot.append(fineOutline(box));
  plot.append(scaleBar(box.left + 10, box.top + box.height - 10, metresPerPx, box.width / 3),
    northArrow(box.left + box.width - 24, box.top + 24, h.north));
  figure.append(plot, bar);
  const text = document.createElement("figcaption");
  text.textContent = caption;
  figure.append(text);
  return { figure, picture };
}

function drawMaps() {
  const { header: h, arrays } = site;
  const holder = document.getElementById("maps");
  holder.replaceChildren();
  let heightPicture = null;
  for (const [name, label, unit, note] of MAPS) {
    const values = arrays[name];
    const finite = values.some(Number.isFinite);
    const [lo, hi] = range(values);
    const image = pixels(h.nx, h.ny, (k) => {
      const v = values[k];
      return Number.isFinite(v) ? viridis((v - lo) / (hi - lo)).map((c) => 255 * c) : UNKNOWN;
    });
    const bar = colourBar({ label, unit, lo: finite ? lo : null, hi: finite ? hi : null, stops: STOPS,
      note: finite ? "2nd to 98th percentile; grey: no data" : "no data: grey" });
    const { figure, picture } = mapFigure(name, image, bar, `${withUnit(label, unit)}${note ? `: ${note}` : ""}`);
    holder.append(figure);
    if (name === "height") heightPicture = picture;
  }
  const hazard = arrays.hazard;
  const slope = arrays.slope;
  const image = pixels(h.nx, h.ny, (k) => (hazard[k] ? (Number.isFinite(slope[k]) ? HAZARD : UNKNOWN) : SAFE));
  const t = h.thresholds;
  const bar = classBar({ label: `hazard: slope > ${t.max_slope_deg} deg or relief > ${t.max_relief_m} m`,
    classes: [["hazard", HAZARD], ["safe", SAFE], ["no data", UNKNOWN]] });
  holder.append(mapFigure("hazard", image, bar,
    `hazard: slope over ${h.baseline_m} m above ${t.max_slope_deg} deg or more than ${t.max_relief_m} m ` +
    `above the plane over ${h.baseline_m} m; ${(100 * h.hazard_fraction).toFixed(1)}% of the site`).figure);
  const body = document.querySelector("#site-stats tbody");
  body.replaceChildren();
  const units = { height: "m", slope: "deg", roughness: "m", albedo: "", relief: "m", sigma: "m" };
  for (const [name, extent] of Object.entries(h.statistics)) {
    const row = tableRow([withUnit(name, units[name]), fmt(extent.min, 4), fmt(extent.mean, 4), fmt(extent.max, 4)], [1, 2, 3]);
    row.dataset.name = name;
    body.append(row);
  }
  listenForProfiles(heightPicture);
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
  const holder = document.getElementById("profile");
  const info = document.getElementById("profile-info");
  const n = 300;
  const length = Math.hypot(to[0] - from[0], to[1] - from[1]) * h.spacing_m;
  const points = [];
  for (let k = 0; k <= n; k++) {
    const t = k / n;
    points.push([t * length, sample(from[0] + t * (to[0] - from[0]), from[1] + t * (to[1] - from[1]))]);
  }
  const heights = points.map((p) => p[1]).filter(Number.isFinite);
  if (!heights.length || length === 0) { holder.replaceChildren(); info.textContent = "the line meets no data"; return; }
  let lo = Math.min(...heights), hi = Math.max(...heights);
  // at least a few spacings of relief shown, so that a flat line is not blown up to noise
  const least = Math.max(h.spacing_m, 0.01);
  if (hi - lo < least) { const mid = (hi + lo) / 2; lo = mid - least / 2; hi = mid + least / 2; }
  const box = { left: 64, top: 10, width: 640, height: 180 };
  const plot = svg("svg", { width: 720, height: 240, class: "profile", "data-role": "profile" });
  plot.append(axes(box, { x0: 0, x1: length, y0: lo, y1: hi, xLabel: "distance along the line (m)",
    yLabel: "height (m)", count: 6 }));
  let d = "", pen = false;
  for (const [s, z] of points) {
    if (!Number.isFinite(z)) { pen = false; continue; }
    const px = box.left + (s / length) * box.width;
    const py = box.top + box.height - ((z - lo) / (hi - lo)) * box.height;
    d += `${pen ? "L" : "M"}${px.toFixed(1)} ${py.toFixed(1)}`;
    pen = true;
  }
  plot.append(svg("path", { d, class: "line" }));
  holder.replaceChildren(plot);
  const step = ticks(0, length, 6).step;
  const xy = (p) => `(${tickText(h.x0_m + p[0] * h.spacing_m, step)}, ${tickText(h.y0_m + p[1] * h.spacing_m, step)}) m`;
  const hs = ticks(lo, hi, 6).step;
  info.textContent = `from ${xy(from)} to ${xy(to)} in the site frame (the orange line on the height map): ${tickText(length, step)} m long, ` +
    `heights ${tickText(Math.min(...heights), hs / 10)} to ${tickText(Math.max(...heights), hs / 10)} m`;
  // the line on the height map
  const map = document.getElementById("map-height");
  map.querySelector(".profile-line")?.remove();
  const { box: mapBox, extent } = layout();
  const at = (p) => [mapBox.left + ((h.x0_m + p[0] * h.spacing_m - extent.x0) / (extent.x1 - extent.x0)) * mapBox.width,
    mapBox.top + mapBox.height - ((h.y0_m + p[1] * h.spacing_m - extent.y0) / (extent.y1 - extent.y0)) * mapBox.height];
  const [x1, y1] = at(from), [x2, y2] = at(to);
  map.append(svg("line", { x1, y1, x2, y2, class: "profile-line" }));
  document.body.dataset.profile = "1";
}

// grid coordinates (sample, line) under a pointer on the height map's image
function gridAt(picture, event) {
  const box = picture.getBoundingClientRect();
  const { header: h } = site;
  return [(event.clientX - box.left) / box.width * h.nx - 0.5, (1 - (event.clientY - box.top) / box.height) * h.ny - 0.5];
}

function listenForProfiles(picture) {
  let start = null;
  picture.addEventListener("pointerdown", (e) => { e.preventDefault(); start = gridAt(picture, e); });
  picture.addEventListener("pointerup", (e) => {
    if (start) profile(start, gridAt(picture, e));
    start = null;
  });
}

// Where the version has refined maplets over the site: a note, or a warning in place of maps
// of the coarse model.
function showFine() {
  const { header: h } = site;
  const fine = h.fine;
  const warning = document.getElementById("coarse-warning");
  const note = document.getElementById("fine-note");
  const bodyOfSite = document.getElementById("site-body");
  if (fine.fraction > 0) {
    warning.hidden = true;
    bodyOfSite.hidden = false;
    note.hidden = false;
    note.textContent = `Refined data: maplet level ${fine.level} (GSD ${fmt(fine.gsd_m, 3)} m; ${fine.maplets.join(", ")}) ` +
      (fine.fraction < 1 ? `covers ${(100 * fine.fraction).toFixed(fine.fraction < 0.1 ? 1 : 0)}% of the site, inside the dashed pink outline; ` +
        "outside it the maps show the coarser model." : "covers the whole site.");
    return;
  }
  note.hidden = true;
  document.getElementById("coarse-text").textContent =
    `Version ${h.version} was fused from no maplet over this site: the maps would show the coarse model ` +
    `resampled on ${h.nx} x ${h.ny} nodes ${fmt(h.spacing_m, 3)} m apart, not a site terrain model.`;
  warning.hidden = false;
  bodyOfSite.hidden = true;
}

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
  showFine();
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
  document.getElementById("show-coarse").addEventListener("click", () => { document.getElementById("site-body").hidden = false; });
  if (page.items.length && document.getElementById("lat").value) await load();
  else status.textContent = "no version or maplet to take a site from";
}

startPage().catch((error) => showError(status, error));

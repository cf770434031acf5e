// Coverage: every maplet on a longitude-latitude map coloured by images per maplet, w_PWM,
// five-view completeness or incidence spread, where a planner sees where more images are
// needed; the table holds the same numbers, with a re-queue control per maplet (a changing
// call: refused without the token).
import { fmt, getJSON, header, params, requeueControl, showError, tableRow, viridis } from "/console/common.js";

header();
let maplets = [];
const METRICS = {
  image_count: { label: "images per maplet", value: (m) => m.image_count },
  region_weight: { label: "w_PWM", value: (m) => m.region_weight },
  five_views: { label: "five views filled (of 5)", value: (m) => m.roles_filled, range: [0, 5] },
  incidence_spread: { label: "incidence spread of the used images (deg)",
    value: (m) => (m.incidence_max_deg === null ? NaN : m.incidence_max_deg - m.incidence_min_deg) },
};

function drawMap() {
  const canvas = document.getElementById("map");
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  if (!maplets.length) { ctx.fillText("no maplets in the catalog", 20, 20); return; }
  const metric = METRICS[document.getElementById("metric").value];
  const values = maplets.map(metric.value);
  const finite = values.filter(Number.isFinite);
  const [lo, hi] = metric.range ?? [Math.min(...finite, 0), Math.max(...finite, 1)];
  const lats = maplets.map((m) => m.center_lat_deg);
  // longitudes unwrapped about the first maplet so that a region across 0/360 stays together
  const lon0 = maplets[0].center_lon_deg;
  const lons = maplets.map((m) => lon0 + ((((m.center_lon_deg - lon0) % 360) + 540) % 360) - 180);
  const pad = 0.05 * Math.max(Math.max(...lons) - Math.min(...lons), Math.max(...lats) - Math.min(...lats)) + 0.5;
  const box = [Math.min(...lons) - pad, Math.max(...lons) + pad, Math.min(...lats) - pad, Math.max(...lats) + pad];
  const margin = 45;
  const sx = (canvas.width - 2 * margin) / (box[1] - box[0]);
  const sy = (canvas.height - 2 * margin) / (box[3] - box[2]);
  const s = Math.min(sx, sy);
  const x = (lon) => margin + (lon - box[0]) * s;
  const y = (lat) => canvas.height - margin - (lat - box[2]) * s;
  maplets.forEach((m, k) => {
    const v = values[k];
    const [r, g, b] = Number.isFinite(v) ? viridis((v - lo) / (hi - lo || 1)) : [0.7, 0.7, 0.7];
    ctx.fillStyle = `rgb(${255 * r}, ${255 * g}, ${255 * b})`;
    // the catalog holds a maplet's side in km, not in degrees: a square of fixed size
    const size = Math.max(6, Math.min(28, s * 1.2));
    ctx.fillRect(x(lons[k]) - size / 2, y(lats[k]) - size / 2, size, size);
  });
  ctx.fillStyle = "#1d232a";
  ctx.font = "12px system-ui";
  ctx.fillText(`east longitude ${fmt(box[0])} to ${fmt(box[1])} deg`, margin, canvas.height - 12);
  ctx.save();
  ctx.translate(14, canvas.height - margin);
  ctx.rotate(-Math.PI / 2);
  ctx.fillText(`latitude ${fmt(box[2])} to ${fmt(box[3])} deg`, 0, 0);
  ctx.restore();
  document.getElementById("legend").textContent =
    `${metric.label}: ${fmt(lo)} (dark) to ${fmt(hi)} (bright); grey: none. ${maplets.length} maplets.`;
}

function fillTable() {
  const body = document.querySelector("#maplets tbody");
  body.replaceChildren();
  for (const m of maplets) {
    const control = requeueControl(m.id);
    const incidence = m.incidence_min_deg === null ? "—" : `${m.incidence_min_deg.toFixed(1)}–${m.incidence_max_deg.toFixed(1)}`;
    const row = tableRow([m.name, m.image_count, m.used_count, m.region_weight.toFixed(3),
      m.five_views ? "yes" : `no (${m.roles_filled}/5)`, incidence, m.current_revision ?? "—", control], [1, 2, 3, 6]);
    row.dataset.maplet = m.id;
    body.append(row);
  }
}

async function load() {
  // ?lat=&lon=&radius_km=: the maplets of a site only
  const site = new URLSearchParams([...params()].filter(([k]) => ["lat", "lon", "radius_km"].includes(k)));
  maplets = await getJSON(`/console/api/coverage?${site}`);
  drawMap();
  fillTable();
  document.body.dataset.ready = "1";
}

document.getElementById("metric").addEventListener("change", drawMap);
load().catch((error) => showError("status", error));

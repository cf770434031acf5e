// Coverage: every maplet on a longitude-latitude map, each drawn at its true extent (its
// square's corners, from the server) and coloured by images per maplet, w_PWM, five-view
// completeness or incidence spread, where a planner sees where more images are needed; axes in
// degrees, a colour bar, a scale bar (km, at the map's middle latitude) and a north arrow. The
// table holds the same numbers, with a re-queue control per maplet (a changing call: refused
// without the token).
import { fmt, getJSON, header, params, requeueControl, showError, tableRow, viridis } from "/console/common.js";
import { axes, colourBar, northArrow, scaleBar, svg } from "/console/maps.js";

header();
let maplets = [];
const METRICS = {
  image_count: { label: "images per maplet", unit: "count", value: (m) => m.image_count },
  region_weight: { label: "w_PWM (region weight)", unit: "", value: (m) => m.region_weight },
  five_views: { label: "five views filled", unit: "of 5", value: (m) => m.roles_filled, range: [0, 5] },
  incidence_spread: { label: "incidence spread of the used images", unit: "deg",
    value: (m) => (m.incidence_max_deg === null ? NaN : m.incidence_max_deg - m.incidence_min_deg) },
};
const STOPS = Array.from({ length: 9 }, (_, k) => viridis(k / 8).map((c) => Math.round(255 * c)));
const WIDTH = 720, HEIGHT = 480;
const MARGIN = { left: 62, top: 10, right: 12, bottom: 44 };

// A longitude unwrapped about lon0, so that a region across 0/360 stays together.
const unwrap = (lon, lon0) => lon0 + ((((lon - lon0) % 360) + 540) % 360) - 180;

function drawMap() {
  const holder = document.getElementById("map-holder");
  const plot = svg("svg", { width: WIDTH, height: HEIGHT, id: "map", class: "map" });
  holder.replaceChildren(plot);
  if (!maplets.length) {
    plot.append(svg("text", { x: 20, y: 30 }, "no maplets in the catalog"));
    return;
  }
  const metric = METRICS[document.getElementById("metric").value];
  const values = maplets.map(metric.value);
  const finite = values.filter(Number.isFinite);
  const [lo, hi] = metric.range ?? [Math.min(...finite, 0), Math.max(...finite, 1)];
  const lon0 = maplets[0].center_lon_deg;
  const corners = maplets.map((m) => m.outline.map(([lat, lon]) => [unwrap(lon, lon0), lat]));
  const lons = corners.flat().map((c) => c[0]), lats = corners.flat().map((c) => c[1]);
  const span = Math.max(Math.max(...lons) - Math.min(...lons), Math.max(...lats) - Math.min(...lats));
  const pad = 0.05 * span + 0.01;
  let box = [Math.min(...lons) - pad, Math.max(...lons) + pad, Math.min(...lats) - pad, Math.max(...lats) + pad];
  // equal distances alike on both axes at the middle latitude: a degree of longitude is
  // cos(latitude) of a degree of latitude there
  const mid = (box[2] + box[3]) / 2;
  const squeeze = Math.max(Math.cos((mid * Math.PI) / 180), 0.05);
  const area = { left: MARGIN.left, top: MARGIN.top, width: WIDTH - MARGIN.left - MARGIN.right, height: HEIGHT - MARGIN.top - MARGIN.bottom };
  const s = Math.min(area.width / ((box[1] - box[0]) * squeeze), area.height / (box[3] - box[2]));
  // widen the shorter range to fill the plot, so the axes match the drawing
  const wideLon = area.width / (s * squeeze), tallLat = area.height / s;
  const cLon = (box[0] + box[1]) / 2, cLat = (box[2] + box[3]) / 2;
  box = [cLon - wideLon / 2, cLon + wideLon / 2, cLat - tallLat / 2, cLat + tallLat / 2];
  const x = (lon) => area.left + (lon - box[0]) * s * squeeze;
  const y = (lat) => area.top + area.height - (lat - box[2]) * s;
  const cells = svg("g", { "data-role": "cells" });
  maplets.forEach((m, k) => {
    const v = values[k];
    const [r, g, b] = Number.isFinite(v) ? viridis((v - lo) / (hi - lo || 1)) : [0.7, 0.7, 0.7];
    const cell = svg("polygon", { points: corners[k].map(([lon, lat]) => `${x(lon).toFixed(1)},${y(lat).toFixed(1)}`).join(" "),
      fill: `rgb(${Math.round(255 * r)},${Math.round(255 * g)},${Math.round(255 * b)})`, "fill-opacity": 0.85,
      stroke: "#1d232a", "stroke-width": 0.3, "data-maplet": m.id });
    cell.append(svg("title", {}, `${m.name}: ${fmt(v)} ${metric.unit}`));
    cells.append(cell);
  });
  const radiusKm = maplets.reduce((sum, m) => sum + m.radius_km, 0) / maplets.length;
  const metresPerPx = ((radiusKm * 1000 * Math.PI) / 180) / s; // along a meridian
  plot.append(cells, axes(area, { x0: box[0], x1: box[1], y0: box[2], y1: box[3],
    xLabel: "east longitude (deg)", yLabel: "latitude (deg)" }),
  scaleBar(area.left + 12, area.top + area.height - 12, metresPerPx, area.width / 4),
  northArrow(area.left + area.width - 26, area.top + 26, [0, 1]));
  document.getElementById("colour-bar").replaceChildren(colourBar({ label: metric.label, unit: metric.unit, lo, hi,
    stops: STOPS, width: 420, note: "grey: none" }));
  document.getElementById("legend").textContent =
    `${maplets.length} maplets, each drawn over its square. Scale at ${fmt(mid, 3)}° latitude, ` +
    `${fmt(radiusKm, 3)} km from the centre.`;
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

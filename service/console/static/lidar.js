// Lidar: how far the catalog's lidar spots lie from a version, on a longitude-latitude map of
// the whole body: the version's RMS map (10-degree cells, faint) with each track drawn over it
// as the footprint of the cone holding its spots, outlined in the colour of its RMS on that
// version; one colour bar (m), axes in degrees, a scale bar (at the equator, the version's mean
// radius) and a north arrow. The table holds each track's strip correction, its 1 sigma and its
// RMS on this version, and its crossovers with other tracks (count, height RMS) as last measured.
// Everything comes from GET /versions/{v}, /versions/{v}/lidar and /lidar/tracks.
import { fmt, getJSON, header, params, showError, tableRow, viridis } from "/console/common.js";
import { axes, colourBar, northArrow, scaleBar, svg } from "/console/maps.js";

header();
const STOPS = Array.from({ length: 9 }, (_, k) => viridis(k / 8).map((c) => Math.round(255 * c)));
const WIDTH = 720, HEIGHT = 420;
const MARGIN = { left: 62, top: 10, right: 12, bottom: 44 };
const metres = (km) => (km === null || km === undefined ? NaN : km * 1000);
const colour = (t) => `rgb(${viridis(t).map((c) => Math.round(255 * c)).join(",")})`;

async function allTracks() {
  const tracks = [];
  for (let offset = 0; ; offset += 1000) {
    const page = await getJSON(`/lidar/tracks?limit=1000&offset=${offset}`);
    tracks.push(...page.items);
    if (tracks.length >= page.total || !page.items.length) return tracks;
  }
}

function drawMap(version, residuals, tracks) {
  const holder = document.getElementById("map-holder");
  const plot = svg("svg", { width: WIDTH, height: HEIGHT, id: "map", class: "map" });
  holder.replaceChildren(plot);
  const area = { left: MARGIN.left, top: MARGIN.top, width: WIDTH - MARGIN.left - MARGIN.right,
    height: HEIGHT - MARGIN.top - MARGIN.bottom };
  // equal degrees alike on both axes (plate carree), centred in the plot
  const s = Math.min(area.width / 360, area.height / 180);
  const x0 = area.left + (area.width - 360 * s) / 2, y0 = area.top + (area.height - 180 * s) / 2;
  const box = { left: x0, top: y0, width: 360 * s, height: 180 * s };
  const x = (lon) => x0 + (((lon % 360) + 360) % 360) * s;
  const y = (lat) => y0 + (90 - lat) * s;
  const grid = residuals.map;
  const trackRms = (t) => metres(residuals.tracks[t.id]?.rms_km);
  const values = [...grid.rms_km.flat().map(metres), ...tracks.map(trackRms)].filter(Number.isFinite);
  const hi = Math.max(...values, 1e-3);
  const cells = svg("g", { "data-role": "cells" });
  const dLon = 360 / grid.lon_cells, dLat = 180 / grid.lat_cells;
  grid.rms_km.forEach((row, r) => row.forEach((value, c) => {
    if (value === null) return;
    const cell = svg("rect", { x: x(c * dLon), y: y(-90 + (r + 1) * dLat), width: dLon * s, height: dLat * s,
      fill: colour(metres(value) / hi), "fill-opacity": 0.45 });
    cell.append(svg("title", {}, `${fmt(metres(value))} m RMS`));
    cells.append(cell);
  }));
  // the tracks clipped to the map, a cone across longitude 0/360 drawn on both sides
  const clip = svg("clipPath", { id: "lidar-map-clip" });
  clip.append(svg("rect", { x: box.left, y: box.top, width: box.width, height: box.height }));
  const defs = svg("defs");
  defs.append(clip);
  const drawn = svg("g", { "data-role": "tracks", "clip-path": "url(#lidar-map-clip)" });
  for (const t of tracks) {
    const rms = trackRms(t);
    const squeeze = Math.max(Math.cos((t.axis_lat_deg * Math.PI) / 180), 0.05);
    for (const wrap of [-360, 0, 360]) {
      const outline = svg("ellipse", { cx: x(t.axis_lon_deg) + wrap * s, cy: y(t.axis_lat_deg),
        rx: Math.min((t.cone_half_angle_deg / squeeze) * s, 180 * s), ry: t.cone_half_angle_deg * s,
        fill: "none", stroke: Number.isFinite(rms) ? colour(rms / hi) : "#9aa0a6", "stroke-width": 2.5,
        "data-track": t.id, "data-rms-m": Number.isFinite(rms) ? rms.toFixed(4) : "" });
      outline.append(svg("title", {}, `track ${t.id} (${t.product} #${t.track}): ${fmt(rms)} m RMS`));
      drawn.append(outline);
    }
  }
  const radiusKm = version.statistics.mean_radius_km;
  plot.append(defs, cells, drawn, axes(box, { x0: 0, x1: 360, y0: -90, y1: 90, xLabel: "east longitude (deg)",
    yLabel: "latitude (deg)" }), northArrow(box.left + box.width - 26, box.top + 26, [0, 1]));
  if (radiusKm) {
    plot.append(scaleBar(box.left + 12, box.top + box.height - 12, (radiusKm * 1000 * Math.PI) / 180 / s, box.width / 4));
  }
  document.getElementById("colour-bar").replaceChildren(colourBar({ label: "lidar residual RMS", unit: "m", lo: 0, hi,
    stops: STOPS, width: 420, note: "cells: RMS per 10°; outlines: each track's cone; grey: none" }));
  document.getElementById("legend").textContent = `${tracks.length} tracks over version ${version.version}. ` +
    (radiusKm ? `Scale at the equator, ${fmt(radiusKm, 3)} km from the centre.` : "");
}

function fillTable(residuals, tracks) {
  const body = document.querySelector("#tracks tbody");
  body.replaceChildren();
  for (const t of tracks) {
    const c = t.correction;
    const shift = c ? Math.hypot(...c.translation_km) * 1000 : NaN;
    const sigma = c && c.sigma.slice(3).every((v) => v !== null) ? Math.hypot(...c.sigma.slice(3)) * 1000 : NaN;
    const off = residuals.tracks[t.id]?.disagreement_sigmas;
    const row = tableRow([t.id, `${t.product} #${t.track}`, t.shots, c ? fmt(shift) : "—", fmt(sigma),
      fmt(metres(residuals.tracks[t.id]?.rms_km)), t.crossovers ?? "—", fmt(metres(t.crossover_rms_km)),
      off == null ? "—" : off.toFixed(1)],
    [0, 2, 3, 4, 5, 6, 7, 8]);
    row.dataset.track = t.id;
    // a track that disagrees with the version beyond its sigmas is flagged, not averaged in
    if ((residuals.disagreeing_tracks ?? []).includes(t.id)) row.classList.add("disagrees");
    body.append(row);
  }
}

async function show(number) {
  const version = await getJSON(`/versions/${number}`);
  document.body.dataset.version = version.version;
  // a version published before the catalog had lidar carries no figures: asked for, they would be
  // a 404, which the browser logs as an error of the page
  if (!version.statistics.lidar) {
    document.getElementById("summary").textContent = `version ${version.version} was not checked against ` +
      "the lidar: the catalog had no usable shot when it was published";
    document.getElementById("map-holder").replaceChildren();
    document.getElementById("colour-bar").replaceChildren();
    document.querySelector("#tracks tbody").replaceChildren();
    return;
  }
  const residuals = await getJSON(`/versions/${number}/lidar`);
  const tracks = await allTracks();
  document.getElementById("summary").textContent = `version ${version.version} (${version.kind}): ` +
    `${residuals.measured} of ${residuals.shots} sampled spots measured (${residuals.usable_shots} usable in ` +
    `${residuals.products} products); mean ${fmt(metres(residuals.mean_km))} m, RMS ${fmt(metres(residuals.rms_km))} m, ` +
    `95th percentile ${fmt(metres(residuals.p95_km))} m`;
  drawMap(version, residuals, tracks);
  fillTable(residuals, tracks);
}

async function load() {
  const page = await getJSON("/versions?limit=1000");
  const select = document.getElementById("version");
  for (const v of page.items) select.append(new Option(`v${v.version} (${v.kind})`, v.version));
  const wanted = Number(params().get("v")) || (page.items[0] && page.items[0].version);
  if (wanted) {
    select.value = wanted;
    await show(wanted);
  }
  select.addEventListener("change", () => show(select.value).catch((error) => showError("status", error)));
  document.body.dataset.ready = "1";
}

load().catch((error) => showError("status", error));

// The height difference of one version from another: the API's figures (/diffs/old/new), named
// with their units (labels.js), and its map over latitude and longitude
// (/diffs/old/new/map.png, made once on the server, with its colour bar and axes), with north
// (up: the map's y is latitude) and its scale along a meridian at the new version's mean radius.
import { fmt, getJSON, header, params, showError, tableRow } from "/console/common.js";
import { statistic } from "/console/labels.js";
import { northArrow, svg } from "/console/maps.js";

header();
const status = document.getElementById("status");

async function compare() {
  const old = document.getElementById("old").value;
  const new_ = document.getElementById("new").value;
  status.textContent = "comparing…";
  status.className = "status";
  const figures = await getJSON(`/diffs/${old}/${new_}`);
  const body = document.querySelector("#figures tbody");
  body.replaceChildren();
  for (const [name, value] of Object.entries(figures)) {
    if (name === "png") continue;
    const row = tableRow(statistic(name, value), [1]);
    row.dataset.name = name;
    body.append(row);
  }
  const radiusKm = (await getJSON(`/versions/${new_}`)).statistics.mean_radius_km;
  const key = svg("svg", { width: 420, height: 44, id: "map-key" });
  key.append(northArrow(22, 22, [0, 1]), svg("text", { x: 48, y: 18 }, "north is up: the map's y axis is latitude"));
  if (radiusKm) {
    key.append(svg("text", { x: 48, y: 34, "data-role": "scale" },
      `scale: 1° of latitude = ${fmt((radiusKm * 1000 * Math.PI) / 180, 3)} m (mean radius ${fmt(radiusKm, 4)} km)`));
  }
  document.getElementById("map-key").replaceWith(key);
  const map = document.getElementById("map");
  await new Promise((resolve, reject) => {
    map.onload = resolve;
    map.onerror = () => reject(new Error("the difference map did not load"));
    map.src = `/diffs/${old}/${new_}/map.png`;
  });
  map.hidden = false;
  status.textContent = "";
  document.body.dataset.ready = "1";
}

async function start() {
  const page = await getJSON("/versions?limit=1000");
  const versions = page.items;
  for (const id of ["old", "new"]) {
    const select = document.getElementById(id);
    for (const v of versions) select.append(new Option(`v${v.version} (${v.kind})`, v.version));
  }
  const p = params();
  const newest = versions[0];
  document.getElementById("new").value = p.get("new") || (newest ? newest.version : "");
  document.getElementById("old").value = p.get("old") || (newest && newest.parent ? newest.parent : (versions[1] || newest || {}).version);
  document.getElementById("compare").addEventListener("click", () => compare().catch((error) => showError(status, error)));
  if (versions.length >= 1) await compare();
  else status.textContent = "no versions in the catalog";
}

start().catch((error) => showError(status, error));

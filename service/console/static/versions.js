// Versions: the list, the lineage as a graph (parent -> child, labels under the nodes, clear of
// the edges), one version's statistics with names and units (labels.js) and downlinks, and the
// release control (a changing call: refused without the token).
import { element, getJSON, header, params, post, showError, tableRow } from "/console/common.js";
import { number, statistic } from "/console/labels.js";

header();
let versions = [];

async function load() {
  const page = await getJSON("/versions?limit=1000");
  versions = page.items;
  const body = document.querySelector("#versions tbody");
  body.replaceChildren();
  for (const v of versions) {
    const row = tableRow([v.version, v.kind, v.parent ?? "—", v.created_at.replace("T", " ").slice(0, 19),
      number(v.faces), v.released ? `released ${v.release_tag}` : "—"], [0, 4]);
    row.dataset.version = v.version;
    row.addEventListener("click", () => select(v.version));
    body.append(row);
  }
  drawLineage();
  const wanted = Number(params().get("v")) || (versions[0] && versions[0].version);
  if (wanted) await select(wanted);
  document.body.dataset.ready = "1";
}

// the lineage's layout: a column per generation, a row per version in it (px)
const COLUMN = 110, ROW = 48, RADIUS = 9;

function drawLineage(selected) {
  const svg = document.getElementById("lineage");
  svg.replaceChildren();
  const byNumber = new Map(versions.map((v) => [v.version, v]));
  // depth: generations from a root; rows: one per version at that depth, in version order
  const depth = new Map();
  const ordered = [...versions].sort((a, b) => a.version - b.version);
  for (const v of ordered) depth.set(v.version, v.parent && depth.has(v.parent) ? depth.get(v.parent) + 1 : 0);
  const rows = new Map();
  const place = new Map();
  for (const v of ordered) {
    const d = depth.get(v.version);
    const r = rows.get(d) ?? 0;
    rows.set(d, r + 1);
    place.set(v.version, [COLUMN / 2 + d * COLUMN, 20 + r * ROW]);
  }
  const width = Math.max(480, COLUMN * (1 + Math.max(0, ...depth.values())));
  const height = Math.max(70, 10 + ROW * Math.max(1, ...rows.values()));
  svg.setAttribute("width", width);
  svg.setAttribute("height", height);
  const ns = "http://www.w3.org/2000/svg";
  for (const v of ordered) {
    if (!v.parent || !place.has(v.parent)) continue;
    const [x1, y1] = place.get(v.parent);
    const [x2, y2] = place.get(v.version);
    // from circle edge to circle edge, so that the edge meets no label (labels sit under nodes)
    const length = Math.hypot(x2 - x1, y2 - y1) || 1;
    const [ux, uy] = [(x2 - x1) / length, (y2 - y1) / length];
    const line = document.createElementNS(ns, "line");
    for (const [k, value] of Object.entries({ x1: x1 + RADIUS * ux, y1: y1 + RADIUS * uy,
      x2: x2 - RADIUS * ux, y2: y2 - RADIUS * uy })) line.setAttribute(k, value);
    svg.append(line);
  }
  for (const v of ordered) {
    const [x, y] = place.get(v.version);
    const dot = document.createElementNS(ns, "circle");
    dot.setAttribute("cx", x);
    dot.setAttribute("cy", y);
    dot.setAttribute("r", RADIUS);
    dot.setAttribute("class", [v.released ? "released" : "", v.version === selected ? "selected" : ""].join(" ").trim());
    dot.dataset.version = v.version;
    dot.addEventListener("click", () => select(v.version));
    const label = document.createElementNS(ns, "text");
    label.setAttribute("x", x);
    label.setAttribute("y", y + RADIUS + 13);
    label.setAttribute("text-anchor", "middle");
    label.textContent = `v${v.version} ${byNumber.get(v.version).kind}`;
    svg.append(dot, label);
  }
}

async function select(number) {
  const v = await getJSON(`/versions/${number}`);
  document.querySelectorAll("#versions tbody tr").forEach((row) =>
    row.classList.toggle("selected", Number(row.dataset.version) === v.version));
  drawLineage(v.version);
  const panel = document.getElementById("detail");
  panel.hidden = false;
  panel.dataset.version = v.version;
  document.getElementById("detail-title").textContent =
    `Version ${v.version} (${v.kind})` + (v.released ? ` — released as ${v.release_tag}` : "");
  const links = document.getElementById("links");
  links.replaceChildren();
  const link = (href, text) => { const a = element("a", text); a.href = href; links.append(a, " · "); };
  link(`/console/view.html?v=${v.version}`, "3D view");
  if (v.parent) link(`/console/diff.html?old=${v.parent}&new=${v.version}`, `difference from v${v.parent}`);
  link(`/console/site.html?v=${v.version}`, "site maps");
  link(`/versions/${v.version}/artifacts/ply`, "PLY");
  const stats = document.querySelector("#statistics tbody");
  stats.replaceChildren();
  const shown = { ...v.statistics, ancestors: v.lineage.ancestors.join(", ") || "—",
    children: v.lineage.children.join(", ") || "—", "maplet revisions": v.lineage.maplet_revisions };
  for (const [name, value] of Object.entries(shown)) {
    const [label, text] = statistic(name, value);
    const row = tableRow([label, text], [1]);
    row.dataset.name = name;
    stats.append(row);
  }
  const downlinks = document.getElementById("downlinks");
  downlinks.replaceChildren(...(v.lineage.downlinks.length
    ? v.lineage.downlinks.map((d) => element("li", `${d.id}: ${d.name}`))
    : [element("li", "none")]));
  document.getElementById("release").disabled = v.released;
  document.getElementById("release-status").textContent = "";
}

document.getElementById("release").addEventListener("click", async () => {
  const number = document.getElementById("detail").dataset.version;
  const status = document.getElementById("release-status");
  try {
    const v = await post(`/versions/${number}/release`, { tag: document.getElementById("release-tag").value.trim() });
    await load();
    status.textContent = `released as ${v.release_tag}`;
    status.className = "status ok";
  } catch (error) {
    showError(status, error);
  }
});

load().catch((error) => showError(document.querySelector("h1"), error));

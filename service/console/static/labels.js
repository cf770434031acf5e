// A version's statistics and a difference's figures as a person reads them: a label and a
// formatted value with its unit for each key the service publishes (STATISTICS: service/versions.py
// mesh_statistics, service/publish.py, service/spg.py, service/diff.py), any other key humanised
// from its name (its unit from a unit word: "lateral_m_prior" -> "lateral prior", m), objects as
// nested tables, never JSON.
import { element, tableRow } from "/console/common.js";

// Numbers as read: integers with thousands separators, others to 4 significant digits.
export function number(value, unit = "") {
  if (typeof value !== "number" || !Number.isFinite(value)) return String(value ?? "—");
  const magnitude = Math.abs(value);
  const text = Number.isInteger(value) ? value.toLocaleString("en-US")
    : magnitude !== 0 && (magnitude < 1e-3 || magnitude >= 1e7) ? value.toExponential(3)
      : Number(value.toPrecision(4)).toLocaleString("en-US", { maximumFractionDigits: 10 });
  return unit ? `${text} ${unit}` : text;
}
const count = (v) => number(v);
const unitOf = (unit) => (v) => number(v, unit);
const yesNo = (v) => (v ? "yes" : "no");
const versionRef = (v) => (v === null || v === undefined ? "none" : `v${v}`);
const hash = (v) => `${String(v).slice(0, 12)}…`;
const seconds = (v) => (v >= 120 ? `${number(v / 60)} min` : number(v, "s"));

// key -> [label, formatter] for what the service publishes in a version's statistics
const STATISTICS = {
  vertices: ["vertices", count], faces: ["faces", count],
  area_km2: ["surface area", unitOf("km²")], volume_km3: ["volume", unitOf("km³")],
  mean_radius_km: ["mean radius", unitOf("km")], min_radius_km: ["smallest radius", unitOf("km")],
  max_radius_km: ["largest radius", unitOf("km")], mean_edge_m: ["mean edge length", unitOf("m")],
  maplets_changed: ["maplets changed", count], maplets_added: ["maplets added", count],
  maplets_replaced: ["maplets replaced", count], maplets_removed: ["maplets removed", count],
  maplets_fused: ["maplets fused in all", count], images: ["images used", count],
  incremental: ["parent's fusion sums reused", yesNo], base_version: ["base version", versionRef],
  surface: ["surface made", String], voxels: ["voxels", count],
  levels: ["levels (spacing 2^k m)", null], composition: ["surface composition", null],
  fusion_seconds: ["fusion time", seconds], seconds: ["time", seconds],
  source: ["imported from", String], source_sha256: ["source SHA-256", hash],
  residual_rms_px: ["image residual RMS", unitOf("px")], features: ["features", count],
  matches: ["matches", count], pairs: ["image pairs", count], tracks: ["tracks", count],
  observations: ["observations", count], iterations: ["adjustment iterations", count],
  feature_tracks: ["feature tracks", count], landmarks: ["landmarks", count], points: ["surface points", count],
  extract_s: ["feature extraction time", seconds], match_s: ["matching time", seconds],
  anchor_shift_m: ["anchor shift (x, y, z)", (v) => v.map((c) => number(c)).join(", ") + " m"],
  anchor_measured_m: ["anchor measured (x, y, z)", (v) => v.map((c) => number(c)).join(", ") + " m"],
  figure: ["figure interpolated over", String], figure_misfit_m: ["figure misfit", null],
  uncertainty: ["pose uncertainty (median 1-sigma)", null], unknowns: ["adjusted unknowns", null],
  note: ["note", String], closure: ["closed-surface checks", null],
  mass: ["enclosed mass properties (per unit density)", null], centre_km: ["centre of figure (x, y, z)", null],
  inertia_km5: ["inertia tensor about the centre", null],
  // a difference of two versions (service/diff.py)
  old: ["old version", versionRef], new: ["new version", versionRef],
  vertices_compared: ["vertices compared", count], vertices_total: ["vertices in all", count],
  mean_m: ["mean height change", unitOf("m")], rms_m: ["RMS height change", unitOf("m")],
  max_abs_m: ["largest height change", unitOf("m")], threshold_m: ["changed above", unitOf("m")],
  vertices_changed: ["vertices changed", count], area_changed_m2: ["area changed", unitOf("m²")], regions_laid: ["regions laid", count], regions_carried: ["regions carried over", count],
  closed_levels_made: ["closed levels made again", yesNo], voxel_m: ["voxel size", unitOf("m")],
  ancestors: ["ancestors", String], children: ["children", String], "maplet revisions": ["maplet revisions", count],
};
// why a statistic is absent
const NULLS = { mass: "none: not one closed surface" };
// unit words at the end of a key: "lateral_m_prior" -> lateral prior (m)
const UNITS = { km2: "km²", km3: "km³", km5: "km⁵", m2: "m²", km: "km", m: "m", px: "px", deg: "deg", s: "s", seconds: "s",
  urad: "µrad", mrad: "mrad", rad: "rad", pct: "%" };

// A key humanised: its words, and its unit from a unit word.
function humanise(key) {
  const words = String(key).split(/[_\s]+/).filter(Boolean);
  const unit = words.find((w) => UNITS[w]);
  const text = words.filter((w) => w !== unit).join(" ");
  return { label: text, unit: unit ? UNITS[unit] : "" };
}

// A statistic's label and its value (text, or a node): known keys by STATISTICS, others
// humanised; objects and lists of objects as nested tables and lists, lists of lists as rows;
// absent (null) values as NULLS says why, else "—".
export function statistic(key, value) {
  const known = STATISTICS[key];
  const { label, unit } = known ? { label: known[0], unit: humanise(key).unit } : humanise(key);
  if (known && known[1]) return [label, known[1](value)];
  if (value === null || value === undefined) return [label, NULLS[key] ?? "—"];
  if (Array.isArray(value)) {
    if (value.length && value.every(Array.isArray)) {
      const rows = element("ol", undefined, "nested matrix");
      for (const row of value) rows.append(element("li", row.map((v) => number(v)).join(", ") + (unit ? ` ${unit}` : "")));
      return [label, rows];
    }
    if (value.every((v) => typeof v !== "object" || v === null)) return [label, value.map((v) => number(v, "")).join(", ") + (unit ? ` ${unit}` : "")];
    const list = element("ol", undefined, "nested");
    for (const item of value) list.append(element("li", describe(item)));
    return [label, list];
  }
  if (typeof value === "object") {
    const table = element("table", undefined, "nested");
    for (const [k, v] of Object.entries(value)) {
      const [l, shown] = statistic(k, v);
      table.append(tableRow([l, shown], [1]));
    }
    return [label, table];
  }
  if (typeof value === "boolean") return [label, yesNo(value)];
  return [label, typeof value === "number" ? number(value, unit) : String(value)];
}

// An object in a line: "name: value, prior sigma: 0.1".
function describe(item) {
  if (item === null || typeof item !== "object") return number(item);
  return Object.entries(item).map(([k, v]) => {
    const [label, shown] = statistic(k, v);
    return `${label}: ${shown instanceof Node ? shown.textContent : shown}`;
  }).join("; ");
}

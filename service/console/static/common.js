// What every console page shares: the navigation, the API token (kept in this tab's
// sessionStorage, sent only to the changing calls), JSON and binary fetches, the binary
// document layout (service/console.py: "PWMC", header length, JSON header, arrays), colour
// maps and number formatting.

const PAGES = [
  ["/", "Versions"], ["/console/view.html", "3D view"], ["/console/coverage.html", "Coverage"],
  ["/console/diff.html", "Difference"], ["/console/site.html", "Site"], ["/console/lidar.html", "Lidar"],
  ["/console/jobs.html", "Jobs & downlinks"],
];
const TOKEN_KEY = "pwm-api-token";

export function header() {
  const bar = document.createElement("header");
  const brand = document.createElement("span");
  brand.className = "brand";
  brand.textContent = "pwm console";
  bar.append(brand);
  const here = location.pathname === "/console/index.html" ? "/" : location.pathname;
  for (const [href, label] of PAGES) {
    const link = document.createElement("a");
    link.href = href;
    link.textContent = label;
    if (href === here) link.className = "here";
    bar.append(link);
  }
  const box = document.createElement("span");
  box.className = "token";
  const input = document.createElement("input");
  input.type = "password";
  input.id = "token";
  input.placeholder = "API token (changes only)";
  input.value = sessionStorage.getItem(TOKEN_KEY) || "";
  input.addEventListener("input", () => sessionStorage.setItem(TOKEN_KEY, input.value.trim()));
  box.append(input);
  bar.append(box);
  document.body.prepend(bar);
}

export class ApiError extends Error {
  constructor(status, detail) {
    super(`${status}: ${detail}`);
    this.status = status;
    this.detail = detail;
  }
}

async function failure(response) {
  let detail = response.statusText;
  try {
    const body = await response.json();
    detail = typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail);
  } catch { /* not JSON */ }
  return new ApiError(response.status, detail);
}

export async function getJSON(path) {
  const response = await fetch(path, { headers: { Accept: "application/json" } });
  if (!response.ok) throw await failure(response);
  return response.json();
}

// A changing call: POST with the token the user gave (none: the API refuses it, and the
// refusal is what the caller shows).
export async function post(path, body) {
  const headers = { "Content-Type": "application/json" };
  const token = sessionStorage.getItem(TOKEN_KEY);
  if (token) headers.Authorization = `Bearer ${token}`;
  const response = await fetch(path, { method: "POST", headers, body: JSON.stringify(body ?? {}) });
  if (!response.ok) throw await failure(response);
  return response.json();
}

// A binary document: {header, arrays: {name: TypedArray}}.
export async function getDocument(path) {
  return documentOf(fetch(path));
}

// The document of a fetch under way.
export async function documentOf(responding) {
  const response = await responding;
  if (!response.ok) throw await failure(response);
  return parseDocument(await response.arrayBuffer());
}

const TYPES = { float32: Float32Array, uint32: Uint32Array, uint8: Uint8Array, int8: Int8Array };

export function parseDocument(buffer) {
  const magic = new TextDecoder().decode(new Uint8Array(buffer, 0, 4));
  if (magic !== "PWMC") throw new Error("not a console document");
  const length = new DataView(buffer).getUint32(4, true);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 8, length)));
  const start = 8 + length;
  const arrays = {};
  for (const entry of header.arrays) {
    const count = entry.shape.reduce((a, b) => a * b, 1);
    arrays[entry.name] = new TYPES[entry.dtype](buffer, start + entry.offset, count);
  }
  return { header, arrays };
}

export function fmt(value, digits = 3) {
  if (value === null || value === undefined || Number.isNaN(value)) return "—";
  if (typeof value !== "number") return String(value);
  if (Number.isInteger(value)) return String(value);
  return value.toPrecision(digits);
}

export function element(tag, text, className) {
  const node = document.createElement(tag);
  if (text !== undefined && text !== null) node.textContent = text;
  if (className) node.className = className;
  return node;
}

export function tableRow(cells, numeric = []) {
  const row = document.createElement("tr");
  cells.forEach((cell, k) => {
    const td = document.createElement("td");
    if (cell instanceof Node) td.append(cell); else td.textContent = cell;
    if (numeric.includes(k)) td.className = "num";
    row.append(td);
  });
  return row;
}

// A button that queues a maplet's refinement again (a changing call), and where its answer or
// refusal shows.
export function requeueControl(mapletId) {
  const button = element("button", "re-queue");
  button.type = "button";
  const status = element("span", "", "status");
  button.addEventListener("click", async () => {
    try {
      const job = await post(`/maplets/${mapletId}/requeue`);
      status.textContent = `queued ${job.key}`;
      status.className = "status ok";
    } catch (error) {
      showError(status, error);
    }
  });
  const control = element("span");
  control.append(button, status);
  return control;
}

export function showError(where, error) {
  const node = typeof where === "string" ? document.getElementById(where) : where;
  node.textContent = error instanceof ApiError ? `refused or failed (${error.message})` : String(error);
  node.className = "status " + (error instanceof ApiError && (error.status === 401 || error.status === 403)
    ? "refused" : "error");
}

// Viridis at 9 stops, interpolated: t in [0, 1] -> [r, g, b] in [0, 1].
const VIRIDIS = [[68, 1, 84], [71, 44, 122], [59, 81, 139], [44, 113, 142], [33, 144, 141],
  [39, 173, 129], [92, 200, 99], [170, 220, 50], [253, 231, 37]];
export function viridis(t) {
  const x = Math.min(Math.max(t, 0), 1) * (VIRIDIS.length - 1);
  const k = Math.min(Math.floor(x), VIRIDIS.length - 2);
  const f = x - k;
  return VIRIDIS[k].map((c, i) => (c + f * (VIRIDIS[k + 1][i] - c)) / 255);
}

// The 2nd and 98th percentiles of the finite values (a colour range that outliers do not set),
// from at most about 20000 of them.
export function range(values) {
  const step = Math.max(1, Math.floor(values.length / 20000));
  const sample = [];
  for (let i = 0; i < values.length; i += step) if (Number.isFinite(values[i])) sample.push(values[i]);
  if (!sample.length) return [0, 1];
  sample.sort((a, b) => a - b);
  const lo = sample[Math.floor(0.02 * (sample.length - 1))];
  const hi = sample[Math.floor(0.98 * (sample.length - 1))];
  return hi > lo ? [lo, hi] : [lo - 1e-6, lo + 1e-6];
}

export function params() {
  return new URLSearchParams(location.search);
}

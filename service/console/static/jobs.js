// Jobs and downlinks: the jobs with their live progress (polled every 2 s), failures with the
// reason the API gives, the downlinks, and the products rejected at ingest with their reasons.
// A failed refinement can be re-queued (a changing call: refused without the token).
import { element, fmt, getJSON, header, requeueControl, showError, tableRow } from "/console/common.js";

header();
const POLL_MS = 2000;
const status = document.getElementById("status");

function when(value) {
  return value ? value.replace("T", " ").slice(0, 19) : "—";
}

async function jobs() {
  const page = await getJSON("/jobs?limit=100");
  const body = document.querySelector("#jobs tbody");
  body.replaceChildren();
  for (const job of page.items) {
    const bar = document.createElement("progress");
    bar.max = 1;
    bar.value = job.progress;
    const progress = element("span");
    progress.append(bar, ` ${Math.round(100 * job.progress)}%`);
    const note = element("span", job.error ?? job.message ?? "", job.error ? "error" : "");
    const cell = job.maplet_id !== null && job.status === "failed" ? requeueControl(job.maplet_id) : "";
    const row = tableRow([job.id, job.kind, job.key, job.status, progress, note, when(job.created_at), cell], [0]);
    row.dataset.job = job.id;
    row.dataset.status = job.status;
    body.append(row);
  }
  status.textContent = `${page.total} jobs; updated ${new Date().toISOString().slice(11, 19)} UTC`;
}

async function downlinks() {
  const page = await getJSON("/downlinks?limit=100");
  const body = document.querySelector("#downlinks tbody");
  body.replaceChildren();
  for (const d of page.items) {
    const images = Object.entries(d.images).map(([k, n]) => `${n} ${k}`).join(", ") || "none";
    body.append(tableRow([d.id, d.name, when(d.received_at), d.status, fmt(d.kernels), images], [0, 4]));
  }
  const rejected = await getJSON("/images?status=rejected&limit=200");
  const table = document.querySelector("#rejected tbody");
  table.replaceChildren();
  for (const image of rejected.items) {
    table.append(tableRow([image.lidvid, image.downlink_id ?? "—", image.rejection_code ?? "—", image.rejection_reason ?? "—"]));
  }
  if (!rejected.items.length) table.append(tableRow(["none", "", "", ""]));
}

async function poll() {
  try {
    await jobs();
  } catch (error) {
    showError(status, error);
  }
  setTimeout(poll, POLL_MS);
}

Promise.all([downlinks(), jobs()])
  .then(() => { document.body.dataset.ready = "1"; setTimeout(poll, POLL_MS); })
  .catch((error) => showError(status, error));

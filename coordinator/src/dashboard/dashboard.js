// The rayfarm dashboard: polls the coordinator's /api/ once a second and draws jobs,
// workers, the running frame's preview and charts. No libraries, no requests elsewhere.
"use strict";

const POLL_MS = 1000;
const COLOURS = ["#6cf", "#fc6", "#6f9", "#f69", "#c9f", "#9cf", "#fa6", "#ccc"];
let token = sessionStorage.getItem("rayfarm-token") || "";
let previewJob = "";
let previewSequence = -1;
let previewUrl = null;

function headers(extra) {
  const h = Object.assign({}, extra || {});
  if (token) h["Authorization"] = "Bearer " + token;
  return h;
}

async function api(path, options) {
  const opts = Object.assign({}, options || {});
  opts.headers = headers(opts.headers);
  const r = await fetch(path, opts);
  if (!r.ok) {
    let why = r.status + " " + r.statusText;
    try { why = (await r.json()).error || why; } catch (e) { /* not JSON */ }
    throw new Error(why);
  }
  return r;
}

// Mutations are POSTs with a JSON body (the server refuses anything else).
function post(path, body) {
  return api(path, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(body),
  });
}

function time(ms) {
  return ms ? new Date(ms).toLocaleTimeString() : "";
}

function bytes(n) {
  const units = ["B", "KiB", "MiB", "GiB", "TiB"];
  let i = 0;
  while (n >= 1024 && i < units.length - 1) { n /= 1024; i++; }
  return (i ? n.toFixed(1) : n) + " " + units[i];
}

function cell(row, text) {
  const td = document.createElement("td");
  td.textContent = text;
  row.appendChild(td);
  return td;
}

function status(text, error) {
  const s = document.getElementById("status");
  s.textContent = text;
  s.className = error ? "error" : "";
}

// "subframe 2/4" while a progressive job runs (the one being rendered), "4/4 subframes"
// once it is done.
function subframeText(j) {
  if (j.subframes_done >= j.subframes) return j.subframes + "/" + j.subframes + " subframes";
  return "subframe " + (j.subframes_done + 1) + "/" + j.subframes;
}

function drawJobs(jobs) {
  const body = document.querySelector("#jobs tbody");
  body.replaceChildren();
  for (const j of jobs) {
    const tr = document.createElement("tr");
    tr.dataset.jobId = j.job_id;
    tr.dataset.state = j.state;
    cell(tr, j.job_id);
    cell(tr, j.state + (j.error ? ": " + j.error : ""));
    const p = cell(tr, "");
    if (j.tiles_total) {
      const bar = document.createElement("span");
      bar.className = "bar";
      const fill = document.createElement("span");
      fill.style.width = (100 * j.tiles_done / j.tiles_total) + "%";
      bar.appendChild(fill);
      p.append(bar, " " + j.tiles_done + "/" + j.tiles_total);
    }
    if (j.subframes > 1) p.append(" " + subframeText(j));
    const pr = cell(tr, "");
    const input = document.createElement("input");
    input.type = "number";
    input.className = "priority";
    input.value = j.priority;
    input.disabled = j.state !== "queued";
    input.addEventListener("change", () =>
      post("/api/jobs/" + encodeURIComponent(j.job_id) + "/priority",
           { priority: parseInt(input.value, 10) || 0 })
        .then(poll).catch(e => status("priority: " + e.message, true)));
    pr.appendChild(input);
    cell(tr, j.owner);
    cell(tr, j.scene);
    cell(tr, j.width + "x" + j.height + " " + j.spp + " spp");
    cell(tr, time(j.submitted_unix_ms));
    cell(tr, time(j.started_unix_ms));
    cell(tr, time(j.finished_unix_ms));
    const c = cell(tr, "");
    if (j.state === "queued" || j.state === "running") {
      const b = document.createElement("button");
      b.className = "cancel";
      b.textContent = "cancel";
      b.addEventListener("click", () =>
        post("/api/jobs/" + encodeURIComponent(j.job_id) + "/cancel", {})
          .then(poll).catch(e => status("cancel: " + e.message, true)));
      c.appendChild(b);
    }
    body.appendChild(tr);
  }
}

function drawWorkers(cluster) {
  const body = document.querySelector("#workers tbody");
  body.replaceChildren();
  for (const w of cluster.workers) {
    const tr = document.createElement("tr");
    tr.dataset.workerId = w.worker_id;
    cell(tr, w.worker_id);
    cell(tr, w.peer_address);
    cell(tr, w.resident_domains.join(" "));
    cell(tr, w.queued_rays);
    cell(tr, bytes(w.queue_bytes));
    cell(tr, bytes(w.spill_bytes));
    cell(tr, w.domain_loads);
    cell(tr, (w.rays_per_second / 1e6).toFixed(2) + " M");
    cell(tr, (w.last_seen_ms / 1000).toFixed(1) + " s ago");
    cell(tr, w.left_out);
    body.appendChild(tr);
  }
  const lost = document.querySelector("#lost tbody");
  lost.replaceChildren();
  for (const l of cluster.lost.slice().reverse()) {
    const tr = document.createElement("tr");
    cell(tr, l.worker_id);
    cell(tr, l.peer_address);
    cell(tr, time(l.lost_unix_ms));
    cell(tr, l.reason);
    lost.appendChild(tr);
  }
}

// The preview of the running job, or else of the newest job that has one; fetched only
// when its sequence number moved.
async function drawPreview(jobs, cluster) {
  const running = jobs.find(j => j.job_id === cluster.running_job_id);
  const shown = running || jobs.find(j => j.preview_sequence > 0 && j.state === "succeeded");
  document.getElementById("running-job").textContent = running ? running.job_id : "(none)";
  if (!shown) return;
  if (shown.job_id === previewJob && shown.preview_sequence === previewSequence) return;
  const r = await api("/api/jobs/" + encodeURIComponent(shown.job_id) + "/preview");
  const sequence = parseInt(r.headers.get("X-Preview-Sequence"), 10);
  const blob = await r.blob();
  const img = document.getElementById("preview");
  if (previewUrl) URL.revokeObjectURL(previewUrl);
  previewUrl = URL.createObjectURL(blob);
  img.src = previewUrl;
  img.dataset.job = shown.job_id;
  img.dataset.sequence = String(sequence);
  previewJob = shown.job_id;
  previewSequence = shown.preview_sequence;
  document.getElementById("preview-note").textContent =
    shown.job_id + ": " + (shown.subframes > 1 ? subframeText(shown) + ", " : "") +
    shown.tiles_done + "/" + shown.tiles_total + " tiles (preview " + sequence + ")";
}

// One chart: each series is [{t, v}], drawn as lines over the samples' time span.
function chart(id, series) {
  const canvas = document.getElementById(id);
  const g = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height, pad = 4;
  g.clearRect(0, 0, w, h);
  const points = series.flatMap(s => s.points);
  if (points.length < 2) return;
  const t0 = Math.min(...points.map(p => p.t)), t1 = Math.max(...points.map(p => p.t));
  const top = Math.max(1, ...points.map(p => p.v));
  g.fillStyle = "#99a";
  g.font = "11px sans-serif";
  g.fillText(top >= 1e6 ? (top / 1e6).toFixed(1) + "M" : String(Math.round(top)), pad, 12);
  series.forEach((s, i) => {
    g.strokeStyle = s.colour || COLOURS[i % COLOURS.length];
    g.beginPath();
    s.points.forEach((p, k) => {
      const x = pad + (w - 2 * pad) * (p.t - t0) / Math.max(1, t1 - t0);
      const y = h - pad - (h - 2 * pad) * p.v / top;
      if (k) g.lineTo(x, y); else g.moveTo(x, y);
    });
    g.stroke();
  });
}

function drawCharts(samples) {
  const ids = [...new Set(samples.flatMap(s => s.workers.map(w => w.worker_id)))];
  const per = field => ids.map(id => ({
    points: samples.flatMap(s => s.workers.filter(w => w.worker_id === id)
      .map(w => ({ t: s.unix_ms, v: w[field] }))),
  }));
  const frame = { colour: "#fff", points: samples.map(s => ({ t: s.unix_ms, v: s.rays_per_second })) };
  chart("chart-rays", [frame].concat(per("rays_per_second")));
  chart("chart-loads", per("domain_loads"));
  chart("chart-queues", per("queue_bytes"));
}

async function poll() {
  try {
    const [jobs, cluster, samples] = await Promise.all(
      ["/api/jobs", "/api/cluster", "/api/history"].map(p => api(p).then(r => r.json())));
    drawJobs(jobs);
    drawWorkers(cluster);
    drawCharts(samples);
    await drawPreview(jobs, cluster);
    status("updated " + new Date().toLocaleTimeString(), false);
  } catch (e) {
    status(e.message, true);
  }
}

document.getElementById("token").value = token;
document.getElementById("token-form").addEventListener("submit", ev => {
  ev.preventDefault();
  token = document.getElementById("token").value.trim();
  sessionStorage.setItem("rayfarm-token", token);
  poll();
});
poll();
setInterval(poll, POLL_MS);

// lfcal-station operator page: start a run, follow it live (SSE), show the result.
// Plain JavaScript, no build step. Talks only to this server's /api/v1.
"use strict";

const API = "/api/v1";
const FIELDS = ["start_mm", "stop_mm", "step_mm", "exposure_us", "settle_s", "calibrate", "note"];
const FINAL = new Set(["succeeded", "failed", "cancelled", "interrupted"]);
const KEY_STORE = "lfcal-api-key";

const state = {
  readNeedsKey: false,
  schema: null,        // the SweepRequest JSON schema (limits, defaults)
  maxFrames: null,
  jobId: null,
  lastStep: null,      // last SSE step id seen (Last-Event-ID on reconnect)
  stream: null,        // AbortController of the event stream
  points: new Map(),   // frame index -> {u, la, q, w}
  model: null,         // {u: [], w: [], focus} once the result is known
  finalShown: null,
  pollTimer: null,
  frameWanted: null,   // latest analysed frame to show with its corners
  frameShown: null,
  frameLoading: false,
};

const $ = (id) => document.getElementById(id);

// ------------------------------------------------------------------ HTTP helpers

class ApiError extends Error {
  constructor(status, body) {
    super((body && body.message) || `HTTP ${status}`);
    this.status = status;
    this.body = body || {};
  }
}

function apiKey() {
  return $("api-key").value.trim();
}

function headers(extra) {
  const h = Object.assign({}, extra || {});
  const key = apiKey();
  if (key) h["X-API-Key"] = key;
  return h;
}

async function api(path, options) {
  const opts = Object.assign({}, options || {});
  opts.headers = headers(opts.headers);
  const response = await fetch(API + path, opts);
  let body = null;
  const type = response.headers.get("content-type") || "";
  if (type.includes("application/json")) body = await response.json();
  if (!response.ok) throw new ApiError(response.status, body);
  return { response, body };
}

// Image and download URLs: plain URLs when reading needs no key, else blob URLs.
async function resourceUrl(path) {
  if (!state.readNeedsKey) return API + path;
  const response = await fetch(API + path, { headers: headers() });
  if (!response.ok) throw new ApiError(response.status, null);
  return URL.createObjectURL(await response.blob());
}

// ------------------------------------------------------------------ start-up

async function init() {
  $("api-key").value = localStorage.getItem(KEY_STORE) || "";
  $("api-key").addEventListener("change", () => {
    localStorage.setItem(KEY_STORE, apiKey());
    refreshJobs();
  });
  $("run-form").addEventListener("submit", onSubmit);
  $("run-form").addEventListener("input", () => validateForm(false));
  $("pause-button").addEventListener("click", () => jobAction("pause"));
  $("resume-button").addEventListener("click", () => jobAction("resume"));
  $("cancel-button").addEventListener("click", () => jobAction("cancel"));
  try {
    const { body } = await api("/healthz");
    state.readNeedsKey = body.read_only_requires_key;
    showDevices(body.devices);
  } catch (err) {
    showDevices("down");
  }
  await loadSchema();
  const jobs = await refreshJobs();
  // a job's URL (?job=ID) shows that job; else an operator who opens the page during a
  // run sees that run at once
  const wanted = jobFromUrl();
  const active = jobs.find((job) => job.state === "running" || job.state === "paused");
  if (wanted !== null && state.jobId === null) follow(wanted);
  else if (active && state.jobId === null) follow(active.id);
  refreshDevices();
  setInterval(refreshDevices, 5000);
}

function jobFromUrl() {
  const text = new URLSearchParams(window.location.search).get("job");
  const id = Number(text);
  return text && Number.isInteger(id) && id > 0 ? id : null;
}

async function loadSchema() {
  try {
    const response = await fetch(API + "/openapi.json");
    const doc = await response.json();
    state.schema = doc.components.schemas.SweepRequest;
  } catch (err) {
    state.schema = null;
  }
  const props = (state.schema && state.schema.properties) || {};
  for (const name of ["start_mm", "stop_mm", "step_mm", "exposure_us", "settle_s"]) {
    const prop = props[name];
    if (!prop) continue;
    const number = (prop.anyOf || [prop]).find((s) => s.type === "number") || {};
    const input = $(name);
    if (number.minimum !== undefined) input.min = number.minimum;
    if (number.maximum !== undefined) input.max = number.maximum;
    if (prop.examples && prop.examples.length) input.value = prop.examples[0];
    if (prop["x-max-frames"]) state.maxFrames = prop["x-max-frames"];
  }
  validateForm(false);
}

function showDevices(text) {
  const badge = $("devices-status");
  badge.textContent = "devices: " + text;
  badge.className = "badge " + (text === "down" ? "down" : text === "connected" || text === "busy" ? "ok" : "");
}

// The badge and the devices panel from one GET /devices (the stages are asked once);
// /healthz (always open) when reading needs a key the page does not have.
async function refreshDevices() {
  const status = await refreshDevicePanel();
  if (status !== null) {
    showDevices(status);
    return;
  }
  try {
    const { body } = await api("/healthz");
    showDevices(body.devices);
  } catch (err) {
    showDevices("down");
  }
}

// ------------------------------------------------------------------ devices panel

function setRow(id, cells) {
  const tds = $(id).querySelectorAll("td");
  cells.forEach((text, k) => { tds[k + 1].textContent = text; });
}

function yesNo(value) {
  return value === true ? "homed" : value === false ? "not homed" : "?";
}

// Fills the devices panel; returns the devices' state for the badge (connected, busy,
// opening, down), or null when the devices cannot be read (no key).
async function refreshDevicePanel() {
  let info = null;
  let note = "";
  let status = null;
  try {
    ({ body: info } = await api("/devices"));
    status = info.busy ? "busy" : "connected";
  } catch (err) {
    note = err.message;
    info = (err.body && err.body.context && err.body.context.devices) || null;
    if (err.body && err.body.code === "devices_opening") status = "opening";
    else if (err.status === 503) status = "down";
  }
  if (!info) {
    $("devices-note").textContent = note;
    return status;
  }
  const cam = info.camera || {};
  const temp = cam.temperature_c !== undefined && cam.temperature_c !== null
    ? `${fmt(cam.temperature_c, 1)} °C` : "temperature not reported";
  const roi = cam.roi ? `ROI ${cam.roi.width}×${cam.roi.height}` : "";
  setRow("dev-camera", [
    [cam.vendor, cam.model].filter(Boolean).join(" ") + (cam.serial ? `, serial ${cam.serial}` : ""),
    roi, "", [temp, cam.error].filter(Boolean).join("; "),
  ]);
  const rail = info.rail || {};
  const railMm = info.busy && info.rail_mm !== undefined && info.rail_mm !== null ? info.rail_mm : rail.position_mm;
  setRow("dev-rail", [
    (rail.identity && (rail.identity.name || rail.identity.device_id)) || "",
    railMm === null || railMm === undefined ? "n/a" : `${fmt(railMm, 3)} mm`
      + (!info.busy && rail.object_distance_mm ? ` (u ${fmt(rail.object_distance_mm, 1)} mm)` : ""),
    yesNo(rail.homed), rail.error || "",
  ]);
  const xy = info.xy_stage || {};
  const pos = Array.isArray(xy.position_mm) ? `${fmt(xy.position_mm[0], 3)}, ${fmt(xy.position_mm[1], 3)} mm` : "n/a";
  setRow("dev-xy", ["", pos, yesNo(xy.homed), xy.error || ""]);
  $("devices-note").textContent = note || (info.busy ? `in use by job ${info.active_job ?? ""} (positions as last read)` : "");
  $("devices-table").dataset.updated = String(Date.now());
  return status;
}

// ------------------------------------------------------------------ the form

function numberLimits(name) {
  const prop = state.schema && state.schema.properties[name];
  if (!prop) return {};
  return (prop.anyOf || [prop]).find((s) => s.type === "number") || {};
}

function setFieldError(name, message) {
  const slot = $("err-" + name);
  if (slot) slot.textContent = message || "";
  const input = $(name);
  if (input) input.classList.toggle("invalid", Boolean(message));
}

// Checks the form; returns the request body, or null (with messages shown) if invalid.
function validateForm(showAll) {
  const body = {};
  const problems = {};
  for (const name of ["start_mm", "stop_mm", "step_mm", "exposure_us", "settle_s"]) {
    const input = $(name);
    const text = input.value.trim();
    if (text === "") {
      problems[name] = "enter a number";
      continue;
    }
    const value = Number(text);
    if (!Number.isFinite(value)) {
      problems[name] = "must be a number";
      continue;
    }
    const lim = numberLimits(name);
    if (lim.minimum !== undefined && value < lim.minimum) problems[name] = `must be ≥ ${lim.minimum}`;
    else if (lim.exclusiveMinimum !== undefined && value <= lim.exclusiveMinimum)
      problems[name] = `must be > ${lim.exclusiveMinimum}`;
    else if (lim.maximum !== undefined && value > lim.maximum) problems[name] = `must be ≤ ${lim.maximum}`;
    body[name] = value;
  }
  if (!problems.start_mm && !problems.stop_mm && body.stop_mm < body.start_mm) {
    problems.stop_mm = `must not be below start (${body.start_mm} mm)`;
  }
  let frames = null;
  if (!problems.start_mm && !problems.stop_mm && !problems.step_mm && body.step_mm > 0) {
    frames = Math.floor((body.stop_mm - body.start_mm) / body.step_mm + 1e-9) + 1;
    if (state.maxFrames && frames > state.maxFrames) {
      problems.step_mm = `gives ${frames} frames, at most ${state.maxFrames} are allowed`;
    }
  }
  $("frame-count").textContent = frames ? `${frames} frames` : "";
  body.calibrate = $("calibrate").checked;
  const note = $("note").value.trim();
  if (note) body.note = note;
  for (const name of FIELDS) {
    const input = $(name);
    if (showAll || (input && input.value !== "")) setFieldError(name, problems[name]);
  }
  return Object.keys(problems).length ? null : body;
}

async function onSubmit(event) {
  event.preventDefault();
  $("form-error").textContent = "";
  const body = validateForm(true);
  if (!body) {
    $("form-error").textContent = "Fix the marked fields.";
    return;
  }
  $("start-button").disabled = true;
  try {
    const { body: job } = await api("/jobs", {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify(body),
    });
    follow(job.id);
    refreshJobs();
  } catch (err) {
    if (err instanceof ApiError) {
      for (const f of err.body.fields || []) setFieldError(f.field, f.message);
      $("form-error").textContent = err.message;
    } else {
      $("form-error").textContent = String(err);
    }
  } finally {
    $("start-button").disabled = false;
  }
}

// ------------------------------------------------------------------ following a job

function follow(jobId) {
  if (state.stream) state.stream.abort();
  if (state.pollTimer) clearInterval(state.pollTimer);
  state.jobId = jobId;
  state.lastStep = null;
  state.points = new Map();
  state.model = null;
  state.finalShown = null;
  state.frameWanted = null;
  state.frameShown = null;
  const url = `${window.location.pathname}?job=${jobId}`;
  if (window.location.search !== `?job=${jobId}`) window.history.replaceState(null, "", url);
  $("job-link").textContent = window.location.origin + url;
  $("job-link").href = url;
  $("frame-caption").textContent = "waiting for the first analysed frame";
  $("job").hidden = false;
  $("result").hidden = true;
  $("job-id").textContent = String(jobId);
  $("job-state").textContent = "";
  showPhase([]);
  $("job-error").textContent = "";
  $("progress").value = 0;
  drawPlots();
  openStream(jobId);
  pollStatus();
  state.pollTimer = setInterval(pollStatus, 2000);
}

// Server-Sent Events over fetch (so the API key header can be sent), with
// reconnection from the last step id (Last-Event-ID) until the job is final.
async function openStream(jobId) {
  const controller = new AbortController();
  state.stream = controller;
  while (state.jobId === jobId && !controller.signal.aborted) {
    const extra = { Accept: "text/event-stream" };
    if (state.lastStep !== null) extra["Last-Event-ID"] = String(state.lastStep);
    let finished = false;
    try {
      const response = await fetch(`${API}/jobs/${jobId}/events`, {
        headers: headers(extra),
        signal: controller.signal,
      });
      if (!response.ok) throw new ApiError(response.status, await response.json());
      const reader = response.body.getReader();
      const decoder = new TextDecoder();
      let buffer = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buffer += decoder.decode(value, { stream: true });
        let cut;
        while ((cut = buffer.indexOf("\n\n")) >= 0) {
          const block = buffer.slice(0, cut);
          buffer = buffer.slice(cut + 2);
          if (handleBlock(block)) finished = true;
        }
      }
    } catch (err) {
      if (controller.signal.aborted) return;
      if (err instanceof ApiError && err.status < 500) {
        $("job-error").textContent = err.message;
        return;
      }
    }
    if (finished) return;
    await new Promise((resolve) => setTimeout(resolve, 1000));
  }
}

// One SSE message; returns true when it reports a final state.
function handleBlock(block) {
  let type = "message";
  let id = null;
  const data = [];
  for (const line of block.split("\n")) {
    if (line.startsWith(":")) continue;
    const colon = line.indexOf(":");
    const field = colon < 0 ? line : line.slice(0, colon);
    const value = colon < 0 ? "" : line.slice(colon + 1).replace(/^ /, "");
    if (field === "event") type = value;
    else if (field === "data") data.push(value);
    else if (field === "id") id = value;
  }
  if (!data.length) return false;
  const event = JSON.parse(data.join("\n"));
  if (id !== null && id !== "") state.lastStep = Number(id);
  return onEvent(type, event.data);
}

function onEvent(type, d) {
  if (type === "step") {
    setProgress(d.frames_done, d.frames_total);
    if (d.summary) {
      addPoint(d.summary);
      showFrame(d.summary.index);
    }
    const rail = d.actual_mm !== undefined ? `rail ${fmt(d.actual_mm, 3)} mm` : "";
    const eta = d.eta_s !== undefined && d.eta_s !== null ? `, ETA ${Math.round(d.eta_s)} s` : "";
    $("progress-text").textContent = `${d.frames_done} of ${d.frames_total} frames, ${rail}${eta}`;
  } else if (type === "analysis") {
    addPoint(d);
    showFrame(d.index);
  } else if (type === "phase") {
    if (state.finalShown !== state.jobId) showPhase([d.phase]);
  } else if (type === "state") {
    $("job-state").textContent = d.state;
    if (d.last_error) $("job-error").textContent = d.last_error;
    if (FINAL.has(d.state)) {
      onFinal(d.state);
      return true;
    }
  }
  return false;
}

// The state span holds the job's state only; its phase and pending requests go beside it.
function showPhase(notes) {
  const shown = notes.filter(Boolean);
  $("job-phase").textContent = shown.length ? `(${shown.join(", ")})` : "";
}

function setProgress(done, total) {
  const bar = $("progress");
  bar.max = Math.max(1, total);
  bar.value = done;
  bar.dataset.done = String(done);
  bar.dataset.total = String(total);
}

async function pollStatus() {
  const jobId = state.jobId;
  if (jobId === null) return;
  try {
    const { body: job } = await api(`/jobs/${jobId}`);
    // a reply that was in flight when the job ended must not overwrite the final state
    if (jobId !== state.jobId || state.finalShown === jobId) return;
    setProgress(job.frames_done, job.frames_total);
    const parts = [`${job.frames_done} of ${job.frames_total} frames`];
    if (job.rail_mm !== null) parts.push(`rail ${fmt(job.rail_mm, 3)} mm`);
    if (job.eta_s !== null) parts.push(`ETA ${Math.round(job.eta_s)} s`);
    $("progress-text").textContent = parts.join(", ");
    $("job-state").textContent = job.state;
    showPhase([
      job.phase,
      job.pause_requested && "pause requested",
      job.cancel_requested && "cancel requested",
    ]);
    if (job.last_error) $("job-error").textContent = job.last_error;
    if (FINAL.has(job.state)) onFinal(job.state);
  } catch (err) {
    $("job-error").textContent = err.message;
  }
}

async function jobAction(action) {
  if (state.jobId === null) return;
  $("job-error").textContent = "";
  try {
    await api(`/jobs/${state.jobId}/${action}`, { method: "POST" });
    if (action === "resume") follow(state.jobId); // a re-queued job streams again from the start
    else pollStatus();
  } catch (err) {
    $("job-error").textContent = err.message;
  }
}

async function onFinal(jobState) {
  if (state.finalShown === state.jobId) return;
  state.finalShown = state.jobId;
  if (state.pollTimer) clearInterval(state.pollTimer);
  state.pollTimer = null;
  $("job-state").textContent = jobState;
  showPhase([]);
  try {
    const { body: job } = await api(`/jobs/${state.jobId}`);
    setProgress(job.frames_done, job.frames_total);
    $("progress-text").textContent = `${job.frames_done} of ${job.frames_total} frames recorded`;
  } catch (err) {
    // the status line keeps its last text
  }
  refreshJobs();
  refreshDevicePanel();
  if (jobState === "succeeded") {
    try {
      const { body: result } = await api(`/jobs/${state.jobId}/result`);
      showResult(state.jobId, result);
    } catch (err) {
      $("job-error").textContent = err.message;
    }
  } else {
    showLinks(state.jobId, false);
  }
}

// ------------------------------------------------------------------ live frame

// Show frame `index` (downscaled) with the corners its analysis found; while a frame
// loads, later requests replace each other, so the view always ends on the latest.
function showFrame(index) {
  if (index === undefined || index === null) return;
  state.frameWanted = index;
  if (!state.frameLoading) loadFrames();
}

function loadImage(url) {
  return new Promise((resolve, reject) => {
    const img = new Image();
    img.onload = () => resolve(img);
    img.onerror = () => reject(new Error("the frame preview cannot be loaded"));
    img.src = url;
  });
}

async function loadFrames() {
  state.frameLoading = true;
  try {
    while (state.frameWanted !== null && state.frameWanted !== state.frameShown) {
      const jobId = state.jobId;
      const index = state.frameWanted;
      const [url, reply] = await Promise.all([
        resourceUrl(`/jobs/${jobId}/frames/${index}?width=640`),
        api(`/jobs/${jobId}/frames/${index}/corners`),
      ]);
      const img = await loadImage(url);
      if (jobId !== state.jobId) return;
      drawFrame(img, reply.body);
      state.frameShown = index;
    }
  } catch (err) {
    $("frame-caption").textContent = `frame preview: ${err.message}`;
  } finally {
    state.frameLoading = false;
  }
}

function drawFrame(img, corners) {
  const canvas = $("frame-view");
  canvas.width = img.naturalWidth;
  canvas.height = img.naturalHeight;
  const ctx = canvas.getContext("2d");
  ctx.drawImage(img, 0, 0);
  const scale = corners.width ? img.naturalWidth / corners.width : 1;
  const mark = (points, colour) => {
    ctx.strokeStyle = colour;
    ctx.lineWidth = 1.5;
    for (const [x, y] of points) {
      const cx = x * scale;
      const cy = y * scale;
      ctx.beginPath();
      ctx.moveTo(cx - 5, cy); ctx.lineTo(cx + 5, cy);
      ctx.moveTo(cx, cy - 5); ctx.lineTo(cx, cy + 5);
      ctx.stroke();
    }
  };
  mark(corners.standard || [], "#00e676");
  mark(corners.reference || [], "#ff4081");
  const n = (corners.standard || []).length + (corners.reference || []).length;
  canvas.dataset.frame = String(corners.index);
  canvas.dataset.corners = String(n);
  const rail = corners.rail_mm !== null && corners.rail_mm !== undefined ? `, rail ${fmt(corners.rail_mm, 3)} mm` : "";
  $("frame-caption").textContent = corners.analysed
    ? `frame ${corners.index}${rail}: ${(corners.standard || []).length} standard (green) and `
      + `${(corners.reference || []).length} reference (pink) corner points`
      + (corners.error ? ` (${corners.error})` : "")
    : `frame ${corners.index}${rail}: not analysed yet`;
}

// ------------------------------------------------------------------ live plots

function addPoint(s) {
  if (s.index === undefined || s.index === null) return;
  // the edge spread (what the defocus model fits); older servers send only edge_width_px
  const w = s.edge_spread_px ?? s.edge_width_px;
  state.points.set(s.index, { u: s.object_distance_mm, la: s.La_mm, q: s.Q, w });
  drawPlots();
}

function drawPlots() {
  const all = [...state.points.values()];
  const la = all.filter((p) => p.u !== null && p.u !== undefined && p.la !== null && p.la !== undefined);
  $("la-note").textContent = all.length && !la.length
    ? "La is not measurable in these frames (is the reference corner in view?)"
    : `${la.length} frames with La`;
  drawScatter($("la-plot"), la.map((p) => [p.u, p.la]), "La (mm)", null, null);
  const w = all.filter((p) => p.u !== null && p.u !== undefined && p.w !== null && p.w !== undefined);
  const model = state.model;
  $("width-note").textContent = `${w.length} frames with an edge spread`
    + (model && model.focus !== null ? `; defocus-model focus plane u0 = ${fmt(model.focus, 2)} mm` : "");
  drawScatter($("width-plot"), w.map((p) => [p.u, p.w]), "edge spread (px)",
    model ? model.points : null, model ? model.focus : null);
}

// Points [[x, y]], an optional model line [[x, y]] and a vertical focus line at x = focus.
function drawScatter(canvas, pts, ylabel, line, focus) {
  const ctx = canvas.getContext("2d");
  const W = canvas.width;
  const H = canvas.height;
  ctx.clearRect(0, 0, W, H);
  canvas.dataset.points = String(pts.length);
  canvas.dataset.modelPoints = String(line ? line.length : 0);
  const m = { l: 60, r: 15, t: 15, b: 40 };
  ctx.strokeStyle = "#888";
  ctx.strokeRect(m.l, m.t, W - m.l - m.r, H - m.t - m.b);
  ctx.fillStyle = "#333";
  ctx.font = "12px sans-serif";
  ctx.fillText("object distance u (mm)", W / 2 - 60, H - 8);
  ctx.save();
  ctx.translate(14, H / 2 + 30);
  ctx.rotate(-Math.PI / 2);
  ctx.fillText(ylabel, 0, 0);
  ctx.restore();
  const every = pts.concat(line || []);
  if (!every.length) return;
  let [x0, x1] = [Math.min(...every.map((p) => p[0])), Math.max(...every.map((p) => p[0]))];
  let [y0, y1] = [Math.min(...every.map((p) => p[1])), Math.max(...every.map((p) => p[1]))];
  if (x1 === x0) { x0 -= 1; x1 += 1; }
  if (y1 === y0) { y0 -= 0.01; y1 += 0.01; }
  const pad = (y1 - y0) * 0.1;
  y0 -= pad; y1 += pad;
  const x = (v) => m.l + ((v - x0) / (x1 - x0)) * (W - m.l - m.r);
  const y = (v) => H - m.b - ((v - y0) / (y1 - y0)) * (H - m.t - m.b);
  ctx.fillText(fmt(x0, 1), m.l - 10, H - m.b + 15);
  ctx.fillText(fmt(x1, 1), W - m.r - 30, H - m.b + 15);
  ctx.fillText(fmt(y1, 3), 18, m.t + 10);
  ctx.fillText(fmt(y0, 3), 18, H - m.b);
  if (focus !== null && focus !== undefined && focus >= x0 && focus <= x1) {
    ctx.strokeStyle = "#c62828";
    ctx.setLineDash([5, 4]);
    ctx.beginPath();
    ctx.moveTo(x(focus), m.t);
    ctx.lineTo(x(focus), H - m.b);
    ctx.stroke();
    ctx.setLineDash([]);
  }
  if (line && line.length) {
    ctx.strokeStyle = "#ef6c00";
    ctx.lineWidth = 2;
    ctx.beginPath();
    line.forEach(([u, v], k) => (k ? ctx.lineTo(x(u), y(v)) : ctx.moveTo(x(u), y(v))));
    ctx.stroke();
    ctx.lineWidth = 1;
  }
  ctx.fillStyle = "#1565c0";
  for (const [u, v] of pts.slice().sort((a, b) => a[0] - b[0])) {
    ctx.beginPath();
    ctx.arc(x(u), y(v), 3.5, 0, 2 * Math.PI);
    ctx.fill();
  }
}

// ------------------------------------------------------------------ result

function fmt(value, digits) {
  if (value === null || value === undefined || !Number.isFinite(Number(value))) return "n/a";
  return Number(value).toFixed(digits);
}

// The data-sheet values against what the sweep measured (issue 11).
const PRIOR_LABELS = {
  main_focal_mm: "main-lens focal length F",
  mla_focal_mm: "microlens focal length f",
  rail_zero_object_distance_mm: "rail zero object distance",
};

function showPriors(priors) {
  const table = $("priors-table");
  const tbody = table.querySelector("tbody");
  tbody.innerHTML = "";
  let n = 0;
  for (const [key, label] of Object.entries(PRIOR_LABELS)) {
    const p = priors[key];
    if (!p) continue;
    n += 1;
    const tr = document.createElement("tr");
    tr.id = "prior-" + key;
    const check = p.contradicted ? "CONTRADICTED" : (p.determined_by === "prior" ? "data sheet used" : "ok");
    const cells = [
      [label, ""], [fmt(p.datasheet, 4), "num"], ["± " + fmt(p.tolerance, 4), "num"],
      [fmt(p.calibrated, 4), "num"], ["± " + fmt(p.uncertainty, 4), "num"],
      [fmt(p.z, 1), "num"], [check, p.contradicted ? "error" : ""],
    ];
    for (const [text, cls] of cells) {
      const td = document.createElement("td");
      td.textContent = text;
      if (cls) td.className = cls;
      tr.appendChild(td);
    }
    tbody.appendChild(tr);
  }
  table.hidden = n === 0;
}

function showResult(jobId, r) {
  const u = r.uncertainty || {};
  const focus = r.focus || {};
  const rows = [
    ["res-a", "a (focus distance in front of the MLA)", r.a_mm, u.a_mm, "mm", 5],
    ["res-b", "b (MLA to sensor)", r.b_mm, u.b_mm, "mm", 5],
    ["res-Q", "Q = b/a", r.Q, u.Q, "", 6],
    ["res-p", "p (patch size)", r.patch_size_px, u.patch_size_px, "px", 4],
    ["res-focus-u", "focus plane: object distance u", focus.object_distance_mm,
      focus.uncertainty_mm, "mm", 3],
    ["res-focus-rail", "focus plane: rail position", focus.rail_mm,
      focus.rail_uncertainty_mm ?? focus.uncertainty_mm, "mm", 3],
    ["res-L", "L (main lens to MLA)", r.L_mm, u.L_mm, "mm", 4],
  ];
  const tbody = $("result-table").querySelector("tbody");
  tbody.innerHTML = "";
  for (const [id, name, value, err, unit, digits] of rows) {
    const tr = document.createElement("tr");
    tr.id = id;
    for (const [text, cls] of [[name, ""], [fmt(value, digits), "num"],
      [err === undefined || err === null ? "" : "± " + fmt(err, digits), "num"], [unit, ""]]) {
      const td = document.createElement("td");
      td.textContent = text;
      if (cls) td.className = cls;
      tr.appendChild(td);
    }
    tbody.appendChild(tr);
  }
  showPriors(r.priors || {});
  for (const w of r.warnings || []) {
    const tr = document.createElement("tr");
    const td = document.createElement("td");
    td.colSpan = 4;
    td.className = "hint";
    td.textContent = "warning: " + w;
    tr.appendChild(td);
    tbody.appendChild(tr);
  }
  $("result").hidden = false;
  const curves = r.curves || {};
  const us = curves.object_distance_mm || [];
  const ws = curves.edge_spread_model_px || curves.edge_width_model_px || [];
  state.model = {
    points: us.map((u, k) => [u, ws[k]]).filter(([u, w]) => u !== null && w !== null && w !== undefined),
    focus: focus.object_distance_mm ?? null,
  };
  drawPlots();
  showLinks(jobId, true);
}

async function showLinks(jobId, succeeded) {
  const list = $("links");
  const images = $("images");
  list.innerHTML = "";
  images.innerHTML = "";
  const base = `/jobs/${jobId}`;
  const items = succeeded
    ? [
        ["focus plot La(u)", `${base}/plots/focus.png`, true],
        ["disparity plot Q(u)", `${base}/plots/disparity.png`, true],
        ["rendered, calibrated p", `${base}/render.png?p=calibrated`, true],
        ["rendered, designed p", `${base}/render.png?p=designed`, true],
        ["calibration report (HTML)", `${base}/report.html`, false],
        ["result JSON", `${base}/result`, false],
        ["sweep archive (zip)", `${base}/archive`, false],
      ]
    : [["sweep archive (zip)", `${base}/archive`, false]];
  $("result").hidden = false;
  for (const [label, path, inline] of items) {
    const li = document.createElement("li");
    const a = document.createElement("a");
    a.textContent = label;
    a.href = API + path;
    if (state.readNeedsKey) {
      a.addEventListener("click", async (ev) => {
        ev.preventDefault();
        window.open(await resourceUrl(path), "_blank");
      });
    }
    li.appendChild(a);
    list.appendChild(li);
    if (inline) {
      const img = document.createElement("img");
      img.alt = label;
      try {
        img.src = await resourceUrl(path);
        images.appendChild(img);
      } catch (err) {
        li.appendChild(document.createTextNode(` (${err.message})`));
      }
    }
  }
}

// ------------------------------------------------------------------ jobs list

// Fills the job table; returns the jobs (oldest first), or [] when they cannot be read.
async function refreshJobs() {
  try {
    const { body } = await api("/jobs?limit=20");
    const tbody = $("jobs-table").querySelector("tbody");
    tbody.innerHTML = "";
    for (const job of body.jobs.slice().reverse()) {
      const tr = document.createElement("tr");
      const created = new Date(job.created_at * 1000).toLocaleString();
      for (const text of [job.id, job.state, `${job.frames_done}/${job.frames_total}`, created]) {
        const td = document.createElement("td");
        td.textContent = String(text);
        tr.appendChild(td);
      }
      const td = document.createElement("td");
      const button = document.createElement("button");
      button.type = "button";
      button.textContent = "show";
      button.addEventListener("click", () => follow(job.id));
      td.appendChild(button);
      tr.appendChild(td);
      tbody.appendChild(tr);
    }
    return body.jobs;
  } catch (err) {
    // reading the jobs may need a key: the form still works once one is entered
    return [];
  }
}

init();

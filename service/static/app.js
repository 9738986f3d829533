// The job page: sign in with an API key, upload a cloud, follow one's jobs, open one to read its
// statistics, look at the flagged cloud in 3-D and download the results. Everything it loads
// comes from this service; text from the server is set as text, never as HTML.
import { Problem, apiKey, getJSON, request, saveFile, submitJob } from "/app/static/api.js";

const ACTIVE = new Set(["accepted", "running"]);
const POLL_ACTIVE_MS = 1000;
const POLL_IDLE_MS = 10000;

const $ = (id) => document.getElementById(id);
let listTimer = null;
let jobTimer = null;
let openJobId = null;
let view = null;

// ---- small helpers -------------------------------------------------------------------------

function element(tag, text, attributes = {}) {
  const node = document.createElement(tag);
  if (text !== undefined && text !== null) node.textContent = String(text);
  for (const [name, value] of Object.entries(attributes)) node.setAttribute(name, value);
  return node;
}

function table(headings, rows, caption) {
  const node = element("table");
  if (caption) node.append(element("caption", caption));
  const head = node.createTHead().insertRow();
  for (const h of headings) head.append(element("th", h));
  const body = node.createTBody();
  for (const row of rows) {
    const tr = body.insertRow();
    for (const cell of row) {
      const td = tr.insertCell();
      if (cell instanceof Node) td.append(cell);
      else td.textContent = cell ?? "";
    }
  }
  return node;
}

const count = (n) => (typeof n === "number" ? n.toLocaleString("en") : n ?? "");
const percent = (part, whole) => (whole ? `${((100 * part) / whole).toFixed(2)} %` : "");

function showProblem(error) {
  const box = $("problem");
  box.textContent = error instanceof Problem ? error.message : `Error: ${error?.message || error}`;
  box.hidden = false;
}

function clearProblem() {
  $("problem").hidden = true;
  $("problem").textContent = "";
}

// ---- signing in ----------------------------------------------------------------------------

async function signIn(event) {
  event.preventDefault();
  clearProblem();
  apiKey.set($("key").value.trim());
  try {
    await getJSON("/jobs?limit=1"); // a wrong key is a 401 problem here, not later
  } catch (error) {
    apiKey.clear();
    showProblem(error);
    return;
  }
  $("key").value = "";
  start();
}

function signOut() {
  apiKey.clear();
  clearTimeout(listTimer);
  closeJob();
  clearProblem();
  $("job-table").tBodies[0].replaceChildren();
  showSignedIn(false);
}

function showSignedIn(signedIn) {
  $("sign-in").hidden = signedIn;
  $("signed-in").hidden = !signedIn;
  $("sign-out").hidden = !signedIn;
  $("who").hidden = !signedIn;
  $("who").textContent = signedIn ? `key ${apiKey.get().slice(0, 6)}…` : "";
}

function start() {
  showSignedIn(true);
  loadProcesses();
  refreshJobs();
  route();
}

async function loadProcesses() {
  try {
    const { processes } = await getJSON("/processes");
    const select = $("process");
    select.replaceChildren(element("option", "pipeline (default for the file)",
                                   { value: "pipeline" }));
    for (const p of processes) {
      if (p.id !== "pipeline") select.append(element("option", p.id, { value: p.id }));
    }
  } catch (error) {
    showProblem(error);
  }
}

// ---- submitting ----------------------------------------------------------------------------

async function submit(event) {
  event.preventDefault();
  clearProblem();
  const file = $("file").files[0];
  if (!file) return;
  let inputs = null;
  const text = $("inputs").value.trim();
  if (text) {
    try {
      inputs = JSON.parse(text);
    } catch (error) {
      showProblem(new Problem({ title: "Invalid inputs", detail: `not JSON: ${error.message}` }));
      return;
    }
  }
  $("submit").disabled = true;
  $("upload").hidden = false;
  const bar = $("upload-progress");
  const progress = (done, total) => {
    bar.value = total ? (100 * done) / total : 0;
    $("upload-text").textContent = `uploading ${file.name}: ${percent(done, total)}`;
  };
  progress(0, file.size);
  try {
    const job = await submitJob($("process").value, file, inputs, progress);
    $("upload-text").textContent = `${file.name} uploaded; job queued`;
    $("submit-form").reset();
    location.hash = `#/jobs/${job.jobID}`;
    refreshJobs();
  } catch (error) {
    $("upload-text").textContent = "upload failed";
    showProblem(error);
  } finally {
    $("submit").disabled = false;
  }
}

// ---- the job list --------------------------------------------------------------------------

async function refreshJobs() {
  clearTimeout(listTimer);
  if (!apiKey.get()) return;
  let active = false;
  try {
    const { jobs } = await getJSON("/jobs?limit=100");
    renderJobs(jobs);
    active = jobs.some((job) => ACTIVE.has(job.status));
  } catch (error) {
    showProblem(error);
    if (error.status === 401) return signOut();
  }
  listTimer = setTimeout(refreshJobs, active ? POLL_ACTIVE_MS : POLL_IDLE_MS);
}

function statusBadge(status) {
  return element("span", status, { class: `status ${status}` });
}

function renderJobs(jobs) {
  const body = $("job-table").tBodies[0];
  body.replaceChildren();
  $("no-jobs").hidden = jobs.length > 0;
  for (const job of jobs) {
    const row = body.insertRow();
    row.dataset.job = job.jobID;
    if (job.jobID === openJobId) row.classList.add("open");
    const link = element("a", job.input_file?.name || job.jobID, { href: `#/jobs/${job.jobID}` });
    const bar = element("progress", null, { max: "100", value: String(job.progress ?? 0) });
    const cells = [link, job.processID, statusBadge(job.status), bar,
                   new Date(job.created).toLocaleString()];
    for (const cell of cells) {
      const td = row.insertCell();
      if (cell instanceof Node) td.append(cell);
      else td.textContent = cell;
    }
    row.cells[3].append(element("span", ` ${job.progress ?? 0} %`, { class: "number" }));
  }
}

// ---- one job -------------------------------------------------------------------------------

function route() {
  const match = /^#\/jobs\/([^/]+)$/.exec(location.hash);
  if (match && apiKey.get()) openJob(decodeURIComponent(match[1]));
  else closeJob();
}

function closeJob() {
  clearTimeout(jobTimer);
  openJobId = null;
  view?.dispose();
  view = null;
  $("job").hidden = true;
  for (const id of ["statistics", "legend"]) $(id).replaceChildren();
  $("downloads").hidden = true;
  $("view-box").hidden = true;
}

function openJob(id) {
  closeJob();
  clearProblem();
  openJobId = id;
  for (const row of $("job-table").tBodies[0].rows) {
    row.classList.toggle("open", row.dataset.job === id);
  }
  $("dismiss").onclick = async () => {
    clearProblem();
    try {
      await request(`/jobs/${encodeURIComponent(id)}`, { method: "DELETE" });
      location.hash = "#/jobs";
      refreshJobs();
    } catch (error) {
      showProblem(error);
    }
  };
  pollJob(id);
}

async function pollJob(id) {
  let job;
  try {
    job = await getJSON(`/jobs/${encodeURIComponent(id)}`);
  } catch (error) {
    if (id === openJobId) {
      closeJob();
      showProblem(error);
    }
    return;
  }
  if (id !== openJobId) return;
  renderStatus(job);
  if (ACTIVE.has(job.status)) {
    jobTimer = setTimeout(() => pollJob(id), POLL_ACTIVE_MS);
  } else if (job.status === "successful") {
    showResults(job);
  }
}

function renderStatus(job) {
  $("job").hidden = false;
  $("job").dataset.status = job.status;
  $("job-title").textContent = `${job.input_file?.name || "job"} · ${job.processID}`;
  $("job-status").replaceWith(Object.assign(statusBadge(job.status), { id: "job-status" }));
  $("job-progress").value = job.progress ?? 0;
  $("job-message").textContent = `${job.progress ?? 0} % ${job.message ? `· ${job.message}` : ""}`;
  $("dismiss").textContent = ACTIVE.has(job.status) ? "Cancel job" : "Delete job";
  $("dismiss").hidden = job.status === "dismissed";
}

async function showResults(job) {
  const id = job.jobID;
  const base = `/jobs/${encodeURIComponent(id)}/results`;
  setDownloads(id, base, job);
  let points = null;
  let statistics;
  try {
    [statistics, points] = await Promise.all([
      getJSON(`${base}/statistics`),
      request(`${base}/points`).then((r) => r.arrayBuffer()).catch((error) => error),
    ]);
  } catch (error) {
    showProblem(error);
    return;
  }
  if (id !== openJobId) return;
  const { parsePoints } = await import("/app/static/viewer.js");
  const data = points instanceof ArrayBuffer ? parsePoints(points) : null;
  renderStatistics(job, statistics, data?.header.bits || {});
  if (data) await showView(id, data);
  else showProblem(points);
}

function setDownloads(id, base, job) {
  const stem = (job.input_file?.name || id).replace(/\.la[sz]$/i, "");
  const links = {
    "download-cloud": [`${base}/cloud`, `${stem}.flagged.${job.input_file?.compressed ? "laz" : "las"}`],
    "download-laz": [`${base}/cloud?format=laz`, `${stem}.flagged.laz`],
    "download-inliers": [`${base}/cloud?keep=inliers`, `${stem}.inliers.las`],
    "download-outliers": [`${base}/cloud?keep=outliers`, `${stem}.outliers.las`],
    "download-statistics": [`${base}/statistics`, `${stem}.statistics.json`],
  };
  for (const [linkId, [href, name]] of Object.entries(links)) {
    const link = $(linkId);
    link.href = href;
    link.onclick = async (event) => {
      event.preventDefault();
      clearProblem();
      const text = $("download-text");
      try {
        await saveFile(href, name, (done, total) => {
          text.textContent = `downloading ${name}: ${total ? percent(done, total) : count(done)}`;
        });
        text.textContent = `${name} saved`;
      } catch (error) {
        text.textContent = "";
        showProblem(error);
      }
    };
  }
  $("downloads").hidden = false;
}

// ---- statistics ----------------------------------------------------------------------------

function parameters(params) {
  const list = element("span", null, { class: "params" });
  for (const [name, value] of Object.entries(params || {})) {
    if (name === "detector") continue;
    const text = typeof value === "string" ? value : JSON.stringify(value);
    list.append(element("code", `${name}=${text}`), " ");
  }
  return list;
}

function renderStatistics(job, stats, bits) {
  const box = $("statistics");
  box.replaceChildren();
  const input = stats.input || {};
  const facts = job.input_file || {};
  box.append(table(["File", "Points", "LAS", "Point format", "GPS time"], [[
    facts.name, count(input.points ?? facts.points), input.las_version ?? facts.las_version,
    input.point_format ?? facts.point_format, (input.has_gps_time ?? facts.has_gps_time) ? "yes" : "no",
  ]], "Input"));
  if (stats.pipeline_source === "default") {
    box.append(element("p", `Default pipeline of the ${stats.profile} profile: `
                        + `${stats.profile_reason || ""}`, { class: "hint" }));
  }
  const stages = (stats.stages || []).map((stage, i) => [
    i + 1, stage.detector, count(stage.points_in), count(stage.points_tested),
    stage.skipped ? stage.skipped : count(stage.points_flagged), parameters(stage.params),
    stage.seconds === undefined ? "" : stage.seconds.toFixed(2),
  ]);
  const stageTable = table(["#", "Detector", "Points in", "Tested", "Flagged", "Parameters",
                            "Seconds"], stages, "Stages");
  stageTable.id = "stage-table";
  box.append(stageTable);
  const overall = stats.overall || {};
  const ran = new Set((stats.stages || []).map((s) => s.detector));
  const rows = Object.entries(overall.flagged_by_bit || {})
    .filter(([name, n]) => n > 0 || ran.has(name))
    .map(([name, n]) => [bits[name] ?? "", name, count(n), percent(n, overall.points)]);
  rows.push(["any", "all detectors", count(overall.points_flagged),
             percent(overall.points_flagged, overall.points)]);
  const flagTable = table(["Bit", "Detector", "Points flagged", "Share"], rows,
                          "Flagged by detector (outlier_flags)");
  flagTable.id = "flag-table";
  box.append(flagTable);
}

// ---- the 3-D view --------------------------------------------------------------------------

async function showView(id, data) {
  const { CloudView, detectorColours } = await import("/app/static/viewer.js");
  if (id !== openJobId) return; // another job was opened meanwhile
  $("view-box").hidden = false;
  try {
    view = new CloudView($("viewer"));
  } catch (error) {
    $("view-note").textContent = `No 3-D view: this browser cannot draw WebGL (${error.message}).`;
    return;
  }
  view.show(data);
  const { header } = data;
  const legend = $("legend");
  legend.replaceChildren();
  const toggle = (label, colour, onChange) => {
    const box = element("input", null, { type: "checkbox" });
    box.checked = true;
    box.addEventListener("change", () => onChange(box.checked));
    const swatch = element("span", null, { class: "swatch" });
    swatch.style.background = colour;
    const wrapper = element("label");
    wrapper.append(box, swatch, label);
    legend.append(wrapper);
    return box;
  };
  const kept = header.points - data.flags.filter((f) => f !== 0).length;
  toggle(`unflagged (${count(kept)})`, "#9aa5b4", (on) => view.setKept(on));
  const colours = detectorColours(header.bits);
  for (const [name, n] of Object.entries(view.counts())) {
    toggle(`${name} (${count(n)})`, colours[name], (on) => view.setDetector(name, on))
      .dataset.detector = name;
  }
  $("view-note").textContent = (header.points < header.total
    ? `${count(header.points)} of ${count(header.total)} points: every flagged point, the rest `
      + "spread evenly. "
    : `All ${count(header.total)} points. `)
    + "Drag to orbit, scroll to zoom, right-drag to pan.";
}

// ---- start ---------------------------------------------------------------------------------

$("sign-in-form").addEventListener("submit", signIn);
$("sign-out").addEventListener("click", signOut);
$("submit-form").addEventListener("submit", submit);
window.addEventListener("hashchange", route);
if (apiKey.get()) start();
else showSignedIn(false);

// The page of stereo-bench serve: a form over the rig file's data, validated by the server
// (the same schema as the YAML), previews, jobs and past runs. No library, nothing remote.
"use strict";
let config = null;          // the resolved rig, as the server last validated it
let pending = null;         // debounce timer of validation
const $ = s => document.querySelector(s);
const CAMERA_FIELDS = ["name", "width", "height", "fx", "fy", "cx", "cy", "dist", "position_mm",
                       "look_at_mm"];
const LISTS = new Set(["dist", "position_mm", "look_at_mm"]);

async function post(url, body, binary) {
  const r = await fetch(url, {method: "POST", headers: {"Content-Type": "application/json"},
                              body: JSON.stringify(body)});
  if (binary && r.ok) return r;
  const data = await r.json();
  if (!r.ok && !data.errors) data.errors = [JSON.stringify(data)];
  return data;
}
const get = (obj, path) => path.split(".").reduce((o, k) => (o == null ? o : o[k]), obj);
function set(obj, path, value) {
  const keys = path.split("."), last = keys.pop();
  const parent = keys.reduce((o, k) => (o[k] = o[k] ?? {}), obj);
  parent[last] = value;
}
const numberOr = text => (text.trim() !== "" && !isNaN(Number(text)) ? Number(text) : text);

function fill(cfg) {
  config = cfg;
  document.querySelectorAll("[data-path]").forEach(el => {
    const v = get(cfg, el.dataset.path);
    el.value = v ?? "";
  });
  const body = $("#cameras tbody");
  body.innerHTML = "";
  cfg.cameras.forEach((cam, i) => {
    const tr = document.createElement("tr");
    CAMERA_FIELDS.forEach(f => {
      const td = document.createElement("td"), input = document.createElement("input");
      input.value = LISTS.has(f) ? cam[f].join(" ") : cam[f];
      input.dataset.camera = i; input.dataset.field = f;
      if (LISTS.has(f)) input.className = "wide";
      input.addEventListener("change", edited);
      td.appendChild(input); tr.appendChild(td);
    });
    const td = document.createElement("td"), rm = document.createElement("button");
    rm.textContent = "remove"; rm.type = "button";
    rm.addEventListener("click", () => { config.cameras.splice(i, 1); validate(); });
    td.appendChild(rm); tr.appendChild(td); body.appendChild(tr);
  });
  const cams = $("#p-camera"), keep = cams.value;
  cams.innerHTML = cfg.cameras.map((c, i) => `<option value="${i}">${c.name}</option>`).join("");
  if (keep && Number(keep) < cfg.cameras.length) cams.value = keep;
  $("#p-frame").max = Math.max(cfg.trajectory.frames - 1, 0);
}

function edited(e) {
  const el = e.target, next = structuredClone(config);
  if (el.dataset.field) {
    const cam = next.cameras[Number(el.dataset.camera)], f = el.dataset.field;
    cam[f] = LISTS.has(f) ? el.value.trim().split(/[\s,]+/).map(Number)
                          : (f === "name" ? el.value : numberOr(el.value));
  } else if (el.dataset.path.endsWith(".kind") && el.dataset.path !== "renderer.kind") {
    // A new kind describes another board or situation: its own defaults fill the section.
    set(next, el.dataset.path.split(".")[0], {kind: el.value});
  } else {
    set(next, el.dataset.path, el.type === "number" ? numberOr(el.value) : el.value);
  }
  validate(next);
}

let asked = 0;  // validations sent: an answer to an older one is dropped (answers can cross)
function validate(next) {
  clearTimeout(pending);
  pending = setTimeout(async () => {
    const mine = ++asked;
    const answer = await post("/api/validate", {config: next ?? config});
    if (mine === asked) show(answer);
  }, 150);
}

function show(answer) {
  const errors = $("#errors");
  errors.innerHTML = "";
  if (!answer.ok) {
    answer.errors.forEach(t => { const li = document.createElement("li"); li.textContent = t;
                                 errors.appendChild(li); });
    return false;
  }
  fill(answer.config);
  $("#yaml").textContent = answer.yaml;
  refreshPreview();
  return true;
}

let previews = 0;  // as for validations: only the newest preview is shown
async function refreshPreview() {
  const camera = Number($("#p-camera").value || 0), frame = Number($("#p-frame").value || 0);
  const mine = ++previews;
  const r = await post("/api/preview", {config, camera, frame}, true);
  if (mine !== previews) return;
  if (r.ok) {
    $("#p-image").src = URL.createObjectURL(await r.blob());
    $("#p-info").textContent = `${r.headers.get("X-Camera")}, frame ${frame + 1}/` +
      `${r.headers.get("X-Frames")}: ${r.headers.get("X-Visible-Points")} points in view`;
  } else {
    $("#p-info").textContent = (await r.json()).errors.join("; ");
  }
  const t = await post("/api/trajectory", {config}, true);
  if (t.ok) $("#p-trajectory").src = URL.createObjectURL(await t.blob());
}

// Server text (an error quoting a value the user typed) is shown as text, never as markup.
const text = s => String(s).replace(/[&<>"']/g, c => `&#${c.charCodeAt(0)};`);

function jobView(job) {
  const done = job.state === "done", failed = job.state === "failed";
  const active = job.state === "queued" || job.state === "running";
  const bar = job.total ? `<progress max="${job.total}" value="${job.done}"></progress>` : "";
  const link = done ? ` <a class="report" href="${job.report}" target="_blank">report</a>` : "";
  const stop = active ? ` <button class="cancel" onclick="cancelJob(${job.id})">cancel</button>` : "";
  return `<div class="job ${job.state}" id="job-${job.id}"><b>${job.kind} ${text(job.name)}</b>: ` +
    `<span class="state">${job.state}</span> ${text(job.stage)} ${bar} ` +
    `${job.total ? job.done + "/" + job.total : ""} (${job.seconds.toFixed(0)} s)` +
    `${failed ? " <span class='errors'>" + text(job.error) + "</span>" : ""}${link}${stop}</div>`;
}

async function cancelJob(id) {
  await fetch(`/api/jobs/${id}/cancel`, {method: "POST"});
}

async function deleteRun(name) {
  if (!confirm(`Delete the run folder ${name} and everything in it?`)) return;
  const r = await fetch(`/api/runs/${encodeURIComponent(name)}`, {method: "DELETE"});
  if (!r.ok) alert((await r.json()).errors.join("; "));
  listRuns();
}

async function follow(job) {
  const box = $("#jobs");
  if (job.errors) { box.insertAdjacentHTML("afterbegin", `<div class="job failed">` +
                    text(job.errors.join("; ")) + "</div>"); return; }
  box.insertAdjacentHTML("afterbegin", jobView(job));
  while (job.state === "queued" || job.state === "running") {
    await new Promise(r => setTimeout(r, 500));
    job = await (await fetch(`/api/jobs/${job.id}`)).json();
    $(`#job-${job.id}`).outerHTML = jobView(job);
  }
  listRuns();
}

async function listRuns() {
  const runs = await (await fetch("/api/runs")).json();
  $("#run-list").innerHTML = runs.map(r =>
    `<li><a href="${r.report}" target="_blank">${r.name}</a> (${r.kind}, ` +
    `${new Date(r.modified * 1000).toLocaleString()}) ` +
    `<button class="delete" onclick="deleteRun('${r.name}')">delete</button></li>`).join("");
  const options = runs.filter(r => r.kind === "report")
    .map(r => `<option>${r.name}</option>`).join("");
  $("#c-a").innerHTML = options; $("#c-b").innerHTML = options;
  if (runs.length > 1) $("#c-b").selectedIndex = 1;
}

function download() {
  const blob = new Blob([$("#yaml").textContent], {type: "application/x-yaml"});
  const a = document.createElement("a");
  a.href = URL.createObjectURL(blob); a.download = `${config.name}.yaml`; a.click();
}

addEventListener("DOMContentLoaded", async () => {
  document.querySelectorAll("[data-path]").forEach(el => el.addEventListener("change", edited));
  $("#p-camera").addEventListener("change", refreshPreview);
  $("#p-frame").addEventListener("change", refreshPreview);
  $("#b-add-camera").addEventListener("click", () => {
    const last = config.cameras[config.cameras.length - 1];
    const copy = structuredClone(last);
    copy.name = `${last.name}_${config.cameras.length + 1}`;
    copy.position_mm = copy.position_mm.map((v, i) => (i === 0 ? v + 150 : v));
    config.cameras.push(copy); validate();
  });
  $("#b-save").addEventListener("click", download);
  $("#f-load").addEventListener("change", async e => {
    const text = await e.target.files[0].text();
    show(await post("/api/yaml", {text}));
  });
  $("#b-run").addEventListener("click", async () =>
    follow(await post("/api/runs", {name: $("#r-name").value, config})));
  $("#b-sweep").addEventListener("click", async () =>
    follow(await post("/api/sweeps", {name: $("#r-name").value, config,
                                     axes: $("#s-axes").value,
                                     trials: Number($("#s-trials").value)})));
  $("#b-compare").addEventListener("click", () =>
    open(`/compare?a=${encodeURIComponent($("#c-a").value)}&b=` +
         `${encodeURIComponent($("#c-b").value)}`, "_blank"));
  show({ok: true, config: await (await fetch("/api/example")).json(), yaml: ""});
  validate();
  listRuns();
});

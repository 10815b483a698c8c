// The venue console: tiles, controls and takes over the console's WebSocket and JSON API (rig/console/server.py).
// State the tests read: document.body.dataset (connected, activity, recording, statusAt), each tile's
// data-* (camera, health, fps, previews, exposure), window.rigConsole.
"use strict";
const $ = (s, el = document) => el.querySelector(s);
const state = { status: null, tiles: {}, prefs: { rate: 5, width: 320, sizes: {}, overlay: [] }, zoomed: null, ws: null,
                notesTimer: null, lastTake: null, statusCount: 0 };
window.rigConsole = state;

function api(method, path, body) {
  return fetch(path, { method, headers: body ? { "Content-Type": "application/json" } : {}, body: body ? JSON.stringify(body) : undefined,
                       credentials: "same-origin" })
    .then(async r => { const data = await r.json().catch(() => ({ error: `HTTP ${r.status}` })); if (!r.ok) throw new Error(data.error || `HTTP ${r.status}`); return data; });
}

// After a change, the state it led to at once (not at the next status push).
function refresh() { return api("GET", "api/status").then(onStatus).catch(() => {}); }

function fmt(v, digits = 1, unit = "") { return v === null || v === undefined ? "–" : `${Number(v).toFixed(digits)}${unit}`; }

function tile(cam) {
  let t = state.tiles[cam.name];
  if (t) return t;
  const el = document.createElement("div");
  el.className = "tile";
  el.dataset.camera = cam.name;
  el.dataset.previews = "0";
  el.innerHTML = `<div class="head"><b class="name"></b> <span class="role badge"></span></div>
    <div class="frame"><img alt=""><canvas class="board-overlay"></canvas></div>
    <canvas class="hist" width="128" height="32"></canvas>
    <div class="figures"><span class="fps"></span><span class="dropped"></span><span class="age"></span><span class="clipped"></span></div>
    <div class="controls">exposure <input type="number" step="any" class="exposure" data-control="exposure"> µs
      gain <input type="number" step="any" class="gain" data-control="gain"> dB
      <button data-action="set-controls">set</button>
      <label><input type="checkbox" class="overlay" data-control="overlay"> clipped</label></div>
    <div class="reported hint"></div><div class="control-error error"></div>`;
  $(".name", el).textContent = cam.name;
  $(".role", el).textContent = cam.role;
  $("#tiles").appendChild(el);
  t = { el, url: null, stats: null, previews: 0 };
  state.tiles[cam.name] = t;
  $("img", el).addEventListener("click", () => zoom(cam.name));
  $(".board-overlay", el).addEventListener("click", () => zoom(cam.name));
  $("button", el).addEventListener("click", () => setControls(cam.name, $(".exposure", el).value, $(".gain", el).value, $(".control-error", el)));
  $(".overlay", el).addEventListener("change", e => {
    const o = new Set(state.prefs.overlay); e.target.checked ? o.add(cam.name) : o.delete(cam.name);
    state.prefs.overlay = [...o]; sendPrefs();
  });
  return t;
}

function parseNumber(text, what) {
  if (text === "" || text === null) return null;
  const v = Number(text);
  if (!Number.isFinite(v)) throw new Error(`${what} must be a number, got ${JSON.stringify(text)}`);
  return v;
}

function setControls(camera, exposure, gain, errorEl) {
  errorEl.textContent = "";
  let body;
  try { body = { camera, exposure_us: parseNumber(exposure, "exposure"), gain: parseNumber(gain, "gain") }; }
  catch (e) { errorEl.textContent = e.message; return Promise.resolve(); }
  if (body.exposure_us === null) delete body.exposure_us;
  if (body.gain === null) delete body.gain;
  document.body.dataset.controlsPending = "1";
  return api("POST", "api/controls", body).then(res => {
    const failed = Object.entries(res).filter(([, r]) => !r.ok).map(([n, r]) => `${n}: ${r.error}`);
    errorEl.textContent = failed.join("; ");
  }).catch(e => { errorEl.textContent = e.message; }).finally(() => { document.body.dataset.controlsPending = "0"; refresh(); });
}

function drawHist(canvas, hist) {
  const g = canvas.getContext("2d"), w = canvas.width, h = canvas.height;
  g.clearRect(0, 0, w, h);
  if (!hist) return;
  const top = Math.max(...hist, 1e-6);
  g.fillStyle = "#9e9e9e";
  hist.forEach((v, i) => { const bh = (v / top) * h; g.fillRect(i * w / hist.length, h - bh, w / hist.length - 1, bh); });
  g.fillStyle = "#ef5350";
  g.fillRect(w - w / hist.length, h - (hist[hist.length - 1] / top) * h, w / hist.length, (hist[hist.length - 1] / top) * h);
}

function zoom(name) {
  state.zoomed = name;
  const z = $("#zoom");
  z.hidden = false;
  z.dataset.camera = name;
  state.prefs.sizes = { [name]: 960 };
  sendPrefs();
}
$("#zoom").addEventListener("click", () => { $("#zoom").hidden = true; state.zoomed = null; state.prefs.sizes = {}; sendPrefs(); });

function onPreview(buf) {
  const view = new DataView(buf);
  const n = view.getUint32(0);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
  const jpeg = new Blob([new Uint8Array(buf, 4 + n)], { type: "image/jpeg" });
  const t = state.tiles[header.camera];
  if (!t) return ack(header.camera);
  const url = URL.createObjectURL(jpeg);
  const img = $("img", t.el);
  img.onload = () => { if (t.url) URL.revokeObjectURL(t.url); t.url = url; t.previews++; t.el.dataset.previews = String(t.previews);
                       t.el.dataset.seq = String(header.seq); ack(header.camera); };
  img.onerror = () => ack(header.camera);
  img.src = url;
  t.stats = header;
  drawHist($(".hist", t.el), header.histogram);
  $(".clipped", t.el).textContent = `clipped ${fmt(100 * header.clipped, 1, " %")}`;
  if (state.zoomed === header.camera) {
    $("#zoom img").src = url;
    drawHist($("#zoom canvas"), header.histogram);
    $("#zoom p").textContent = `${header.camera}: clipped ${fmt(100 * header.clipped, 2, " %")}`;
  }
}

function ack(camera) { if (state.ws && state.ws.readyState === 1) state.ws.send(JSON.stringify({ type: "ack", camera })); }
function sendPrefs() { if (state.ws && state.ws.readyState === 1) state.ws.send(JSON.stringify({ type: "prefs", ...state.prefs })); }

function onStatus(s) {
  state.status = s;
  state.statusCount++;
  document.body.dataset.statusAt = String(performance.now());
  document.body.dataset.activity = s.activity;
  if (document.body.dataset.recording !== s.recording.state) document.body.dataset.recordingChangedAt = String(performance.now());
  document.body.dataset.recording = s.recording.state;
  document.body.dataset.role = s.role;
  $("#rig-name").textContent = s.rig;
  $("#activity").textContent = s.activity;
  $("#role").textContent = s.role;
  for (const cam of s.cameras) {
    const t = tile(cam), el = t.el;
    el.dataset.health = cam.health;
    el.dataset.fps = cam.fps === null ? "" : String(cam.fps);
    const exposure = cam.exposure_us === null ? "" : String(cam.exposure_us), gain = cam.gain === null ? "" : String(cam.gain);
    if (el.dataset.exposure !== exposure || el.dataset.gain !== gain) el.dataset.changedAt = String(performance.now());
    el.dataset.exposure = exposure;
    el.dataset.gain = gain;
    $(".fps", el).textContent = `${fmt(cam.fps, 1)} / ${fmt(cam.target_fps, 0)} fps`;
    $(".dropped", el).textContent = `dropped ${cam.dropped}`;
    $(".age", el).textContent = `last ${cam.age_s === null ? "never" : fmt(1000 * cam.age_s, 0, " ms")} ago`;
    const r = cam.ranges || {};
    $(".reported", el).textContent = `camera reports: exposure ${fmt(cam.exposure_us, 0, " µs")}, gain ${fmt(cam.gain, 1, " dB")}`
      + (r.exposure_us ? ` (exposure ${r.exposure_us[0]}–${Math.round(r.exposure_us[1])} µs)` : "") + (cam.live_controls ? "" : " · set at open only");
    if (cam.control_error) $(".control-error", el).textContent = cam.control_error;
    drawBoard($(".board-overlay", el), cam.board, cam.size);
    el.dataset.board = cam.board ? (cam.board.still ? "still" : "seen") : "";
  }
  const rec = s.recording, running = ["starting", "recording", "stopping"].includes(rec.state);
  const operator = s.role === "operator", h0 = s.health, cal = s.calibration || {};
  document.querySelectorAll("[data-action]").forEach(b => {
    const a = b.dataset.action;
    if (a === "stop") b.disabled = !operator || rec.state !== "recording";
    else if (a === "doctor") b.disabled = !operator || s.activity !== "previewing" || (h0 && h0.state === "running");
    else if (["record", "sync-check"].includes(a)) b.disabled = !operator || s.activity !== "previewing";
    else if (a === "calibrate") b.disabled = !operator || s.activity !== "previewing";
    else if (["capture-view", "calibrate-stop"].includes(a)) b.disabled = !operator || !["starting", "capturing"].includes(cal.state);
    else if (a === "solve") b.disabled = !operator || !cal.views || cal.state === "solving";
    else if (a === "live-stop") b.disabled = !operator || !s.live || s.live.state !== "running";
    else if (["set-controls", "set-all"].includes(a)) b.disabled = !operator || s.activity === "starting" || s.activity === "idle";
  });
  $("#take-name").disabled = running || !operator;
  $("#take-timer").textContent = running || rec.state === "done" ? clock(rec.elapsed_s) : "0:00";
  $("#record-error").textContent = rec.error || "";
  const figures = running || rec.summary ? [["take", rec.take], ["state", rec.state], ["sets", rec.sets], ["lost", rec.lost],
    ["write", fmt(rec.write_mb_per_s, 1, " MB/s")], ["disk", fmt(rec.disk_mb_per_s, 0, " MB/s")],
    ["free", s.disk.free_bytes === null ? "–" : fmt(s.disk.free_bytes / 1e9, 1, " GB")], ["minutes left", fmt(rec.minutes_left, 0)]] : [];
  $("#record-figures tbody").innerHTML = figures.map(([k, v]) => `<tr><td>${k}</td><td data-figure="${k}">${escape(v)}</td></tr>`).join("");
  $("#takes tbody").innerHTML = s.takes.map(t => {
    const v = t.validation || {};
    const st = v.state || (v.readable ? "valid" : `invalid: ${(v.errors || []).join("; ")}`);
    return `<tr data-take="${escape(t.take)}" data-valid="${v.readable ? "true" : "false"}"><td>${escape(t.take)}</td><td>${escape(st)}</td>`
      + `<td>${v.sets ?? ""}</td><td>${v.duration_s ?? ""}</td></tr>`;
  }).join("");
  $("#events").innerHTML = s.events.slice().reverse().map(e => `<li class="${e.level}">${new Date(1000 * e.time).toLocaleTimeString()} ${escape(e.kind)}: ${escape(e.detail)}</li>`).join("");
  showSync(s.sync);
  $("#banners").innerHTML = (s.faults || []).map(f => `<div class="${f.level}" data-fault="${escape(f.kind)}">${escape(f.detail)}</div>`).join("");
  document.body.dataset.faults = (s.faults || []).map(f => f.kind).join(" ");
  const h = s.health;
  $("#doctor-verdict").textContent = h ? (h.state === "done" ? h.verdict : h.state) : "";
  document.body.dataset.doctor = h ? (h.verdict || h.state) : "";
  $("#doctor tbody").innerHTML = h && h.checks ? h.checks.map(c => `<tr class="${c.status}"><td>${escape(c.status)}</td><td>${escape(c.area)}</td>`
    + `<td>${escape(c.name)}</td><td>${escape(c.measured)}</td><td>${escape(c.needed)}</td><td><code>${escape(c.fix || "")}</code></td></tr>`).join("")
    : (h && h.error ? `<tr><td class="error">${escape(h.error)}</td></tr>` : "");
  showLive(s.live || { state: "off" });
  showCalibration(cal);
  if (!running && rec.take && rec.take !== state.lastTake && rec.state !== "idle") {
    state.lastTake = rec.take;
    api("GET", `api/take-name?after=${encodeURIComponent(rec.take)}`).then(r => { if (!$("#take-name").matches(":focus")) $("#take-name").value = r.take; });
  }
}

function showSync(y) {
  const b = y.board || {}, k = y.skew_us || {};
  const rows = [["rate", fmt(y.rate_hz, 1, " Hz")], ["pulses", b.pulses ?? "–"], ["lost pulses", b.lost_pulses ?? "–"],
    ["clock residual p99", fmt(b.clock_residual_p99_us, 1, " µs")], ["exposure skew p50 / p99", `${fmt(k.p50, 1)} / ${fmt(k.p99, 1)} µs`],
    ["board", b.connected === undefined ? "none" : (b.connected ? "connected" : `lost: ${b.last_error || ""}`)]];
  for (const [name, c] of Object.entries(y.cameras || {})) rows.push([`${name} drops`, `${c.drops ?? 0} (missed triggers ${c.missed_triggers ?? 0})`]);
  $("#sync-figures tbody").innerHTML = rows.map(([n, v]) => `<tr><td>${escape(n)}</td><td data-figure="${escape(n)}">${escape(v)}</td></tr>`).join("");
  const c = y.check;
  const verdict = !c ? "" : (c.state === "done" ? c.verdict : c.state === "failed" ? "failed" : `${c.state}…`);
  $("#sync-verdict").textContent = verdict;
  document.body.dataset.syncCheck = c ? c.state : "";
  document.body.dataset.syncVerdict = c && c.verdict ? c.verdict : "";
  $("#sync-error").textContent = c && c.error ? c.error : "";
  $("#sync-failures").innerHTML = c && c.failures ? c.failures.map(f => `<li>${escape(f)}</li>`).join("") : "";
}

function escape(v) { return String(v ?? "").replace(/[&<>"]/g, c => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c])); }
function clock(s) { s = Math.max(0, s || 0); return `${Math.floor(s / 60)}:${String(Math.floor(s % 60)).padStart(2, "0")}`; }

function connect() {
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}${location.pathname.replace(/[^/]*$/, "")}ws`);
  ws.binaryType = "arraybuffer";
  state.ws = ws;
  ws.onopen = () => { document.body.dataset.connected = "true"; sendPrefs(); };
  ws.onmessage = ev => {
    if (typeof ev.data !== "string") return onPreview(ev.data);
    const m = JSON.parse(ev.data);
    if (m.type === "status") onStatus(m);
    else if (m.type === "error") console.warn("console:", m.error);
  };
  ws.onclose = () => { document.body.dataset.connected = "false"; setTimeout(connect, 1000); };
}

// When the last control was clicked (the tests measure click-to-state on the page's own clock).
document.addEventListener("click", e => { if (e.target.closest("[data-action]")) document.body.dataset.clickAt = String(performance.now()); }, true);
$("#preview-rate").addEventListener("change", e => { state.prefs.rate = Number(e.target.value); sendPrefs(); });
document.querySelector('[data-action="set-all"]').addEventListener("click", () =>
  setControls("*", $("#all-exposure").value, $("#all-gain").value, $("#all-error")));
document.querySelector('[data-action="record"]').addEventListener("click", () => {
  $("#record-error").textContent = "";
  const take = $("#take-name").value.trim();
  api("POST", "api/record/start", { take: take || undefined, notes: $("#take-notes").value })
    .then(t => { $("#take-name").value = t.take; return refresh(); }).catch(e => { $("#record-error").textContent = e.message; });
});
document.querySelector('[data-action="stop"]').addEventListener("click", () =>
  api("POST", "api/record/stop").then(refresh).catch(e => { $("#record-error").textContent = e.message; }));
document.querySelector('[data-action="sync-check"]').addEventListener("click", () => {
  $("#sync-error").textContent = "";
  let seconds;
  try { seconds = parseNumber($("#sync-seconds").value, "seconds"); } catch (e) { $("#sync-error").textContent = e.message; return; }
  api("POST", "api/sync-check", seconds === null ? {} : { seconds }).then(refresh).catch(e => { $("#sync-error").textContent = e.message; });
});
document.querySelector('[data-action="doctor"]').addEventListener("click", () => api("POST", "api/doctor").then(refresh).catch(() => {}));
$("#take-notes").addEventListener("input", () => {
  clearTimeout(state.notesTimer);
  $("#notes-saved").textContent = "…";
  state.notesTimer = setTimeout(saveNotes, 300);
});
function saveNotes() {
  const take = $("#take-name").value.trim();
  if (!take) { $("#notes-saved").textContent = "give the take a name to keep its notes"; return; }
  api("PUT", "api/notes", { take, text: $("#take-notes").value })
    .then(() => { $("#notes-saved").textContent = "saved"; document.body.dataset.notesSaved = String(Date.now()); })
    .catch(e => { $("#notes-saved").textContent = e.message; });
}
api("GET", "api/take-name").then(r => { if (!$("#take-name").value) $("#take-name").value = r.take; }).catch(() => {});
connect();

// The Live tab: `rig live`'s own viewer (served at live/ by the console) in a frame, started on the
// first visit by an operator; a viewer token watches it once an operator has started it.
function showTab(name) {
  document.body.dataset.tab = name;
  document.querySelectorAll("nav.tabs [data-tab]").forEach(b => b.classList.toggle("on", b.dataset.tab === name));
  $("main").hidden = name !== "rig";
  $("#live-panel").hidden = name !== "live";
}
function showLive(live) {
  document.body.dataset.live = live.state;
  $("#live-state").textContent = live.state;
  $("#live-error").textContent = live.error || "";
  $("#live-figures").textContent = live.state === "running" ? `in ${fmt(live.fps_in, 1)} fps · out ${fmt(live.fps_out, 1)} fps` : "";
  const frame = $("#live-frame"), want = live.state === "running" && document.body.dataset.tab === "live" ? "live/" : "about:blank";
  if (frame.getAttribute("src") !== want) frame.setAttribute("src", want);
}
document.querySelector('[data-tab="rig"]').addEventListener("click", () => { showTab("rig"); refresh(); });
document.querySelector('[data-action="live"]').addEventListener("click", () => {
  showTab("live");
  const live = state.status && state.status.live;
  if (state.status && state.status.role === "operator" && (!live || live.state === "off")) {
    $("#live-state").textContent = "starting";
    api("POST", "api/live/start").then(refresh).catch(e => { $("#live-error").textContent = e.message; });
  } else refresh();
});
document.querySelector('[data-action="live-stop"]').addEventListener("click", () =>
  api("POST", "api/live/stop").then(refresh).catch(e => { $("#live-error").textContent = e.message; }));
showTab("rig");

// Calibration: the board found in each still drawn over its tile (green once it is held still),
// coverage per camera (the 8x6 cells of its image the kept views covered) and per pair of cameras.
function drawBoard(canvas, board, size) {
  const g = canvas.getContext("2d");
  if (!board || !size) { canvas.hidden = true; return; }
  canvas.hidden = false;
  if (canvas.width !== size[0] || canvas.height !== size[1]) { canvas.width = size[0]; canvas.height = size[1]; }
  g.clearRect(0, 0, canvas.width, canvas.height);
  g.fillStyle = board.still ? "#66bb6a" : "#ffca28";
  const r = Math.max(1.5, canvas.width / 320);
  for (const [x, y] of board.points) g.fillRect(x - r, y - r, 2 * r, 2 * r);
}
function coverageMap(cells) {
  const rows = cells.length, cols = rows ? cells[0].length : 0;
  return `<span class="cells" style="grid-template-columns: repeat(${cols}, 8px)">`
    + cells.flat().map(c => `<i class="${c ? "on" : ""}"></i>`).join("") + "</span>";
}
function showCalibration(c) {
  document.body.dataset.calibration = c.state || "off";
  document.body.dataset.calibrationViews = String(c.views || 0);
  document.body.dataset.calibrationReady = c.ready ? "true" : "false";
  $("#cal-state").textContent = c.state === "capturing" ? `capturing · ${c.views} views of ${c.looked} sets` : (c.state || "off");
  if (document.activeElement !== $("#cal-auto")) $("#cal-auto").checked = c.auto !== false;
  $("#cal-last").textContent = c.last ? `last set: ${c.last}` + (c.decision && c.decision !== c.last ? ` · last view: ${c.decision}` : "")
    : (c.board ? `board: ${c.board}` : "no board file: start the console with --board BOARD.toml");
  $("#cal-error").textContent = c.error || "";
  $("#cal-ready").innerHTML = c.views === undefined ? "" : (c.ready ? `<b class="ok">coverage passes</b> (the report's limits): solve when you like`
    : `still needed: <ul>${(c.needs || []).map(n => `<li>${escape(n)}</li>`).join("")}</ul>`);
  $("#cal-coverage").innerHTML = c.coverage ? Object.entries(c.coverage).map(([n, v]) =>
    `<div class="cov" data-coverage="${escape(n)}">${coverageMap(c.cells[n])} <b>${escape(n)}</b> ${fmt(100 * v, 0, " %")} · ${c.views_per_camera[n]} views</div>`).join("") : "";
  $("#cal-pairs").innerHTML = c.pairs && c.pairs.length ? "<tr><th>pair</th><th>views together</th></tr>"
    + c.pairs.map(p => `<tr><td>${escape(p.a)}–${escape(p.b)}</td><td>${p.views}</td></tr>`).join("") : "";
  const r = c.result;
  $("#cal-report").textContent = r ? (r.written ? `wrote ${r.written}` + (r.previous ? ` (the previous calibration kept as ${r.previous})` : "") + "\n\n" : "")
    + r.report : "";
  document.body.dataset.calibrationWritten = r && r.written ? r.written : "";
}
function calibrationCall(path, body) {
  $("#cal-error").textContent = "";
  return api("POST", path, body).then(refresh).catch(e => { $("#cal-error").textContent = e.message; });
}
document.querySelector('[data-action="calibrate"]').addEventListener("click", () => calibrationCall("api/calibration/start", { auto: $("#cal-auto").checked }));
document.querySelector('[data-action="capture-view"]').addEventListener("click", () => calibrationCall("api/calibration/capture"));
document.querySelector('[data-action="calibrate-stop"]').addEventListener("click", () => calibrationCall("api/calibration/stop"));
document.querySelector('[data-action="solve"]').addEventListener("click", () => calibrationCall("api/calibration/solve"));
$("#cal-auto").addEventListener("change", e => {
  const c = state.status && state.status.calibration;
  if (c && ["starting", "capturing"].includes(c.state)) calibrationCall("api/calibration/auto", { auto: e.target.checked });
});

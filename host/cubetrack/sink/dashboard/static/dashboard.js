// cubetrack dashboard: renders what the JSON endpoints say (GET /api/state) and follows the
// server-sent events (GET /api/events). It keeps no state of its own beyond that copy:
// everything shown here can be read from the API (docs/dashboard.md).
"use strict";

const model = { session: null, cameras: new Map(), topview: null, panels: {}, actions: {}, files: [] };
const $ = (sel, root = document) => root.querySelector(sel);

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === null || v === undefined || v === false) continue;
    if (k === "class") node.className = v; else if (k === "text") node.textContent = v;
    else if (k.startsWith("on")) node.addEventListener(k.slice(2), v); else node.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children.flat()) if (c !== null && c !== undefined && c !== false) node.append(c);
  return node;
}

const svgNS = "http://www.w3.org/2000/svg";
function svg(tag, attrs = {}, text) {
  const node = document.createElementNS(svgNS, tag);
  for (const [k, v] of Object.entries(attrs)) if (v !== null && v !== undefined) node.setAttribute(k, v);
  if (text !== undefined) node.textContent = text;
  return node;
}

const fmt = (v, digits = 1, unit = "") => (v === null || v === undefined || Number.isNaN(v)) ? "–" : v.toFixed(digits) + unit;

function showMessage(text) {
  const m = $("#message");
  m.textContent = text || "";
  m.hidden = !text;
}

async function getJSON(path) {
  const r = await fetch(path, { cache: "no-store" });
  if (!r.ok) throw new Error(`${path}: HTTP ${r.status}`);
  return r.json();
}

async function act(panel, action, body = {}) {
  showMessage("");
  const r = await fetch(`/api/${encodeURIComponent(panel)}/${encodeURIComponent(action)}`, {
    method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
  const answer = await r.json().catch(() => ({ error: `HTTP ${r.status}` }));
  if (answer.panel) setPanel(panel, answer.panel);
  if (!r.ok) showMessage(answer.error || `HTTP ${r.status}`);
  return answer;
}

// --- session ---

function renderSession() {
  const s = model.session;
  const state = $("#session-state");
  state.textContent = s ? `session ${s.state}` : "no session";
  state.className = "pill " + (s && s.state === "running" ? "ok" : "wait");
  const cal = $("#session-calibrated");
  if (s && s.calibrated !== undefined) {
    cal.textContent = s.calibrated ? "calibrated" : "not calibrated";
    cal.className = "pill " + (s.calibrated ? "ok" : "wait");
  }
  const rec = model.panels.recording;
  $("#session-mode").textContent = rec ? rec.mode + (rec.recording ? " · recording" : "") : "";
}

// --- camera tiles ---

function tileFor(name) {
  let tile = document.querySelector(`.tile[data-camera="${CSS.escape(name)}"]`);
  if (tile) return tile;
  const stat = (key, label, wide) => [el("dt", { text: label }), el("dd", { "data-stat": key, class: wide ? "wide" : null, text: "–" })];
  tile = el("article", { class: "tile", "data-camera": name, "data-status": "waiting" },
    el("header", {}, el("span", { class: "name", text: name }), el("span", { class: "status", text: "waiting" })),
    el("div", { class: "frame" }, el("img", { alt: `${name}: newest frame`, hidden: true }), el("span", { class: "hint", text: "no frame yet" })),
    el("p", { class: "reason" }),
    el("p", { class: "watch" }),
    el("dl", { class: "stats" },
      stat("fps", "fps"), stat("dropped", "dropped"), stat("latency", "transfer"), stat("jpeg", "JPEG"),
      stat("offset", "clock offset"), stat("drift", "drift"), stat("reconnects", "reconnects"), stat("bad", "bad parts"),
      stat("timing", "timing", true), stat("error", "last error", true), stat("url", "url", true)));
  const img = $("img", tile);
  img.addEventListener("load", () => { img.dataset.loading = ""; img.hidden = false; $(".frame .hint", tile).hidden = true; loadFrame(tile); });
  img.addEventListener("error", () => { img.dataset.loading = ""; });
  $("#tiles").append(tile);
  return tile;
}

function loadFrame(tile) {
  const img = $("img", tile);
  const want = tile.dataset.frame;
  if (!want || img.dataset.loading || img.dataset.src === want) return;
  img.dataset.loading = "1";
  img.dataset.src = want;
  img.src = want;
}

function setFrame(name, view) {
  if (!view) return;
  const tile = tileFor(name);
  tile.dataset.frame = view.frame;
  tile.dataset.seq = view.seq;
  tile.dataset.markers = view.markers;
  loadFrame(tile);
}

// what the camera watching says of it (docs/calibration.md): moved / re-calibrating (progress) / rejoined ...
function renderWatch(tile, w) {
  const p = $(".watch", tile);
  if (!w) { delete tile.dataset.watch; p.replaceChildren(); return; }
  tile.dataset.watch = w.state;
  const text = `${w.state}${w.message ? " · " + w.message : ""}`;
  if (w.state === "re-calibrating")
    p.replaceChildren(el("progress", { max: 1, value: w.progress }), el("span", { text: ` ${text}` }));
  else
    p.replaceChildren(el("span", { text }));
}

// host minus device clock: for a node counting seconds since it booted, the Unix time it booted
function clockOffset(s) {
  if (s === null || s === undefined) return "–";
  if (Math.abs(s) > 1e6) return `booted ${new Date(s * 1000).toLocaleTimeString()}.${String(Math.floor((s % 1) * 1000)).padStart(3, "0")}`;
  return fmt(s * 1000, 1, " ms");
}

function renderCamera(cam) {
  model.cameras.set(cam.name, cam);
  const tile = tileFor(cam.name);
  tile.dataset.status = cam.status;
  $(".status", tile).textContent = cam.status + (cam.calibrated ? " · calibrated" : "");
  $(".reason", tile).textContent = cam.reason;
  renderWatch(tile, cam.watch);
  const h = cam.health || {};
  const put = (key, text) => { $(`[data-stat="${key}"]`, tile).textContent = text; };
  put("fps", fmt(h.frames_per_s, 1));
  put("dropped", h.dropped === undefined ? "–" : String(h.dropped));
  put("latency", fmt(h.transfer_latency_s === null || h.transfer_latency_s === undefined ? null : h.transfer_latency_s * 1000, 0, " ms"));
  put("jpeg", h.jpeg_bytes ? fmt(h.jpeg_bytes / 1024, 1, " KB") : "–");
  put("offset", clockOffset(h.clock_offset_s));
  put("drift", fmt(h.clock_drift_ppm, 1, " ppm"));
  put("reconnects", h.reconnects === undefined ? "–" : String(h.reconnects));
  put("bad", h.bad === undefined ? "–" : String(h.bad));
  put("timing", h.timing || "–");
  put("error", h.last_error || "–");
  put("url", cam.url || "–");
  setFrame(cam.name, cam.view);
  const tv = model.topview && model.topview.cameras.find((c) => c.name === cam.name);
  if (tv && tv.status !== cam.status) { tv.status = cam.status; scheduleTopview(); }
}

// --- top view ---

let topviewPending = false;
function scheduleTopview() {
  if (topviewPending) return;
  topviewPending = true;
  requestAnimationFrame(() => { topviewPending = false; renderTopview(); });
}

function renderTopview() {
  const tv = model.topview;
  const root = $("#topview");
  root.replaceChildren();
  if (!tv) return;
  const W = 640, H = 480, pad = 20;
  const [x0, y0, x1, y1] = tv.bounds;
  const scale = Math.min((W - 2 * pad) / (x1 - x0), (H - 2 * pad) / (y1 - y0));
  const ox = (W - scale * (x1 - x0)) / 2, oy = (H - scale * (y1 - y0)) / 2;
  const X = (x) => ox + (x - x0) * scale, Y = (y) => H - oy - (y - y0) * scale;
  const pts = (list) => list.map(([x, y]) => `${X(x).toFixed(1)},${Y(y).toFixed(1)}`).join(" ");
  const grid = svg("g", { class: "grid" });
  for (let gx = Math.ceil(x0 * 2) / 2; gx <= x1; gx += 0.5) grid.append(svg("line", { x1: X(gx), y1: Y(y0), x2: X(gx), y2: Y(y1) }));
  for (let gy = Math.ceil(y0 * 2) / 2; gy <= y1; gy += 0.5) grid.append(svg("line", { x1: X(x0), y1: Y(gy), x2: X(x1), y2: Y(gy) }));
  root.append(grid);
  root.append(svg("polygon", { class: "world-marker", points: pts(tv.world_marker) }));
  root.append(svg("line", { class: "axis-x", x1: X(0), y1: Y(0), x2: X(0.3), y2: Y(0) }));
  root.append(svg("line", { class: "axis-y", x1: X(0), y1: Y(0), x2: X(0), y2: Y(0.3) }));
  const where = new Map();
  for (const cam of tv.cameras) {
    const g = svg("g", { class: "camera", "data-camera": cam.name, "data-status": cam.status });
    if (cam.fov.length) g.append(svg("polygon", { class: "fov", points: pts(cam.fov) }));
    if (cam.position_m) {
      const [cx, cy] = cam.position_m;
      where.set(cam.name, [cx, cy]);
      g.append(svg("circle", { cx: X(cx), cy: Y(cy), r: 6 }));
      g.append(svg("text", { x: X(cx) + 8, y: Y(cy) - 8 }, cam.name));
    }
    root.append(g);
  }
  for (const robot of tv.robots) {
    const g = svg("g", { class: "robot", "data-robot": robot.name, "data-seen-by": robot.seen_by.join(",") });
    if (robot.trail.length > 1) g.append(svg("polyline", { class: "trail", points: pts(robot.trail.map(([, x, y]) => [x, y])) }));
    if (robot.position_m) {
      const [rx, ry] = robot.position_m;
      for (const cam of robot.seen_by) {
        const c = where.get(cam);
        if (c) g.append(svg("line", { class: "sight", x1: X(c[0]), y1: Y(c[1]), x2: X(rx), y2: Y(ry) }));
      }
      const yaw = (robot.yaw_deg || 0) * Math.PI / 180;
      g.append(svg("rect", { x: X(rx) - 6, y: Y(ry) - 6, width: 12, height: 12 }));
      g.append(svg("line", { x1: X(rx), y1: Y(ry), x2: X(rx + 0.2 * Math.cos(yaw)), y2: Y(ry + 0.2 * Math.sin(yaw)) }));
      g.append(svg("text", { x: X(rx) + 9, y: Y(ry) + 16 }, robot.name));
    }
    root.append(g);
  }
  renderRobots(tv.robots);
}

function renderRobots(robots) {
  const body = $("#robots tbody");
  body.replaceChildren(...robots.map((r) => el("tr", { "data-robot": r.name },
    el("td", { text: r.name }),
    el("td", { class: "num", text: r.position_m ? r.position_m.map((v) => v.toFixed(3)).join(", ") : "–" }),
    el("td", { class: "num", text: fmt(r.yaw_deg, 1) }),
    el("td", { class: "seen-by", text: r.seen_by.join(", ") || "no camera" }),
    el("td", { class: "num", text: fmt(r.age_s, 1) }))));
}

function updateRobot(robot) {
  if (!model.topview) return;
  const i = model.topview.robots.findIndex((r) => r.name === robot.name);
  if (i >= 0) model.topview.robots[i] = robot; else model.topview.robots.push(robot);
  scheduleTopview();
}

// --- panels: calibration and recording ---

const LABELS = {
  calibration: { collect: "Collect samples", stop: "Stop and calibrate now", cancel: "Cancel", save: "Save extrinsics",
                 drive: "Drive the robot around", refine: "Refine now" },
  recording: { start: "Start recording", stop: "Stop recording" },
};
const STEPS = [["check", "1 · cameras see the world marker"], ["collect", "2 · collect samples"],
               ["result", "3 · results"], ["save", "4 · save"], ["refine", "5 · drive and refine"]];
const STEP_OF = { check: 0, collecting: 1, calibrating: 1, failed: 2, result: 2, driving: 4, refining: 4, refined: 4 };

function buttons(panel, value) {
  return el("div", { class: "buttons" }, Object.entries(LABELS[panel]).map(([action, label]) =>
    el("button", { id: `${panel}-${action}`, type: "button", disabled: !(value.actions || []).includes(action),
                   class: action === "cancel" || (panel === "recording" && action === "stop") ? "danger" : null,
                   onclick: (e) => { e.target.disabled = true; act(panel, action); } }, label)));
}

function progressBar(done, total, label) {
  return el("div", { class: "progress" }, el("progress", { max: Math.max(total, 1), value: Math.min(done, total) }),
            el("span", { class: "hint", text: `${label ? label + ": " : ""}${done} / ${total}` }));
}

function renderCalibration() {
  const c = model.panels.calibration;
  const root = $("#calibration");
  if (!c) return;
  const current = STEP_OF[c.step] ?? 0;
  const saved = c.saved ? 3 : -1;
  const steps = el("ol", { class: "steps" }, STEPS.map(([key, label], i) => el("li", {
    "data-step": key, class: i === current ? "current" : (i < current || i === saved ? "done" : null), text: label })));
  const headers = ["camera", "world marker", "samples", "spread", "reprojection", "verdict", "refinement moved it by"];
  const rows = c.cameras.flatMap((cam) => {
    const r = cam.result, f = cam.refined;
    const seen = cam.sees_marker === null ? el("span", { class: "unknown", text: cam.status === "down" || cam.status === "stale" ? "camera down" : "not checked" })
      : cam.sees_marker ? el("span", { class: "good", text: `✓ seen${cam.marker_side_px ? `, ${cam.marker_side_px.toFixed(0)} px` : ""}` })
      : el("span", { class: "poor", text: "✗ not seen" });
    const verdict = r ? el("span", { class: r.poor ? "poor" : "good", text: !r.calibrated ? "NOT CALIBRATED" : r.poor ? "POOR" : "good" }) : "–";
    const row = el("tr", { "data-camera": cam.name, "data-poor": r ? String(r.poor) : null },
      el("td", { text: cam.name }), el("td", { class: "marker" }, seen),
      el("td", { class: "samples" }, c.step === "collecting" ? progressBar(cam.samples, c.target_samples) : String(cam.samples || "–")),
      el("td", { class: "num spread", text: r && r.calibrated ? `${fmt(r.spread_cm, 2)} cm / ${fmt(r.spread_deg, 2)}°` : "–" }),
      el("td", { class: "num reprojection", text: r && r.calibrated ? fmt(r.reprojection_px, 2, " px") : "–" }),
      el("td", { class: "verdict" }, verdict),
      el("td", { class: "num moved", text: f ? `${fmt(f.shift_cm, 2)} cm / ${fmt(f.shift_deg, 2)}°${f.moved ? " MOVED" : ""}` : "–" }));
    if (!r || !r.advice.length) return [row];
    return [row, el("tr", { class: "advice-row", "data-advice-for": cam.name },
      el("td", { colspan: headers.length }, el("ul", { class: "advice" }, r.advice.map((a) => el("li", { text: a })))))];
  });
  const table = el("table", { id: "calibration-cameras" },
    el("thead", {}, el("tr", {}, headers.map((h) => el("th", { text: h })))),
    el("tbody", {}, rows));
  const parts = [steps, el("p", { id: "calibration-message", text: c.message })];
  if (c.progress) parts.push(progressBar(c.progress.done, c.progress.total, c.progress.label));
  if (c.drive) parts.push(el("div", { id: "drive-progress" }, progressBar(c.drive.instants, c.drive.target, "sightings matched by another camera")));
  parts.push(table, buttons("calibration", c));
  for (const w of c.warnings || []) parts.push(el("p", { class: "poor", text: w }));
  parts.push(el("p", { class: "hint", text: c.saved ? `saved ${c.saved.what} to ${c.saved.path}` : `Save writes ${c.save_to}` }));
  root.replaceChildren(...parts);
}

function renderRecording() {
  const r = model.panels.recording;
  if (!r) return;
  const since = r.since_s ? ` since ${new Date(r.since_s * 1000).toLocaleTimeString()}` : "";
  $("#recording").replaceChildren(el("div", {},
    el("p", { id: "recording-state", "data-recording": String(r.recording), text: (r.recording ? "recording" : r.mode) + since }),
    r.out_dir ? el("p", { class: "hint", text: `trajectories: ${r.out_dir}` }) : null,
    r.recording_dir ? el("p", { class: "hint", text: `frames: ${r.recording_dir}` }) : null,
    r.message ? el("p", { class: "hint", text: r.message }) : null,
    r.controls ? buttons("recording", r) : null));
  renderSession();
}

function renderFiles() {
  const groups = new Map();
  for (const f of model.files) {
    if (!groups.has(f.group)) groups.set(f.group, []);
    groups.get(f.group).push(f);
  }
  const root = $("#files");
  if (!groups.size) { root.replaceChildren(el("p", { class: "hint", text: "No trajectory files yet." })); return; }
  root.replaceChildren(...[...groups].map(([group, files]) => el("div", { class: "files-group", "data-group": group },
    el("span", { class: "hint", text: group + ": " }),
    files.map((f) => el("a", { href: f.url, download: f.name, text: `${f.name} (${fmt((f.bytes || 0) / 1024, 1)} KB)` })))));
}

function setPanel(name, value) {
  model.panels[name] = value;
  if (name === "calibration") renderCalibration();
  if (name === "recording") renderRecording();
}

// --- state and events ---

function applyState(s) {
  model.session = s.session;
  model.actions = s.actions;
  model.topview = s.topview;
  model.files = s.files;
  for (const cam of s.cameras) renderCamera(cam);
  for (const [name, value] of Object.entries(s.panels)) setPanel(name, value);
  renderSession();
  renderTopview();
  renderFiles();
}

async function refresh() {
  try { applyState(await getJSON("/api/state")); } catch (e) { showMessage(String(e)); }
}

async function refreshSlow() {
  try {
    model.topview = await getJSON("/api/topview");
    model.files = await getJSON("/api/files");
    renderTopview();
    renderFiles();
  } catch (e) { /* the event stream says when the server is gone */ }
}

function connect() {
  const link = $("#link");
  const events = new EventSource("/api/events");
  events.onopen = () => { link.textContent = "live"; link.className = "pill ok"; refresh(); };
  events.onerror = () => { link.textContent = "server unreachable, retrying"; link.className = "pill bad"; };
  const on = (kind, fn) => events.addEventListener(kind, (e) => fn(JSON.parse(e.data)));
  on("camera", renderCamera);
  on("view", (v) => setFrame(v.camera, v));
  on("robot", updateRobot);
  on("panel", (p) => { setPanel(p.name, p.value); if (p.name === "recording" || p.name === "calibration") refreshSlow(); });
  on("session", (s) => { model.session = s; renderSession(); refreshSlow(); });
  on("resync", refresh);
}

setInterval(refreshSlow, 5000);
connect();

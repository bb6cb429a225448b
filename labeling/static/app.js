// dynrecon labeling page: plain JS, no build step, talks to labeling/server.py.
// Coordinates: image pixels in OpenCV's convention (the centre of the top-left pixel is (0, 0)); the canvas draws
// pixel i over [i, i+1], so image point u sits at canvas x = (u + 0.5) * scale + tx.
"use strict";

const PALETTE = ["#ff6b6b", "#4f9dff", "#3fdf8f", "#ffb13b", "#c77dff", "#2ed3d3", "#ff7ac6", "#b8e04a",
  "#ff9f68", "#8fa3ff"];
const HIT_RADIUS = 11; // screen px within which a press grabs an existing marker
const FRAME_CACHE = 48; // decoded <img> kept in the page

const $ = (id) => document.getElementById(id);
const canvas = $("canvas");
const ctx = canvas.getContext("2d");
const timeline = $("timeline");
const tctx = timeline.getContext("2d");

const S = {
  videos: [], points: [], connections: [],
  video: null, // {name, frames, width, height, fps}
  frame: 0,
  labels: new Map(), // `${frame}|${point}` -> {source: "label"|"hidden", x, y} for the current video
  tracks: new Map(), // `${frame}|${point}` -> {x, y, score}
  selected: null,
  view: { scale: 1, tx: 0, ty: 0 },
  img: null, imgKey: null, want: null, loading: null,
  images: new Map(), // `${video}|${frame}` -> HTMLImageElement (LRU by insertion order)
  undo: [], redo: [],
  drag: null, pan: null, space: false, cursor: null,
  lowThreshold: 0.5,
  trackSeq: -1, trackState: "idle", staleVideos: new Set(),
  pending: 0, saveError: null,
};

const key = (frame, point) => `${frame}|${point}`;
const color = (point) => PALETTE[Math.max(0, S.points.indexOf(point)) % PALETTE.length];

// ---------------------------------------------------------------- server
async function api(method, path, body) {
  const options = { method, headers: {} };
  if (body !== undefined) {
    options.body = JSON.stringify(body);
    options.headers["Content-Type"] = "application/json";
  }
  const response = await fetch(path, options);
  let data = null;
  try { data = await response.json(); } catch (e) { data = null; }
  if (!response.ok) {
    const error = new Error((data && data.error) || `${response.status} ${response.statusText}`);
    error.status = response.status;
    throw error;
  }
  return data;
}

// Writes go out one at a time, in order: the server sees the changes in the order the user made them.
let saveChain = Promise.resolve();
function save(changes) {
  S.pending += 1;
  showSaveStatus();
  const wire = changes.map((c) => wireChange(c.video, c.frame, c.point, c.state));
  saveChain = saveChain.then(async () => {
    for (let attempt = 0; ; attempt++) {
      try {
        await api("POST", "/api/labels", { changes: wire });
        S.saveError = null;
        break;
      } catch (error) {
        // Rejected: do not retry. A timeout (408), a full disk (507) or a read-only folder (503) may pass later.
        if (error.status && error.status < 500 && error.status !== 408) { S.saveError = `not saved: ${error.message}`; break; }
        S.saveError = `not saved: ${error.message} (retrying…)`;
        showSaveStatus();
        await new Promise((resolve) => setTimeout(resolve, Math.min(5000, 500 * (attempt + 1))));
      }
    }
    S.pending -= 1;
    showSaveStatus();
  });
  return saveChain;
}

function wireChange(video, frame, point, state) {
  if (!state) return { video, frame, point, source: "none" };
  if (state.source === "hidden") return { video, frame, point, source: "hidden" };
  return { video, frame, point, source: "label", x: round3(state.x), y: round3(state.y) };
}
const round3 = (v) => Math.round(v * 1000) / 1000;

function showSaveStatus() {
  const el = $("save-status");
  if (S.saveError) { el.className = "badge bad"; el.textContent = S.saveError; el.title = S.saveError; }
  else if (S.pending > 0) { el.className = "badge busy"; el.textContent = "saving…"; }
  else { el.className = "badge ok"; el.textContent = "saved"; el.title = "every change is written to labels.csv at once"; }
  el.dataset.pending = String(S.pending);
}

// ---------------------------------------------------------------- edits, undo, redo
function labelAt(frame, point) { return S.labels.get(key(frame, point)) || null; }

function setLocal(frame, point, state) {
  if (state) S.labels.set(key(frame, point), state); else S.labels.delete(key(frame, point));
}

// One user action = one undo step: a list of {video, frame, point, before, after}.
function commit(edits) {
  const real = edits.filter((e) => !sameState(e.before, e.after));
  if (!real.length) return;
  for (const e of real) if (e.video === S.video.name) setLocal(e.frame, e.point, e.after);
  S.undo.push(real);
  S.redo = [];
  S.staleVideos.add(S.video.name);
  save(real.map((e) => ({ video: e.video, frame: e.frame, point: e.point, state: e.after })));
  scheduleAutoTrack();
  refresh();
}

// Opt-in: a correction re-anchors the track without pressing T (waits for a pause in the clicking).
let autoTrackTimer = null;
function scheduleAutoTrack() {
  if (!$("auto-track").checked) return;
  clearTimeout(autoTrackTimer);
  autoTrackTimer = setTimeout(() => {
    if (S.trackState === "running") scheduleAutoTrack(); else startTracking();
  }, 1500);
}

function sameState(a, b) {
  if (!a || !b) return !a && !b;
  return a.source === b.source && a.x === b.x && a.y === b.y;
}

async function undoRedo(from, to, field) {
  const step = from.pop();
  if (!step) return;
  to.push(step);
  const target = step[0];
  if (target.video !== S.video.name) await selectVideo(target.video, target.frame);
  for (const e of step) setLocal(e.frame, e.point, e[field]);
  S.staleVideos.add(target.video);
  save(step.map((e) => ({ video: e.video, frame: e.frame, point: e.point, state: e[field] })));
  scheduleAutoTrack();
  if (S.frame !== target.frame) gotoFrame(target.frame);
  selectPoint(target.point);
  flash(`${field === "before" ? "undid" : "redid"} ${describe(step)}`);
  refresh();
}
const undo = () => undoRedo(S.undo, S.redo, "before");
const redo = () => undoRedo(S.redo, S.undo, "after");

function describe(step) {
  const e = step[0];
  const what = e.after ? (e.after.source === "hidden" ? "not visible" : "label") : "removal";
  return `${what} of ${e.point} on frame ${e.frame}`;
}

function toggleHidden() {
  if (!S.selected) return;
  const before = labelAt(S.frame, S.selected);
  const after = before && before.source === "hidden" ? null : { source: "hidden" };
  commit([{ video: S.video.name, frame: S.frame, point: S.selected, before, after }]);
}

// Enter: the tracked position is right; keep it as a label (an anchor for the next track).
function acceptTrack() {
  if (!S.selected) return;
  const st = stateAt(S.frame, S.selected);
  if (st.kind !== "track") return;
  commit([{ video: S.video.name, frame: S.frame, point: S.selected, before: labelAt(S.frame, S.selected),
    after: { source: "label", x: round3(st.x), y: round3(st.y) } }]);
}

function removeLabel() {
  if (!S.selected) return;
  const before = labelAt(S.frame, S.selected);
  if (before) commit([{ video: S.video.name, frame: S.frame, point: S.selected, before, after: null }]);
}

// ---------------------------------------------------------------- loading
async function loadState() {
  const state = await api("GET", "/api/state");
  S.videos = state.videos;
  S.points = state.points;
  S.connections = state.connections;
  // The folder name; the full path on hover.
  $("workspace").textContent = state.workspace.split(/[\\/]/).filter(Boolean).pop() || state.workspace;
  $("workspace").title = state.workspace;
  renderVideos();
  onTrackStatus(state.track, true);
  return state;
}

async function selectVideo(name, frame) {
  const video = S.videos.find((v) => v.name === name) || S.videos[0];
  const [labels, tracks] = await Promise.all([
    api("GET", `/api/labels?video=${encodeURIComponent(video.name)}`),
    api("GET", `/api/tracks?video=${encodeURIComponent(video.name)}`),
  ]);
  S.video = video;
  S.labels = new Map(labels.labels.map((r) => [key(r.frame, r.point), { source: r.source, x: r.x, y: r.y }]));
  setTracks(tracks.tracks);
  $("slider").max = String(video.frames - 1);
  $("frame").max = String(video.frames - 1);
  $("frame-count").textContent = `/ ${video.frames - 1}`;
  S.view.fitted = false;
  renderVideos();
  gotoFrame(Math.min(Math.max(0, frame || 0), video.frames - 1));
}

function setTracks(rows) {
  S.tracks = new Map(rows.map((r) => [key(r.frame, r.point), { x: r.x, y: r.y, score: r.score }]));
}

async function reloadTracks() {
  const tracks = await api("GET", `/api/tracks?video=${encodeURIComponent(S.video.name)}`);
  if (tracks.video === S.video.name) setTracks(tracks.tracks);
  refresh();
}

function imageUrl(video, frame) { return `/frame/${encodeURIComponent(video)}/${frame}.jpg`; }

function cachedImage(video, frame) {
  const k = `${video}|${frame}`;
  let img = S.images.get(k);
  if (img) { S.images.delete(k); S.images.set(k, img); return img; }
  img = new Image();
  img.decoding = "async";
  img.src = imageUrl(video, frame);
  S.images.set(k, img);
  while (S.images.size > FRAME_CACHE) S.images.delete(S.images.keys().next().value);
  return img;
}

// Only the latest wanted frame is fetched; frames skipped while scrubbing are never requested.
function requestImage() {
  S.want = `${S.video.name}|${S.frame}`;
  if (S.loading) return;
  const [video, frameText] = [S.video.name, S.frame];
  const k = `${video}|${frameText}`;
  const img = cachedImage(video, frameText);
  const done = () => {
    S.loading = null;
    if (img.naturalWidth > 0) { S.img = img; S.imgKey = k; }
    if (!S.view.fitted && S.img) fitView();
    draw();
    if (S.want !== k) requestImage();
    else prefetch();
  };
  if (img.complete && img.naturalWidth > 0) { S.loading = null; S.img = img; S.imgKey = k; if (!S.view.fitted) fitView(); draw(); prefetch(); return; }
  S.loading = k;
  img.addEventListener("load", done, { once: true });
  img.addEventListener("error", done, { once: true });
}

function prefetch() {
  for (const d of [1, 2, -1]) {
    const f = S.frame + d;
    if (f >= 0 && f < S.video.frames && !S.images.has(`${S.video.name}|${f}`)) cachedImage(S.video.name, f);
  }
}

// ---------------------------------------------------------------- navigation
function gotoFrame(frame) {
  if (!S.video) return;
  S.frame = Math.min(Math.max(0, Math.round(frame)), S.video.frames - 1);
  $("slider").value = String(S.frame);
  $("frame").value = String(S.frame);
  history.replaceState(null, "", `#video=${encodeURIComponent(S.video.name)}&frame=${S.frame}` +
    (S.selected ? `&point=${encodeURIComponent(S.selected)}` : ""));
  requestImage();
  refresh();
}

function stateAt(frame, point) {
  const label = labelAt(frame, point);
  if (label) return label.source === "hidden" ? { kind: "hidden" } : { kind: "label", x: label.x, y: label.y };
  const track = S.tracks.get(key(frame, point));
  if (track) return { kind: "track", x: track.x, y: track.y, score: track.score };
  return { kind: "none" };
}

const isLow = (st) => st.kind === "track" && st.score !== null && st.score < S.lowThreshold;

function jump(predicate, what) {
  if (!S.selected) return;
  for (let f = S.frame + 1; f < S.video.frames; f++) {
    if (predicate(stateAt(f, S.selected))) { gotoFrame(f); return; }
  }
  flash(`no ${what} of ${S.selected} after frame ${S.frame}`);
}
const nextGap = () => jump((st) => st.kind === "none", "gap");
const nextLow = () => jump(isLow, "low-confidence frame");

function selectPoint(name) {
  if (!S.points.includes(name)) return;
  S.selected = name;
  if (S.video) history.replaceState(null, "", `#video=${encodeURIComponent(S.video.name)}&frame=${S.frame}` +
    `&point=${encodeURIComponent(name)}`);
  refresh();
}

function selectNextPoint(delta) {
  if (!S.points.length) return;
  const i = S.points.indexOf(S.selected);
  selectPoint(S.points[(i + delta + S.points.length) % S.points.length]);
}

// ---------------------------------------------------------------- view
function resizeCanvas() {
  const dpr = window.devicePixelRatio || 1;
  const rect = canvas.getBoundingClientRect();
  canvas.width = Math.max(1, Math.round(rect.width * dpr));
  canvas.height = Math.max(1, Math.round(rect.height * dpr));
  const trect = timeline.getBoundingClientRect();
  timeline.width = Math.max(1, Math.round(trect.width * dpr));
  timeline.height = Math.max(1, Math.round(trect.height * dpr));
  if (!S.view.userMoved) S.view.fitted = false;
  if (S.img && !S.view.fitted) fitView();
  draw();
}

function fitView() {
  if (!S.video) return;
  const rect = canvas.getBoundingClientRect();
  const scale = Math.min(rect.width / S.video.width, rect.height / S.video.height) * 0.98;
  S.view = { scale, tx: (rect.width - S.video.width * scale) / 2, ty: (rect.height - S.video.height * scale) / 2,
    fitted: true, userMoved: false };
  draw();
}

function zoomAt(sx, sy, factor) {
  const v = S.view;
  const scale = Math.min(64, Math.max(0.05, v.scale * factor));
  const k = scale / v.scale;
  S.view = { scale, tx: sx - (sx - v.tx) * k, ty: sy - (sy - v.ty) * k, fitted: true, userMoved: true };
  draw();
}

const toScreen = (u, v) => [(u + 0.5) * S.view.scale + S.view.tx, (v + 0.5) * S.view.scale + S.view.ty];
const toImage = (sx, sy) => [(sx - S.view.tx) / S.view.scale - 0.5, (sy - S.view.ty) / S.view.scale - 0.5];

function eventPos(event) {
  const rect = canvas.getBoundingClientRect();
  return [event.clientX - rect.left, event.clientY - rect.top];
}

// ---------------------------------------------------------------- drawing
function refresh() {
  renderPoints();
  renderTrackInfo();
  draw();
}

function draw() {
  const dpr = window.devicePixelRatio || 1;
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  const rect = canvas.getBoundingClientRect();
  ctx.fillStyle = "#0c0d10";
  ctx.fillRect(0, 0, rect.width, rect.height);
  if (!S.video) return;
  if (S.img) {
    ctx.save();
    ctx.translate(S.view.tx, S.view.ty);
    ctx.scale(S.view.scale, S.view.scale);
    ctx.imageSmoothingEnabled = S.view.scale < 3; // zoomed in: show real pixels for precise clicks
    ctx.drawImage(S.img, 0, 0, S.video.width, S.video.height);
    ctx.restore();
  }
  const shown = new Map();
  for (const point of S.points) {
    const st = S.drag && S.drag.point === point ? { kind: "label", x: S.drag.x, y: S.drag.y } : stateAt(S.frame, point);
    if (st.kind === "label" || st.kind === "track") shown.set(point, st);
  }
  drawSkeleton(shown);
  for (const [point, st] of shown) if (point !== S.selected) drawMarker(point, st, false);
  if (shown.has(S.selected)) drawMarker(S.selected, shown.get(S.selected), true);
  drawHud();
  drawTimeline();
}

function drawSkeleton(shown) {
  ctx.lineWidth = 2;
  for (const [a, b] of S.connections) {
    const pa = shown.get(a), pb = shown.get(b);
    if (!pa || !pb) continue;
    const [ax, ay] = toScreen(pa.x, pa.y), [bx, by] = toScreen(pb.x, pb.y);
    ctx.setLineDash(pa.kind === "track" || pb.kind === "track" ? [6, 4] : []);
    ctx.strokeStyle = "rgba(0,0,0,0.55)";
    ctx.lineWidth = 4;
    line(ax, ay, bx, by);
    ctx.strokeStyle = "rgba(255,255,255,0.8)";
    ctx.lineWidth = 2;
    line(ax, ay, bx, by);
  }
  ctx.setLineDash([]);
}

function line(ax, ay, bx, by) { ctx.beginPath(); ctx.moveTo(ax, ay); ctx.lineTo(bx, by); ctx.stroke(); }

function drawMarker(point, st, selected) {
  const [x, y] = toScreen(st.x, st.y);
  const c = color(point);
  const r = selected ? 9 : 7;
  const low = isLow(st);
  ctx.save();
  // Labels: solid ring with a crosshair gap at the centre (the clicked pixel stays visible).
  // Tracks: dashed ring, red when the tracker's confidence is low.
  ctx.lineWidth = 4;
  ctx.strokeStyle = "rgba(0,0,0,0.6)";
  ctx.setLineDash(st.kind === "track" ? [4, 3] : []);
  circle(x, y, r);
  ctx.lineWidth = 2;
  ctx.strokeStyle = st.kind === "track" && low ? "#ff3b3b" : c;
  circle(x, y, r);
  ctx.setLineDash([]);
  if (st.kind === "label") {
    // Ticks outside the ring point at the clicked pixel without covering it.
    for (const [dx, dy] of [[1, 0], [-1, 0], [0, 1], [0, -1]]) {
      const [x0, y0, x1, y1] = [x + dx * (r + 2), y + dy * (r + 2), x + dx * (r + 7), y + dy * (r + 7)];
      ctx.lineWidth = 4;
      ctx.strokeStyle = "rgba(0,0,0,0.6)";
      line(x0, y0, x1, y1);
      ctx.lineWidth = 2;
      ctx.strokeStyle = c;
      line(x0, y0, x1, y1);
    }
  }
  ctx.fillStyle = st.kind === "track" && low ? "#ff3b3b" : c;
  ctx.fillRect(x - 1, y - 1, 2, 2);
  if (selected) {
    ctx.lineWidth = 1;
    ctx.strokeStyle = "#fff";
    circle(x, y, r + 3);
  }
  const text = st.kind === "track" && st.score !== null && st.score !== undefined ? `${point} ${st.score.toFixed(2)}` : point;
  ctx.font = `${selected ? "bold " : ""}12px system-ui, sans-serif`;
  ctx.lineWidth = 3;
  ctx.strokeStyle = "rgba(0,0,0,0.8)";
  ctx.strokeText(text, x + r + 5, y - r + 2);
  ctx.fillStyle = st.kind === "track" && low ? "#ff8080" : "#fff";
  ctx.fillText(text, x + r + 5, y - r + 2);
  ctx.restore();
}

function circle(x, y, r) { ctx.beginPath(); ctx.arc(x, y, r, 0, 2 * Math.PI); ctx.stroke(); }

function drawHud() {
  const v = S.video;
  let text = `${v.name} · frame ${S.frame} / ${v.frames - 1} · ${v.width}×${v.height} · ${Math.round(S.view.scale * 100)}%`;
  if (S.cursor) text += ` · x ${S.cursor[0].toFixed(1)} y ${S.cursor[1].toFixed(1)}`;
  if (S.loading && S.imgKey !== `${v.name}|${S.frame}`) text += " · loading…";
  $("hud").textContent = text;
}

function drawTimeline() {
  const dpr = window.devicePixelRatio || 1;
  const w = timeline.width / dpr, h = timeline.height / dpr;
  tctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  tctx.fillStyle = "#1f2229";
  tctx.fillRect(0, 0, w, h);
  if (!S.video || !S.selected) return;
  const n = S.video.frames;
  const c = color(S.selected);
  for (let f = 0; f < n; f++) {
    const st = stateAt(f, S.selected);
    if (st.kind === "none") continue;
    const x0 = (f / n) * w, x1 = Math.max(x0 + 1, ((f + 1) / n) * w);
    if (st.kind === "label") { tctx.fillStyle = c; tctx.fillRect(x0, 0, x1 - x0, h); }
    else if (st.kind === "hidden") { tctx.fillStyle = "#777"; tctx.fillRect(x0, 0, x1 - x0, h); }
    else {
      tctx.fillStyle = isLow(st) ? "#ff3b3b" : c;
      tctx.globalAlpha = 0.35;
      tctx.fillRect(x0, h * 0.25, x1 - x0, h * 0.5);
      tctx.globalAlpha = 1;
    }
  }
  const x = ((S.frame + 0.5) / n) * w;
  tctx.fillStyle = "#fff";
  tctx.fillRect(x - 1, 0, 2, h);
}

// ---------------------------------------------------------------- side panel
function renderVideos() {
  const ul = $("videos");
  ul.replaceChildren(...S.videos.map((v) => {
    const li = document.createElement("li");
    li.className = S.video && v.name === S.video.name ? "active" : "";
    li.dataset.video = v.name;
    const name = document.createElement("span");
    name.className = "name";
    name.textContent = v.name;
    const info = document.createElement("span");
    info.className = "state";
    info.textContent = `${v.frames} fr · ${v.width}×${v.height}`;
    li.append(name, info);
    li.addEventListener("click", () => { if (!S.video || v.name !== S.video.name) selectVideo(v.name, 0); });
    return li;
  }));
}

function renderPoints() {
  const ul = $("points");
  if (ul.querySelector("input.rename-input")) return; // do not disturb a rename in progress
  // Rebuild only when the names change; otherwise update in place, so a double click lands on the same element.
  const signature = S.points.join("\n");
  if (ul.dataset.signature !== signature) {
    ul.dataset.signature = signature;
    ul.replaceChildren(...S.points.map(pointItem));
  }
  for (const li of ul.children) {
    const p = li.dataset.point;
    li.classList.toggle("active", p === S.selected);
    const st = S.video ? stateAt(S.frame, p) : { kind: "none" };
    const state = li.querySelector(".state");
    state.className = `state ${st.kind}${isLow(st) ? " low" : ""}`;
    state.textContent = st.kind === "label" ? "label" : st.kind === "hidden" ? "not visible"
      : st.kind === "track" ? `track ${st.score === null ? "" : st.score.toFixed(2)}` : "–";
  }
}

function pointItem(p, i) {
  const li = document.createElement("li");
  li.dataset.point = p;
  const keyEl = document.createElement("span");
  keyEl.className = "key";
  keyEl.textContent = i < 9 ? String(i + 1) : "";
  const swatch = document.createElement("span");
  swatch.className = "swatch";
  swatch.style.background = color(p);
  const name = document.createElement("span");
  name.className = "name";
  name.textContent = p;
  const state = document.createElement("span");
  state.className = "state";
  const rename = document.createElement("button");
  rename.className = "rename";
  rename.title = "rename";
  rename.textContent = "✎";
  rename.addEventListener("click", (e) => { e.stopPropagation(); startRename(li, p); });
  li.append(keyEl, swatch, name, state, rename);
  li.addEventListener("click", () => selectPoint(p));
  li.addEventListener("dblclick", () => startRename(li, p));
  return li;
}

function startRename(li, old) {
  const input = document.createElement("input");
  input.className = "rename-input";
  input.value = old;
  input.maxLength = 64;
  li.querySelector(".name").replaceWith(input);
  input.focus();
  input.select();
  let finished = false;
  const finish = async (apply) => {
    if (finished) return;
    finished = true;
    const name = input.value.trim();
    input.remove();
    $("points").dataset.signature = "";
    if (apply && name && name !== old) {
      try {
        const answer = await api("POST", "/api/points", { op: "rename", old, new: name });
        renamePointLocally(old, name, answer);
        flash(`renamed ${old} to ${name}`);
      } catch (error) { flash(`rename failed: ${error.message}`, true); }
    }
    renderPoints();
  };
  input.addEventListener("keydown", (e) => {
    e.stopPropagation();
    if (e.key === "Enter") finish(true);
    if (e.key === "Escape") finish(false);
  });
  input.addEventListener("blur", () => finish(true));
}

function renamePointLocally(old, name, answer) {
  S.points = answer.points;
  S.connections = answer.connections;
  const rename = (map) => new Map([...map].map(([k, v]) => {
    const [f, p] = k.split("|");
    return [p === old ? key(f, name) : k, v];
  }));
  S.labels = rename(S.labels);
  S.tracks = rename(S.tracks);
  const fix = (e) => (e.point === old ? { ...e, point: name } : e);
  S.undo = S.undo.map((step) => step.map(fix));
  S.redo = S.redo.map((step) => step.map(fix));
  if (S.selected === old) S.selected = name;
  refresh();
}

async function addPoint(name) {
  name = name.trim();
  if (!name) return;
  try {
    const answer = await api("POST", "/api/points", { op: "add", name });
    S.points = answer.points;
    S.connections = answer.connections;
    selectPoint(name);
  } catch (error) { flash(`cannot add ${name}: ${error.message}`, true); }
}

function renderTrackInfo() {
  $("stale").hidden = !(S.video && S.staleVideos.has(S.video.name) && S.tracks.size > 0);
  $("undo").disabled = !S.undo.length;
  $("redo").disabled = !S.redo.length;
}

// ---------------------------------------------------------------- tracking
async function startTracking() {
  if (S.trackState === "running") return;
  const videos = $("track-all").checked ? null : [S.video.name];
  await saveChain; // the tracker must see the last click
  try {
    const status = await api("POST", "/api/track", { videos });
    onTrackStatus(status, false);
    pollTracking();
  } catch (error) { flash(`tracking not started: ${error.message}`, true); }
}

async function pollTracking() {
  if (S.polling) return;
  S.polling = true;
  while (S.trackState === "running") {
    await new Promise((resolve) => setTimeout(resolve, 400));
    try { onTrackStatus(await api("GET", "/api/track"), false); } catch (error) { /* server busy: ask again */ }
  }
  S.polling = false;
}

// While idle, look now and then for changes made outside the page (e.g. `dynrecon track` in a shell).
async function watchOutside() {
  for (;;) {
    await new Promise((resolve) => setTimeout(resolve, 3000));
    if (document.hidden || S.trackState === "running") continue;
    try { onTrackStatus(await api("GET", "/api/track"), false); } catch (error) { /* try again later */ }
  }
}

function onTrackStatus(status, initial) {
  const el = $("track-status");
  const previousSeq = S.trackSeq;
  S.trackState = status.state;
  S.trackSeq = status.seq;
  $("track").disabled = status.state === "running";
  $("track").textContent = status.state === "running" ? "Tracking…" : "Track this video";
  el.className = status.state === "failed" ? "small bad" : "muted small";
  el.textContent = status.state === "idle" ? "not run yet" : status.state === "running" ? `${status.message}…`
    : `${status.message} (${status.seconds.toFixed(1)} s)`;
  document.body.dataset.trackState = status.state;
  document.body.dataset.trackSeq = String(status.seq);
  if (initial && status.state === "running") pollTracking();
  const finished = status.seq !== previousSeq && status.state !== "running";
  if (!initial && finished && status.state === "done") for (const v of status.videos) S.staleVideos.delete(v);
  const outside = S.tracksVersion !== undefined && status.tracks_version !== S.tracksVersion;
  S.tracksVersion = status.tracks_version;
  if (!initial && (finished || outside) && status.state !== "running" && S.video) reloadTracks();
  updateFrameCounts(status.frames || {});
  renderTrackInfo();
}

// The server counts the frames exactly in the background; the container's count may have been off.
function updateFrameCounts(frames) {
  for (const v of S.videos) {
    if (frames[v.name] === undefined || frames[v.name] === v.frames) continue;
    v.frames = frames[v.name];
    if (S.video && S.video.name === v.name) {
      $("slider").max = String(v.frames - 1);
      $("frame").max = String(v.frames - 1);
      $("frame-count").textContent = `/ ${v.frames - 1}`;
      if (S.frame >= v.frames) gotoFrame(v.frames - 1);
    }
    renderVideos();
  }
}

// ---------------------------------------------------------------- messages
let flashTimer = null;
function flash(text, bad) {
  const el = $("message");
  el.textContent = text;
  el.className = bad ? "bad" : "";
  el.hidden = false;
  clearTimeout(flashTimer);
  flashTimer = setTimeout(() => { el.hidden = true; }, bad ? 6000 : 2500);
}

// ---------------------------------------------------------------- mouse
function hitTest(sx, sy) {
  let best = null, bestDist = HIT_RADIUS;
  // The selected point first: with markers on top of each other, the one you are working on wins.
  const order = [S.selected, ...S.points.filter((p) => p !== S.selected)].filter(Boolean);
  for (const point of order) {
    const st = stateAt(S.frame, point);
    if (st.kind !== "label" && st.kind !== "track") continue;
    const [x, y] = toScreen(st.x, st.y);
    const d = Math.hypot(x - sx, y - sy);
    if (d < bestDist - 0.01) { best = point; bestDist = d; }
  }
  return best;
}

canvas.addEventListener("mousedown", (event) => {
  if (!S.video) return;
  canvas.focus();
  const [sx, sy] = eventPos(event);
  if (event.button === 1 || (event.button === 0 && (event.shiftKey || S.space))) {
    S.pan = { sx, sy, tx: S.view.tx, ty: S.view.ty };
    canvas.classList.add("panning");
    event.preventDefault();
    return;
  }
  if (event.button !== 0) return;
  const grabbed = hitTest(sx, sy);
  const point = grabbed || S.selected;
  if (!point) { flash("add a point first (left panel)", true); return; }
  if (grabbed && grabbed !== S.selected) selectPoint(grabbed);
  const st = stateAt(S.frame, point);
  let [x, y] = toImage(sx, sy);
  let offset = [0, 0];
  if (grabbed) offset = [st.x - x, st.y - y]; // keep the grab offset: a drag does not jump to the cursor
  [x, y] = clampToImage(x + offset[0], y + offset[1]);
  S.drag = { point, x, y, offset, before: labelAt(S.frame, point), moved: false, grabbed: !!grabbed };
  draw();
  event.preventDefault();
});

window.addEventListener("mousemove", (event) => {
  const [sx, sy] = eventPos(event);
  if (S.pan) {
    S.view = { ...S.view, tx: S.pan.tx + sx - S.pan.sx, ty: S.pan.ty + sy - S.pan.sy, userMoved: true };
    draw();
    return;
  }
  if (!S.video) return;
  if (S.drag) {
    const [x, y] = toImage(sx, sy);
    [S.drag.x, S.drag.y] = clampToImage(x + S.drag.offset[0], y + S.drag.offset[1]);
    S.drag.moved = true;
    S.cursor = [S.drag.x, S.drag.y];
    draw();
    return;
  }
  if (event.target === canvas) {
    S.cursor = toImage(sx, sy);
    canvas.classList.toggle("over-point", !!hitTest(sx, sy));
    drawHud();
  }
});

window.addEventListener("mouseup", () => {
  if (S.pan) { S.pan = null; canvas.classList.remove("panning"); return; }
  if (!S.drag) return;
  const d = S.drag;
  S.drag = null;
  if (d.grabbed && !d.moved) { draw(); return; } // a click on a marker only selects its point
  const after = { source: "label", x: round3(d.x), y: round3(d.y) };
  commit([{ video: S.video.name, frame: S.frame, point: d.point, before: d.before, after }]);
  // A click on empty image (not a drag of an existing marker) moves on to the next point to label.
  if (!d.grabbed && $("advance").checked) advanceSelection();
});

function clampToImage(x, y) {
  return [Math.min(Math.max(x, -0.5), S.video.width - 0.5), Math.min(Math.max(y, -0.5), S.video.height - 0.5)];
}

function advanceSelection() {
  const i = S.points.indexOf(S.selected);
  for (let k = 1; k < S.points.length; k++) {
    const p = S.points[(i + k) % S.points.length];
    if (stateAt(S.frame, p).kind !== "label" && !labelAt(S.frame, p)) { selectPoint(p); return; }
  }
}

canvas.addEventListener("wheel", (event) => {
  event.preventDefault();
  const [sx, sy] = eventPos(event);
  const delta = event.deltaMode === 1 ? event.deltaY * 16 : event.deltaY;
  zoomAt(sx, sy, Math.pow(1.0015, -delta));
}, { passive: false });

canvas.addEventListener("auxclick", (event) => event.preventDefault());
canvas.addEventListener("contextmenu", (event) => event.preventDefault());
canvas.addEventListener("mouseleave", () => { S.cursor = null; if (S.video) drawHud(); });

timeline.addEventListener("mousedown", (event) => {
  const seek = (e) => {
    const rect = timeline.getBoundingClientRect();
    gotoFrame(Math.floor(((e.clientX - rect.left) / rect.width) * S.video.frames));
  };
  seek(event);
  const move = (e) => seek(e);
  window.addEventListener("mousemove", move);
  window.addEventListener("mouseup", () => window.removeEventListener("mousemove", move), { once: true });
});

// ---------------------------------------------------------------- keyboard
window.addEventListener("keydown", (event) => {
  const tag = event.target.tagName;
  if ((tag === "INPUT" && event.target.type !== "range" && event.target.type !== "checkbox") || !S.video) return;
  const k = event.key;
  const mod = event.ctrlKey || event.metaKey;
  let handled = true;
  if (mod && (k === "z" || k === "Z")) { if (event.shiftKey) redo(); else undo(); }
  else if (mod && (k === "y" || k === "Y")) redo();
  else if (mod) handled = false;
  else if (k === "ArrowRight" || k === ".") gotoFrame(S.frame + (event.shiftKey ? 10 : 1));
  else if (k === "ArrowLeft" || k === ",") gotoFrame(S.frame - (event.shiftKey ? 10 : 1));
  else if (k === "Home") gotoFrame(0);
  else if (k === "End") gotoFrame(S.video.frames - 1);
  else if (k === "n" || k === "N") nextGap();
  else if (k === "l" || k === "L") nextLow();
  else if (k === "x" || k === "X") toggleHidden();
  else if (k === "Delete" || k === "Backspace") removeLabel();
  else if (k === "Enter" && tag !== "BUTTON") acceptTrack();
  else if (k === "Tab") selectNextPoint(event.shiftKey ? -1 : 1);
  else if (/^[1-9]$/.test(k) && S.points[Number(k) - 1]) selectPoint(S.points[Number(k) - 1]);
  else if (k === "t" || k === "T") startTracking();
  else if (k === "f" || k === "F") fitView();
  else if (k === "+" || k === "=") zoomAt(canvas.clientWidth / 2, canvas.clientHeight / 2, 1.25);
  else if (k === "-") zoomAt(canvas.clientWidth / 2, canvas.clientHeight / 2, 0.8);
  else if (k === " ") { S.space = true; }
  else handled = false;
  if (handled) event.preventDefault();
});
window.addEventListener("keyup", (event) => { if (event.key === " ") S.space = false; });

// ---------------------------------------------------------------- controls
$("slider").addEventListener("input", (e) => gotoFrame(Number(e.target.value)));
$("frame").addEventListener("change", (e) => gotoFrame(Number(e.target.value)));
$("prev").addEventListener("click", () => gotoFrame(S.frame - 1));
$("next").addEventListener("click", () => gotoFrame(S.frame + 1));
$("next-gap").addEventListener("click", nextGap);
$("next-low").addEventListener("click", nextLow);
$("hide").addEventListener("click", toggleHidden);
$("undo").addEventListener("click", undo);
$("redo").addEventListener("click", redo);
$("fit").addEventListener("click", fitView);
$("track").addEventListener("click", startTracking);
$("low-threshold").addEventListener("input", (e) => {
  const v = Number(e.target.value);
  if (Number.isFinite(v)) { S.lowThreshold = v; refresh(); }
});
$("add-point").addEventListener("submit", (e) => {
  e.preventDefault();
  addPoint($("new-point").value);
  $("new-point").value = "";
});
window.addEventListener("resize", resizeCanvas);
window.addEventListener("beforeunload", (e) => { if (S.pending > 0) e.preventDefault(); });

// ---------------------------------------------------------------- start
async function start() {
  try {
    await loadState();
    const params = new URLSearchParams(location.hash.slice(1));
    S.selected = S.points.includes(params.get("point")) ? params.get("point") : S.points[0] || null;
    resizeCanvas();
    await selectVideo(params.get("video") || (S.videos[0] && S.videos[0].name), Number(params.get("frame")) || 0);
    document.body.dataset.ready = "1";
    watchOutside();
  } catch (error) {
    flash(`cannot load the workspace: ${error.message}`, true);
  }
}

// For tests and power users: the page's state and the image -> client coordinate mapping.
window.dynreconLabel = {
  state: S,
  toClient(u, v) {
    const rect = canvas.getBoundingClientRect();
    const [x, y] = toScreen(u, v);
    return [rect.left + x, rect.top + y];
  },
};

start();

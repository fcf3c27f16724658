// spheroseg's viewer page: NiiVue shows the study (three slices and a 3D
// view); this script places points, sends them to the server, receives the
// surfaces it streams (Server-Sent Events) and draws the wall's contour on the
// slices. World points here are NIfTI RAS millimetres (NiiVue's); the server
// converts to ITK's LPS.
'use strict';

const $ = (id) => document.getElementById(id);
const COLORS = { contour: '#ffd23c', apex: '#ff4d4d', base: '#4dff88', landmark: '#4de1ff', annulus: '#ff9f40',
                 selected: '#ffffff' };
const NEAR_MM = 2.0;   // a point this close to a slice is drawn full, farther ones faded
const GRAB_PX = 9;     // how close a press must be to a point to drag it

const state = {
  study: null, frame: 0, frames: 1,
  points: { apex: null, base: null, landmarks: [], annulus: [] },
  history: [], mode: 'apex', selected: -1,
  job: 0, faces: null, vertices: new Map(), shown: null, pending: null,
  tracking: null, playing: null, drag: null,
  timings: [],          // per job: click, first and final surface drawn (ms, performance.now)
};
let nv = null;

// -- server -------------------------------------------------------------------

async function api(path, body) {
  const init = body === undefined ? {} : {
    method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body),
  };
  const response = await fetch(path, init);
  const data = await response.json();
  if (!response.ok) throw new Error(data.error || response.statusText);
  return data;
}

function decode(base64, Type) {
  const text = atob(base64);
  const bytes = new Uint8Array(text.length);
  for (let i = 0; i < text.length; i++) bytes[i] = text.charCodeAt(i);
  return new Type(bytes.buffer);
}

function say(text, kind) {
  $('status').textContent = text;
  if (kind) document.body.dataset.state = kind;
}

// -- points -------------------------------------------------------------------

function copyPoints(p) {
  return { apex: p.apex && [...p.apex], base: p.base && [...p.base],
           landmarks: p.landmarks.map((q) => [...q]), annulus: p.annulus.map((q) => [...q]) };
}

function complete(p) { return p.apex !== null && (p.base !== null || p.annulus.length >= 3); }

async function changePoints(change, { record = true } = {}) {
  const before = copyPoints(state.points);
  change(state.points);
  if (record) state.history.push(before);
  await sendPoints(before);
}

async function sendPoints(fallback) {
  state.vertices.clear();
  state.tracking = null;
  showTracking();
  // the job's number comes with the reply, which may arrive after its surfaces
  const timing = { job: null, click: performance.now(), first: null, final: null };
  state.timings.push(timing);
  if (complete(state.points)) say('segmenting...', 'running');
  try {
    const { job } = await api('/api/points', { frame: state.frame, ...state.points });
    timing.job = job;
    state.job = Math.max(state.job, job);
    document.body.dataset.sent = String(job);
    if (!complete(state.points)) hideSurface();
  } catch (error) {
    if (fallback) state.points = fallback;
    say(error.message, 'error');
  }
  listPoints();
  drawOverlay();
}

function place(mm, shift) {
  const mode = shift ? 'landmark' : state.mode;
  if (mode === 'apex') {
    changePoints((p) => { p.apex = mm; });
    setMode(state.points.base === null ? 'base' : 'navigate');
  } else if (mode === 'base') {
    changePoints((p) => { p.base = mm; });
    setMode('navigate');
  } else if (mode === 'annulus') {
    changePoints((p) => { p.annulus.push(mm); });
    if (state.points.annulus.length < 3 && state.points.base === null) {
      say(`${state.points.annulus.length} annulus point(s): 3 or more close the cavity at their plane`);
    }
  } else if (mode === 'landmark') {
    if (!complete(state.points)) { say('place the apex and the base first', 'error'); return; }
    changePoints((p) => { p.landmarks.push(mm); });
    state.selected = state.points.landmarks.length - 1;
  }
}

function undo() {
  const previous = state.history.pop();
  if (!previous) { say('nothing to undo'); return; }
  state.points = previous;
  state.selected = -1;
  sendPoints(null);
}

function deleteSelected() {
  const k = state.selected;
  if (k < 0 || k >= state.points.landmarks.length) { say('click a landmark (cyan) to select it first'); return; }
  state.selected = -1;
  changePoints((p) => { p.landmarks.splice(k, 1); });
}

function setMode(mode) {
  state.mode = mode;
  for (const b of document.querySelectorAll('#modes button')) b.classList.toggle('active', b.dataset.mode === mode);
  const hints = { apex: 'click the apex', base: 'click the base (centre of the mitral plane)',
                  annulus: 'click points of the mitral annulus (3 or more)',
                  landmark: 'click a point the wall must pass through', navigate: '' };
  if (hints[mode]) say(hints[mode]);
}

function listPoints() {
  const f = (p) => (p ? p.map((v) => v.toFixed(1)).join(', ') : '-');
  const p = state.points;
  $('pointlist').textContent = `apex (${f(p.apex)}) base (${f(p.base)}) landmarks ${p.landmarks.length}` +
    (p.annulus.length ? ` annulus ${p.annulus.length}` : '');
}

// -- where the mouse is, in mm --------------------------------------------------

const PLANE = [  // per tile kind (axial, coronal, sagittal): in-plane axes and the fixed one
  { u: 0, v: 1, w: 2 }, { u: 0, v: 2, w: 1 }, { u: 1, v: 2, w: 0 },
];

function sliceTiles() {
  return nv.screenSlices.filter((t) => t.axCorSag <= 2 && t.sliceFrac !== Infinity && t.fovMM && t.fovMM.length);
}

function toScreen(tile, a, b) {
  const [l, t, w, h] = tile.leftTopWidthHeight;
  return [l + ((a - tile.leftTopMM[0]) / tile.fovMM[0]) * w, t + h - ((b - tile.leftTopMM[1]) / tile.fovMM[1]) * h];
}

function crosshairMM() { return Array.from(nv.frac2mm(nv.scene.crosshairPos)).slice(0, 3); }

function canvasXY(event) {
  const canvas = $('gl');
  const r = canvas.getBoundingClientRect();
  return [(event.clientX - r.left) * (canvas.width / r.width), (event.clientY - r.top) * (canvas.height / r.height)];
}

function tileAt(x, y) {
  return sliceTiles().find((t) => {
    const [l, tp, w, h] = t.leftTopWidthHeight;
    return x >= l && x <= l + w && y >= tp && y <= tp + h;
  });
}

function mmAt(tile, x, y, fixed) {
  const [l, t, w, h] = tile.leftTopWidthHeight;
  const plane = PLANE[tile.axCorSag];
  const mm = [...fixed];
  mm[plane.u] = tile.leftTopMM[0] + ((x - l) / w) * tile.fovMM[0];
  mm[plane.v] = tile.leftTopMM[1] + ((t + h - y) / h) * tile.fovMM[1];
  return mm;
}

function allPoints() {
  const p = state.points;
  const list = [];
  if (p.apex) list.push({ kind: 'apex', mm: p.apex });
  if (p.base) list.push({ kind: 'base', mm: p.base });
  p.landmarks.forEach((mm, k) => list.push({ kind: 'landmark', index: k, mm }));
  p.annulus.forEach((mm, k) => list.push({ kind: 'annulus', index: k, mm }));
  return list;
}

function grab(tile, x, y) {
  const plane = PLANE[tile.axCorSag];
  const level = crosshairMM()[plane.w];
  let best = null;
  for (const point of allPoints()) {
    if (Math.abs(point.mm[plane.w] - level) > NEAR_MM) continue;
    const [sx, sy] = toScreen(tile, point.mm[plane.u], point.mm[plane.v]);
    const d = Math.hypot(sx - x, sy - y);
    if (d <= GRAB_PX && (!best || d < best.d)) best = { ...point, d };
  }
  return best;
}

function onPress(event) {
  if (event.type === 'mousedown') {  // the press a drag began with is not NiiVue's
    if (state.drag) event.stopPropagation();
    return;
  }
  if (event.button !== 0 || !nv || !nv.volumes.length) return;
  const [x, y] = canvasXY(event);
  const tile = tileAt(x, y);
  if (!tile) return;
  const hit = grab(tile, x, y);
  if (hit) {  // a point: select it and drag it (no mouse events follow a prevented pointerdown)
    event.stopPropagation();
    event.preventDefault();
    state.selected = hit.kind === 'landmark' ? hit.index : -1;
    state.drag = { ...hit, tile, fixed: hit.mm, before: copyPoints(state.points), moved: false };
    drawOverlay();
    return;
  }
  if (state.mode !== 'navigate' || event.shiftKey) {
    // the slices move to the point as NiiVue's cursor would, but NiiVue does
    // not draw a frame for the click: the surface's frame shows both (without
    // a graphics card a frame takes hundreds of ms, and the page waits for it)
    event.stopPropagation();
    event.preventDefault();
    const mm = mmAt(tile, x, y, crosshairMM());
    nv.scene.crosshairPos = nv.mm2frac(mm);
    place(mm, event.shiftKey);
    if (!complete(state.points)) nv.drawScene();
  }
}

function onMove(event) {
  const drag = state.drag;
  if (!drag) return;
  event.stopPropagation();
  const [x, y] = canvasXY(event);
  const mm = mmAt(drag.tile, x, y, drag.fixed);
  const p = state.points;
  if (drag.kind === 'apex') p.apex = mm;
  else if (drag.kind === 'base') p.base = mm;
  else p[drag.kind === 'landmark' ? 'landmarks' : 'annulus'][drag.index] = mm;
  drag.moved = true;
  drawOverlay();
}

function onRelease(event) {
  const drag = state.drag;
  if (!drag) return;
  event.stopPropagation();
  state.drag = null;
  if (drag.moved) {
    state.history.push(drag.before);
    sendPoints(drag.before);
  }
}

// -- surfaces ------------------------------------------------------------------

function receive(data) {
  if (data.job !== null && data.job < state.job) return;  // an older request's
  if (data.job !== null) state.job = data.job;
  const timing = state.timings.find((t) => t.job === data.job) || state.timings.find((t) => t.job === null);
  if (timing) {  // when the page had it, before drawing (which software rendering makes the slow part)
    const now = performance.now();
    if (timing.firstReceived === undefined) timing.firstReceived = now;
    if (data.final) timing.finalReceived = now;
  }
  const vertices = decode(data.vertices, Float32Array);
  if (data.final) state.vertices.set(data.frame, { vertices, data });
  if (data.frame !== state.frame) return;
  state.pending = { vertices, data };
  requestAnimationFrame(showPending);
}

function showPending() {
  const pending = state.pending;
  if (!pending) return;
  state.pending = null;
  showSurface(pending.vertices, pending.data);
}

function showSurface(vertices, data) {
  const mesh = nv.meshes[0];
  mesh.pts = vertices;
  mesh.visible = true;
  mesh.updateMesh(nv.gl);
  state.shown = vertices;
  nv.drawScene();
  drawOverlay();
  const gl = nv.gl;
  gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));  // waits for the frame to be drawn
  const timing = state.timings.find((t) => t.job === data.job) || state.timings.find((t) => t.job === null);
  if (timing) {
    const now = performance.now();
    if (timing.first === null) timing.first = now;
    if (data.final) timing.final = now;
  }
  $('volume').textContent = `${data.volume_ml.toFixed(1)} mL`;
  if (data.final) {
    $('detail').textContent = data.iterations !== undefined
      ? `frame ${data.frame + 1}: ${data.iterations} iterations, ${(1000 * data.seconds).toFixed(0)} ms (${data.message})` : '';
    $('warnings').textContent = (data.warnings || []).join('; ');
    document.body.dataset.job = String(data.job);
    if (data.job === state.job && !state.trackingRun) say('done', 'done');
  } else {
    $('detail').textContent = `iteration ${data.iteration}, level ${data.level}`;
  }
}

function hideSurface() {
  const mesh = nv.meshes[0];
  mesh.visible = false;
  state.shown = null;
  nv.drawScene();
  drawOverlay();
  $('volume').textContent = '-';
  $('detail').textContent = '';
  $('warnings').textContent = '';
}

// -- the overlay: contours and points on the slices -----------------------------

function drawOverlay() {
  const gl = $('gl');
  const overlay = $('overlay');
  if (overlay.width !== gl.width || overlay.height !== gl.height) {
    overlay.width = gl.width;
    overlay.height = gl.height;
  }
  const ctx = overlay.getContext('2d');
  ctx.clearRect(0, 0, overlay.width, overlay.height);
  if (!nv || !nv.volumes.length) return;
  const cross = crosshairMM();
  for (const tile of sliceTiles()) {
    const plane = PLANE[tile.axCorSag];
    const level = cross[plane.w];
    const [l, t, w, h] = tile.leftTopWidthHeight;
    ctx.save();
    ctx.beginPath();
    ctx.rect(l, t, w, h);
    ctx.clip();
    if (state.shown) drawContour(ctx, tile, plane, level);
    for (const point of allPoints()) drawPoint(ctx, tile, plane, level, point);
    ctx.restore();
  }
}

function drawContour(ctx, tile, plane, level) {
  const v = state.shown;
  const f = state.faces;
  ctx.strokeStyle = COLORS.contour;
  ctx.lineWidth = 2;
  ctx.beginPath();
  const cut = [];
  for (let k = 0; k < f.length; k += 3) {
    cut.length = 0;
    for (let e = 0; e < 3; e++) {
      const i = f[k + e];
      const j = f[k + ((e + 1) % 3)];
      const di = v[3 * i + plane.w] - level;
      const dj = v[3 * j + plane.w] - level;
      if ((di < 0) !== (dj < 0)) {
        const s = di / (di - dj);
        cut.push([v[3 * i + plane.u] + s * (v[3 * j + plane.u] - v[3 * i + plane.u]),
                  v[3 * i + plane.v] + s * (v[3 * j + plane.v] - v[3 * i + plane.v])]);
      }
    }
    if (cut.length === 2) {
      const a = toScreen(tile, cut[0][0], cut[0][1]);
      const b = toScreen(tile, cut[1][0], cut[1][1]);
      ctx.moveTo(a[0], a[1]);
      ctx.lineTo(b[0], b[1]);
    }
  }
  ctx.stroke();
}

function drawPoint(ctx, tile, plane, level, point) {
  const off = Math.abs(point.mm[plane.w] - level);
  const [x, y] = toScreen(tile, point.mm[plane.u], point.mm[plane.v]);
  const selected = point.kind === 'landmark' && point.index === state.selected;
  ctx.globalAlpha = off <= NEAR_MM ? 1 : 0.35;
  ctx.fillStyle = COLORS[point.kind];
  ctx.strokeStyle = selected ? COLORS.selected : '#000';
  ctx.lineWidth = selected ? 3 : 1.5;
  ctx.beginPath();
  ctx.arc(x, y, 5, 0, 2 * Math.PI);
  ctx.fill();
  ctx.stroke();
  ctx.globalAlpha = 1;
}

// -- sequences ----------------------------------------------------------------

function setFrame(frame) {
  state.frame = frame;
  $('frame').value = String(frame);
  $('framelabel').textContent = `${frame + 1}/${state.frames}`;
  nv.setFrame4D(nv.volumes[0].id, frame);
  const cached = state.vertices.get(frame);
  if (cached) showSurface(cached.vertices, cached.data);
  else if (complete(state.points) && !state.trackingRun) sendPoints(null);  // this frame from the same points
  else hideSurface();
  drawCurve();
}

function showTracking() {
  const t = state.tracking;
  $('indices').textContent = t
    ? `EDV ${t.edv_ml.toFixed(1)} mL (frame ${t.ed_frame + 1}), ESV ${t.esv_ml.toFixed(1)} mL ` +
      `(frame ${t.es_frame + 1}), EF ${t.ef_percent.toFixed(1)} %`
    : 'EDV - ESV - EF -';
  drawCurve();
}

function drawCurve() {
  const canvas = $('curve');
  const ctx = canvas.getContext('2d');
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const t = state.tracking;
  if (!t) return;
  const v = t.volumes_ml;
  const lo = Math.min(...v) * 0.95;
  const hi = Math.max(...v) * 1.05;
  const x = (k) => 24 + (k / Math.max(1, v.length - 1)) * (canvas.width - 34);
  const y = (ml) => canvas.height - 14 - ((ml - lo) / (hi - lo)) * (canvas.height - 24);
  ctx.strokeStyle = '#556';
  ctx.beginPath();
  ctx.moveTo(x(state.frame), 4);
  ctx.lineTo(x(state.frame), canvas.height - 14);
  ctx.stroke();
  ctx.strokeStyle = COLORS.contour;
  ctx.lineWidth = 2;
  ctx.beginPath();
  v.forEach((ml, k) => (k ? ctx.lineTo(x(k), y(ml)) : ctx.moveTo(x(k), y(ml))));
  ctx.stroke();
  for (const [k, color, label] of [[t.ed_frame, '#ff6b6b', 'ED'], [t.es_frame, '#6bb8ff', 'ES']]) {
    ctx.fillStyle = color;
    ctx.beginPath();
    ctx.arc(x(k), y(v[k]), 4, 0, 2 * Math.PI);
    ctx.fill();
    ctx.fillText(label, Math.min(x(k) + 7, canvas.width - 16), y(v[k]) + (k === t.ed_frame ? 10 : -4));
  }
  ctx.fillStyle = '#99a';
  ctx.fillText(`${hi.toFixed(0)} mL`, 0, 10);
  ctx.fillText(`${lo.toFixed(0)}`, 0, canvas.height - 14);
}

async function track() {
  state.trackingRun = true;
  say('tracking...', 'running');
  try {
    const { job } = await api('/api/track', { frame: state.frame });
    state.job = Math.max(state.job, job);
  } catch (error) {
    state.trackingRun = null;
    say(error.message, 'error');
  }
}

function play() {
  if (state.playing) {
    clearInterval(state.playing);
    state.playing = null;
    $('play').textContent = 'Play';
    return;
  }
  $('play').textContent = 'Pause';
  state.playing = setInterval(() => setFrame((state.frame + 1) % state.frames), 250);
}

async function save() {
  const folder = $('folder').value;
  say('saving...', 'running');
  try {
    const saved = await api('/api/save', { folder, frame: state.frame });
    $('saved').textContent = `${saved.files.length} files in ${saved.folder}`;
    document.body.dataset.saved = saved.folder;
    say('saved', 'done');
  } catch (error) {
    $('saved').textContent = error.message;
    say(error.message, 'error');
  }
}

// -- start --------------------------------------------------------------------

function listen() {
  const events = new EventSource('/api/events');
  events.addEventListener('surface', (e) => receive(JSON.parse(e.data)));
  events.addEventListener('cleared', () => hideSurface());
  events.addEventListener('progress', (e) => {
    const d = JSON.parse(e.data);
    if (d.job >= state.job) say(`tracking: ${d.done}/${d.total} frames`, 'running');
  });
  events.addEventListener('tracked', (e) => {
    const d = JSON.parse(e.data);
    if (d.job < state.job) return;
    state.tracking = d;
    state.trackingRun = null;
    showTracking();
    say('tracked', 'done');
  });
  events.addEventListener('failure', (e) => {
    const d = JSON.parse(e.data);
    if (d.job >= state.job) say(d.message, 'error');
  });
}

async function start() {
  const study = await api('/api/study');
  state.study = study;
  state.frames = study.frames;
  state.faces = decode(study.faces, Uint32Array);
  $('source').textContent = study.source;
  $('folder').value = `${study.source.replace(/(\.seq\.nrrd|\.nii\.gz|\.[^.]*)$/, '')}-spheroseg`;
  nv = new niivue.Niivue({
    backColor: [0.06, 0.07, 0.09, 1], crosshairColor: [0.25, 0.55, 1, 0.6], meshThicknessOn2D: 0, meshXRay: 0.35,
    dragAndDropEnabled: false, isSliceMM: true, multiplanarShowRender: niivue.SHOW_RENDER.ALWAYS,
    multiplanarLayout: niivue.MULTIPLANAR_TYPE.GRID, loadingText: 'loading the study...', logLevel: 'warn',
    isOrientationTextVisible: true,
  });
  await nv.attachToCanvas($('gl'));
  // the mesh exists before the volume: adding one later rebuilds the volume's textures
  let count = 0;
  for (const i of state.faces) count = Math.max(count, i + 1);
  const mesh = new niivue.NVMesh(new Float32Array(3 * count), state.faces, 'surface',
                                 new Uint8Array([255, 210, 60, 255]), 1.0, false, nv.gl);
  nv.addMesh(mesh);
  await nv.loadVolumes([{ url: '/api/volume.nii', name: 'study.nii', colormap: 'gray' }]);
  const draw = nv.drawScene.bind(nv);
  nv.drawScene = () => { const out = draw(); drawOverlay(); return out; };
  if (state.frames > 1) {
    $('sequence').hidden = false;
    $('frame').max = String(state.frames - 1);
    $('framelabel').textContent = `1/${state.frames}`;
  }
  for (const b of document.querySelectorAll('#modes button')) b.onclick = () => setMode(b.dataset.mode);
  $('undo').onclick = undo;
  $('delete').onclick = deleteSelected;
  $('clear').onclick = () => { changePoints((p) => { p.apex = null; p.base = null; p.landmarks = []; p.annulus = []; }); setMode('apex'); };
  $('frame').oninput = () => setFrame(Number($('frame').value));
  $('play').onclick = play;
  $('track').onclick = track;
  $('save').onclick = save;
  $('render3d').onchange = () => {
    nv.opts.multiplanarShowRender = $('render3d').checked ? niivue.SHOW_RENDER.ALWAYS : niivue.SHOW_RENDER.NEVER;
    nv.drawScene();
  };
  const views = $('views');
  for (const kind of ['pointerdown', 'mousedown']) views.addEventListener(kind, onPress, true);
  window.addEventListener('pointermove', onMove, true);
  window.addEventListener('pointerup', onRelease, true);
  document.addEventListener('keydown', (e) => {
    if (e.target.tagName === 'INPUT') return;
    if ((e.ctrlKey || e.metaKey) && e.key === 'z') { e.preventDefault(); undo(); return; }
    const keys = { a: 'apex', b: 'base', m: 'annulus', l: 'landmark', Escape: 'navigate' };
    if (keys[e.key]) setMode(keys[e.key]);
    if (e.key === 'Delete' || e.key === 'Backspace') deleteSelected();
  });
  listen();
  const p = study.points;
  state.points = { apex: p.apex, base: p.base, landmarks: p.landmarks, annulus: p.annulus };
  listPoints();
  if (complete(state.points)) {
    setMode('navigate');
    say('segmenting the given points...', 'running');
    try { const data = await api('/api/surface?frame=0'); receive(data); } catch (error) { /* still running */ }
  } else {
    setMode(state.points.apex ? 'base' : 'apex');
    document.body.dataset.state = 'ready';
  }
  drawOverlay();
}

window.viewer = { state, get nv() { return nv; }, crosshairMM, sliceTiles, toScreen };
start().catch((error) => say(`could not start: ${error.message}`, 'error'));

// spheroseg's viewer page: NiiVue shows the study (three slices and a 3D
// view); this script places points, sends them to the server, receives the
// surfaces it streams (Server-Sent Events) and draws the wall's contour on the
// slices.
//
// Coordinates: the page, the server, the files and every message use LPS
// millimetres (ITK's, 3D Slicer's files'). NiiVue draws in its own world
// frame ("display" here): NIfTI's RAS, turned 180 degrees about the
// left-right axis in the echo orientation so that the probe (the image's
// first z slices) is at the top of the long-axis slices, as echo machines
// show them. Both frames differ from LPS by signs only (toDisplay).
'use strict';

const $ = (id) => document.getElementById(id);
const COLORS = { contour: '#ffd23c', epicardium: '#ff5ad2', apex: '#ff4d4d', base: '#4dff88', landmark: '#4de1ff',
                 annulus: '#ff9f40', selected: '#ffffff' };
const NEAR_MM = 2.0;      // a point this close to a slice is drawn full, farther ones faded
const GRAB_PX = 9;        // how close a press must be to a point to drag it
const DRAG_SEND_MS = 120; // the least time between two segmentations sent while a point is dragged
// without a graphics card each picture the page shows costs the browser tens of ms
// of the CPU the segmentation runs on: intermediate surfaces are shown at most this often
const INTERMEDIATE_MS = 150;
const IDLE_3D_MS = 600;   // the 3D view is drawn once the slices have been still this long
const PLAY_MS = 250;      // Play shows one frame this often (frames the browser cannot keep up with are skipped)
// the tiles' names (3D echo's multiplanar planes): A and B contain the beam axis, C is across it
const TILE_NAMES = ['C plane', 'A plane', 'B plane'];
// display = LPS * SIGN (a map that is its own inverse)
const SIGN = { echo: [-1, 1, -1], anatomical: [-1, -1, 1] };
const HINTS = {
  apex: 'click the apex', base: 'click the base (centre of the mitral plane)',
  annulus: 'click points of the mitral annulus (3 or more)', landmark: 'click a point the wall must pass through',
  navigate: '',
};

const state = {
  study: null, frame: 0, frames: 1, echo: false, affine: null,  // echo: set at start
  points: { apex: null, base: null, landmarks: [], annulus: [] },
  history: [], future: [], mode: 'apex', selected: -1,
  // status: 'loading' | 'ready' | 'running' | 'done' | 'error' (document.body.dataset.state)
  status: 'loading', job: 0, faces: null, vertices: new Map(), shown: null, shownLPS: null, pending: null,
  tracking: null, trackingRun: null, playing: null, drag: null, dragSent: 0, later3D: null, slicesQueued: false,
  timings: [],          // per job: click, first and final surface drawn on the slices, 3D drawn (ms)
  epicardium: null,     // the shown frame's epicardium (display mm), when the myocardium is drawn
  note: null,           // [text, status] a note (a refused action) replaced: the next action puts it back
  server: null,         // the study's state as the server last said it (points, options, start frame)
  sending: 0,           // point requests not yet answered
  sent: 0,              // point requests sent (the newest's answer is adopted)
  inflight: null,       // the newest of them (a drag's release waits for it)
  // how often the page drew the 3D view, a new frame, and NiiVue a scene with the 3D view; the
  // 3D view's last cost (ms); Play's frames as [ms since Play, frame, the frame it began at]
  draws3D: 0, framesShown: 0, renders: 0, cost3D: 0, playLog: [],
  labels: [],           // the labels drawn on the tiles at the last overlay: [tile kind, text]
};
let nv = null;

// -- server -------------------------------------------------------------------

async function api(path, body) {
  const init = body === undefined ? {} : {
    method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body),
  };
  const response = await fetch(path, init);
  const data = await response.json();
  if (!response.ok) {
    const error = new Error(data.error || response.statusText);
    error.state = data.state;  // the study's state the refusal left unchanged
    throw error;
  }
  return data;
}

function decode(base64, Type) {
  const text = atob(base64);
  const bytes = new Uint8Array(text.length);
  for (let i = 0; i < text.length; i++) bytes[i] = text.charCodeAt(i);
  return new Type(bytes.buffer);
}

// -- status and modes: every transition goes through say(), note() and setMode() --

function show(text, status) {
  $('status').textContent = text;
  if (status) {
    state.status = status;
    document.body.dataset.state = status;
  }
}

// the study's state (segmenting, done, an error of the server's)
function say(text, status) {
  state.note = null;
  show(text, status);
}

// a note on an action that changed nothing (a refused click, nothing to undo):
// it stays until the next action, which puts back what the status said
function note(text, status = 'error') {
  if (!state.note) state.note = [$('status').textContent, state.status];
  show(text, status);
}

// the study's state changed by itself (a surface finished): said at once, or
// after the note on screen has gone
function settle(text, status) {
  if (state.note) state.note = [text, status];
  else say(text, status);
}

// the next action: a note goes, the status it replaced comes back
function viewChanged() {
  if (!state.note) return;
  const [text, status] = state.note;
  state.note = null;
  show(text, status);
}

function showHint() { $('hint').textContent = HINTS[state.mode]; }

function userMode(mode) { viewChanged(); setMode(mode); }

function setMode(mode) {
  state.mode = mode;
  for (const b of document.querySelectorAll('#modes button')) b.classList.toggle('active', b.dataset.mode === mode);
  showHint();
}

// the mode after a point is placed in ``mode``
function nextMode(mode, p) {
  if (mode === 'apex') return p.base === null && p.annulus.length < 3 ? 'base' : 'navigate';
  if (mode === 'base') return p.apex === null ? 'apex' : 'navigate';
  return mode;  // annulus points and landmarks: more may follow
}

// the mode that asks for what the points lack (after an undo, a redo, a refusal)
function modeFor(p, mode) {
  if (p.apex === null) return 'apex';
  if (p.base === null && p.annulus.length < 3) return mode === 'annulus' ? 'annulus' : 'base';
  return mode === 'apex' || mode === 'base' ? 'navigate' : mode;
}

// -- coordinates ----------------------------------------------------------------

function toDisplay(mm) {
  const s = SIGN[state.echo ? 'echo' : 'anatomical'];
  return [mm[0] * s[0], mm[1] * s[1], mm[2] * s[2]];
}
const toLPS = toDisplay;

function displayVertices(lps) {
  const s = SIGN[state.echo ? 'echo' : 'anatomical'];
  const out = new Float32Array(lps.length);
  for (let i = 0; i < lps.length; i++) out[i] = lps[i] * s[i % 3];
  return out;
}

// -- points -------------------------------------------------------------------

function copyPoints(p) {
  return { apex: p.apex && [...p.apex], base: p.base && [...p.base],
           landmarks: p.landmarks.map((q) => [...q]), annulus: p.annulus.map((q) => [...q]) };
}

function complete(p) { return p.apex !== null && (p.base !== null || p.annulus.length >= 3); }

function samePoints(a, b) { return JSON.stringify(a) === JSON.stringify(b); }

// the server's state is the one truth: the page lists, draws and saves its points
function adopt(server) {
  if (!server) return;
  state.server = server;
  state.points = copyPoints(server.points);
  const top = state.history[state.history.length - 1];
  if (top && samePoints(top, state.points)) state.history.pop();  // the step changed nothing
  listPoints();
  drawOverlay();
}

async function changePoints(change, { record = true } = {}) {
  const before = copyPoints(state.points);
  change(state.points);
  if (record) { state.history.push(before); state.future = []; }
  return sendPoints();
}

function expectJob(clickTime) {
  // the job's number comes with the reply, which may arrive after its surfaces
  const timing = { job: null, click: clickTime, first: null, final: null, final3d: null };
  state.timings.push(timing);
  return timing;
}

// send the page's points; the answer's state is then shown (a refusal's: the
// points the server kept). A drag's intermediate points keep the dragged one
// under the mouse: the release adopts the server's.
function sendPoints({ intermediate = false, released = null } = {}) {
  state.vertices.clear();
  state.tracking = null;
  showTracking();
  const timing = expectJob(performance.now());
  if (complete(state.points)) say('segmenting...', 'running');
  else if (!intermediate) say('', 'ready');
  state.sending += 1;
  const seq = ++state.sent;  // only the newest request's answer is the state (answers may cross)
  const sent = api('/api/points', { frame: state.frame, ...state.points }).then((reply) => {
    timing.job = reply.job;
    state.job = Math.max(state.job, reply.job);
    document.body.dataset.sent = String(reply.job);
    if (!intermediate && seq === state.sent) adopt(reply.state);
    if (!complete(state.points)) hideSurface();
  }, (error) => {
    if (intermediate) return;  // the drag goes on; its release says what the server kept
    if (seq !== state.sent) { note(error.message, 'error'); return; }  // a newer request is on its way
    adopt(error.state);
    // the status the note replaces: the kept points' job, finished or still running
    if (!complete(state.points)) show('', 'ready');
    else if (state.doneJob === state.job) show(state.donePoor ? 'done: poor result' : 'done', 'done');
    else show('segmenting...', 'running');
    const kept = released && error.state ? `; ${released.name} stays at its last accepted point` : '';
    if (kept) {  // the slices go back to it from the padding the drag ended in
      const point = allPoints().find((q) => q.kind === released.kind && (q.index === undefined ||
                                                                         q.index === released.index));
      if (point) { nv.scene.crosshairPos = nv.mm2frac(point.shown); drawSlices(); }
    }
    note(error.message + kept, 'error');
    if (!complete(state.points)) hideSurface();
  }).finally(() => {
    state.sending -= 1;
    listPoints();
    drawOverlay();
  });
  state.inflight = sent;
  return sent;
}

function place(mm, shift) {
  const mode = shift ? 'landmark' : state.mode;
  if (mode === 'landmark' && !complete(state.points)) { note('place the apex and the base first', 'error'); return; }
  const key = { apex: 'apex', base: 'base' }[mode];
  changePoints((p) => {
    if (key) p[key] = mm;
    else if (mode === 'annulus') p.annulus.push(mm);
    else if (mode === 'landmark') p.landmarks.push(mm);
  }).then(() => {
    if (state.status === 'error') setMode(mode);  // refused: the same point is asked for again
    const p = state.points;
    if (mode === 'annulus' && p.annulus.length < 3 && p.base === null && state.status !== 'error') {
      say(`${p.annulus.length} annulus point(s): 3 or more close the cavity at their plane`);
    }
  });
  if (mode === 'landmark') state.selected = state.points.landmarks.length - 1;
  if (!shift) setMode(nextMode(mode, state.points));
}

// undo: back one step of the history (the current points to the future); redo: the reverse
function step(from, to, word) {
  const points = from.pop();
  if (!points) { note(`nothing to ${word}`, state.status === 'error' ? 'ready' : state.status); return; }
  to.push(copyPoints(state.points));
  state.points = points;
  state.selected = -1;
  setMode(modeFor(points, state.mode));  // and its prompt: what the points now lack
  sendPoints();
}

const undo = () => step(state.history, state.future, 'undo');
const redo = () => step(state.future, state.history, 'redo');

function deleteSelected() {
  const k = state.selected;
  if (k < 0 || k >= state.points.landmarks.length) { note('click a landmark (cyan) to select it first', state.status); return; }
  state.selected = -1;
  changePoints((p) => { p.landmarks.splice(k, 1); });
}

function clearPoints() {
  changePoints((p) => { p.apex = null; p.base = null; p.landmarks = []; p.annulus = []; });
  setMode('apex');
}

async function find() {
  const timing = expectJob(performance.now());
  say('finding the ventricle...', 'running');
  try {
    const found = await api('/api/find', { frame: state.frame });
    state.history.push(copyPoints(state.points));
    state.future = [];
    adopt(found.state);
    state.vertices.clear();  // other frames' surfaces and the tracking were for the old points
    state.tracking = null;
    showTracking();
    timing.job = found.job;
    state.job = Math.max(state.job, found.job);
    document.body.dataset.sent = String(found.job);
    $('found').textContent = `found: confidence ${(100 * found.confidence).toFixed(0)} %` +
      (found.reason ? ` (${found.reason})` : '') + '; drag apex or base to correct them';
    showQuality(found);  // a location too uncertain is a poor start, said at once as the API says it
    const mid = [0, 1, 2].map((i) => 0.5 * (found.apex[i] + found.base[i]));
    nv.scene.crosshairPos = nv.mm2frac(toDisplay(mid));
    setMode('navigate');
    if (state.status === 'running') say('segmenting...', 'running');
  } catch (error) {
    $('found').textContent = '';
    adopt(error.state);
    say(`could not find the ventricle: ${error.message}`, 'error');
  }
  listPoints();
  drawSlices();
}

function listPoints() {
  const f = (p) => (p ? p.map((v) => v.toFixed(1)).join(', ') : '-');
  const p = state.points;
  $('pointlist').textContent = `LPS mm: apex (${f(p.apex)}) base (${f(p.base)}) landmarks ${p.landmarks.length}` +
    (p.annulus.length ? ` annulus ${p.annulus.length}` : '');
  const o = state.server && state.server.options;
  $('options').textContent = o ? `options: ${o.system}, ${o.patches.join(' x ')} patches, ${o.mode}, ` +
    `step ${o.step} mm, tol ${o.tol} mm` : '';
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
function crosshairLPS() { return toLPS(crosshairMM()); }

function canvasXY(event) {
  const canvas = $('gl');
  const r = canvas.getBoundingClientRect();
  return [(event.clientX - r.left) * (canvas.width / r.width), (event.clientY - r.top) * (canvas.height / r.height)];
}

function inside(t, x, y) {
  const [l, tp, w, h] = t.leftTopWidthHeight;
  return x >= l && x <= l + w && y >= tp && y <= tp + h;
}

function tileAt(x, y) { return sliceTiles().find((t) => inside(t, x, y)); }

function renderTileAt(x, y) {
  return nv.screenSlices.find((t) => t.axCorSag > 2 && t.leftTopWidthHeight && inside(t, x, y));
}

function mmAt(tile, x, y, fixed) {
  const [l, t, w, h] = tile.leftTopWidthHeight;
  const plane = PLANE[tile.axCorSag];
  const mm = [...fixed];
  mm[plane.u] = tile.leftTopMM[0] + ((x - l) / w) * tile.fovMM[0];
  mm[plane.v] = tile.leftTopMM[1] + ((t + h - y) / h) * tile.fovMM[1];
  return mm;
}

function inImage(mm) { return Array.from(nv.mm2frac(mm)).slice(0, 3).every((f) => f >= 0 && f <= 1); }

function allPoints() {
  const p = state.points;
  const list = [];
  if (p.apex) list.push({ kind: 'apex', mm: p.apex });
  if (p.base) list.push({ kind: 'base', mm: p.base });
  p.landmarks.forEach((mm, k) => list.push({ kind: 'landmark', index: k, mm }));
  p.annulus.forEach((mm, k) => list.push({ kind: 'annulus', index: k, mm }));
  return list.map((point) => ({ ...point, shown: toDisplay(point.mm) }));
}

function grab(tile, x, y) {
  const plane = PLANE[tile.axCorSag];
  const level = crosshairMM()[plane.w];
  let best = null;
  for (const point of allPoints()) {
    if (Math.abs(point.shown[plane.w] - level) > NEAR_MM) continue;
    const [sx, sy] = toScreen(tile, point.shown[plane.u], point.shown[plane.v]);
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
  const placing = state.mode !== 'navigate' || event.shiftKey;
  if (!tile) {
    if (placing && renderTileAt(x, y)) {
      note(`the 3D view only turns: ${HINTS[state.mode] || 'click'} on a slice`, 'error');
    }
    else if (placing) note('outside the image: click on a slice', 'error');
    return;
  }
  const hit = grab(tile, x, y);
  if (hit) {  // a point: select it and drag it (no mouse events follow a prevented pointerdown)
    event.stopPropagation();
    event.preventDefault();
    state.selected = hit.kind === 'landmark' ? hit.index : -1;
    state.drag = { ...hit, tile, fixed: hit.shown, before: copyPoints(state.points), moved: false };
    drawOverlay();
    return;
  }
  if (placing) {
    event.stopPropagation();
    event.preventDefault();
    const mm = mmAt(tile, x, y, crosshairMM());
    if (!inImage(mm)) { note('outside the image: click inside the volume', 'error'); return; }
    // the slices stay (as 3D Slicer's markups placement): the contour is then
    // drawn over them as soon as it comes, with no slice drawing before it
    place(toLPS(mm), event.shiftKey);
    drawOverlay();
  }
}

function onMove(event) {
  const drag = state.drag;
  if (!drag) return;
  event.stopPropagation();
  const [x, y] = canvasXY(event);
  const shown = mmAt(drag.tile, x, y, drag.fixed);
  if (!inImage(shown)) return;  // beside the image: the point stays at the last place inside it
  const mm = toLPS(shown);
  const p = state.points;
  if (drag.kind === 'apex') p.apex = mm;
  else if (drag.kind === 'base') p.base = mm;
  else p[drag.kind === 'landmark' ? 'landmarks' : 'annulus'][drag.index] = mm;
  drag.moved = true;
  nv.scene.crosshairPos = nv.mm2frac(shown);  // the other slices follow the point
  const now = performance.now();
  if (complete(p) && now - state.dragSent >= DRAG_SEND_MS) {  // the surface follows, throttled
    state.dragSent = now;
    sendPoints({ intermediate: true });
  }
  drawOverlay();
  requestSlices();
}

async function onRelease(event) {
  const drag = state.drag;
  if (!drag) return;
  event.stopPropagation();
  if (drag.moved) {
    state.history.push(drag.before);
    state.future = [];
    // after the last intermediate's answer: the server's points are then the
    // last it accepted, which a refused release leaves on both sides
    const released = copyPoints(state.points);
    if (state.inflight) await state.inflight.catch(() => {});
    state.points = released;
    state.drag = null;
    const name = { apex: 'the apex', base: 'the base', landmark: `landmark ${drag.index}`,
                   annulus: `annulus point ${drag.index}` }[drag.kind];
    sendPoints({ released: { name, kind: drag.kind, index: drag.index } });
  } else state.drag = null;
}

// -- drawing: the slices first, the 3D view when the slices are still ----------
// A new surface changes only the overlay's contour (a 2D canvas, drawn at
// once) and the 3D view's mesh; the slices' pictures change only when they
// move. Without a graphics card a frame with the 3D view takes seconds on a
// large echo, so the 3D view waits until nothing is running or dragged.

function drawSlices() {
  if (!nv) return;
  if (!$('render3d').checked) { nv.drawScene(); return; }
  nv.opts.multiplanarShowRender = niivue.SHOW_RENDER.NEVER;
  try { nv.drawScene(); } finally { nv.opts.multiplanarShowRender = niivue.SHOW_RENDER.ALWAYS; }
  schedule3D();
}

function requestSlices() {  // at most one slice drawing per animation frame
  if (state.slicesQueued) return;
  state.slicesQueued = true;
  requestAnimationFrame(() => { state.slicesQueued = false; drawSlices(); });
}

function schedule3D() {
  clearTimeout(state.later3D);
  if ($('render3d').checked) state.later3D = setTimeout(draw3D, IDLE_3D_MS);
}

function draw3D({ now = false } = {}) {
  state.later3D = null;
  if (!now && (state.drag || state.pending || state.slicesQueued || state.status === 'running' || state.playing)) {
    schedule3D();
    return;
  }
  for (const [mesh, pts] of [[nv.meshes[0], state.shown], [nv.meshes[1], state.epicardium]]) {
    mesh.visible = pts !== null;
    if (pts && mesh.pts !== pts) {
      mesh.pts = pts;
      mesh.updateMesh(nv.gl);
    }
  }
  state.draws3D += 1;
  const began = performance.now();
  nv.drawScene();
  const gl = nv.gl;
  gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));  // waits for the frame to be drawn
  state.cost3D = performance.now() - began;  // Play draws the 3D view only when a frame leaves this long
  const timing = state.timings.find((t) => t.job === state.job);
  if (timing && timing.final !== null && timing.final3d === null) timing.final3d = performance.now();
  document.body.dataset.drawn3d = String(state.job);
}

// -- surfaces ------------------------------------------------------------------

// a surface's timing record; before the request's reply has come, the newest
// request's (the server runs the newest job only)
function timingOf(job) {
  return state.timings.find((t) => t.job === job) || state.timings.findLast((t) => t.job === null);
}

function receive(data) {
  if (data.job !== null && data.job < state.job) return;  // an older request's
  if (data.job !== null) state.job = data.job;
  const timing = timingOf(data.job);
  if (timing) {  // when the page had it, before drawing (which software rendering makes the slow part)
    const now = performance.now();
    if (timing.firstReceived === undefined) timing.firstReceived = now;
    if (data.final) timing.finalReceived = now;
  }
  const vertices = decode(data.vertices, Float32Array);
  if (data.final) state.vertices.set(data.frame, { vertices, data });
  if (data.frame !== state.frame) return;
  state.pending = { vertices, data };
  if (data.final) showPending();  // at once: the one that matters
  else if (!state.pendingQueued) {  // intermediates: at most one per INTERMEDIATE_MS
    state.pendingQueued = true;
    setTimeout(() => { state.pendingQueued = false; requestAnimationFrame(showPending); }, INTERMEDIATE_MS);
  }
}

function showPending() {
  const pending = state.pending;
  if (!pending) return;
  state.pending = null;
  showSurface(pending.vertices, pending.data);
}

function showSurface(lps, data) {
  state.shownLPS = lps;
  state.shown = displayVertices(lps);
  state.epicardium = null;  // it belonged to the surface shown before
  if (data.final) { showEpicardium(data); showViews(); }
  drawOverlay();
  schedule3D();
  if (data.final) {  // the slices under it are drawn (a wait for the GPU: not for every intermediate)
    const gl = nv.gl;
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));
  }
  const timing = timingOf(data.job);
  if (timing) {
    const now = performance.now();
    if (timing.first === null) timing.first = now;
    if (data.final) timing.final = now;
  }
  $('volume').textContent = `${data.volume_ml.toFixed(1)} mL`;
  if (data.final) {
    const frame = state.frames > 1 ? `frame ${data.frame}: ` : '';
    $('detail').textContent = data.iterations !== undefined
      ? `${frame}${data.iterations} iterations, ${(1000 * data.seconds).toFixed(0)} ms; ${data.message}` : '';
    showQuality(data);
    document.body.dataset.job = String(data.job);
    state.doneJob = data.job;
    state.donePoor = Boolean(data.poor);
    // the points it was made from, when no newer ones are on their way
    if (data.points && data.job === state.job && !state.drag && !state.sending && !samePoints(data.points, state.points)) {
      state.points = copyPoints(data.points);
      listPoints();
      drawOverlay();
    }
    if (data.job === state.job && !state.trackingRun && !state.drag) {
      settle(data.poor ? 'done: poor result' : 'done', 'done');
    }
  } else {
    $('detail').textContent = `iteration ${data.iteration}, level ${data.level}`;
  }
}

function showQuality(data) {
  const banner = $('banner');
  const warnings = data.warnings || [];
  banner.hidden = !data.poor && !warnings.length;
  banner.classList.toggle('poor', Boolean(data.poor));
  banner.textContent = (data.poor ? 'Poor result, check before use: ' : 'Warning: ') + warnings.join('; ');
  document.body.dataset.poor = data.poor ? '1' : '0';
}

// the epicardium of a final surface, asked for only while the box is ticked
// (the endocardium's latency stays the same without it)
async function showEpicardium(data) {
  if (!$('myocardium').checked) return;
  let epi;
  try { epi = await api(`/api/epicardium?frame=${data.frame}`); } catch (error) { return; }  // points changed since
  if (epi.frame !== state.frame || epi.job !== state.job || !state.shown) return;
  state.epicardium = displayVertices(decode(epi.vertices, Float32Array));
  $('volume').textContent = `${data.volume_ml.toFixed(1)} mL, LV mass ${epi.lv_mass_g.toFixed(0)} g*`;
  $('caveats').textContent = `* LV mass: ${(epi.caveats || []).join('; ')}`;
  document.body.dataset.epicardium = String(epi.job);
  drawOverlay();
  schedule3D();
}

// the standard views of the shown frame's final surface, asked for only while their box is ticked
async function showViews() {
  const box = $('standardviews');
  if (!$('standard').checked || !state.shown) { box.replaceChildren(); state.views = null; return; }
  let data;
  try { data = await api(`/api/views?frame=${state.frame}`); } catch (error) { return; }  // points changed since
  if (data.frame !== state.frame || data.job !== state.job || !state.shown) return;
  state.views = data.views;
  box.replaceChildren();
  for (const view of data.views) {
    const figure = document.createElement('figure');
    const canvas = document.createElement('canvas');
    canvas.width = view.cols;
    canvas.height = view.rows;
    const ctx = canvas.getContext('2d');
    const grey = decode(view.image, Uint8Array);
    const pixels = ctx.createImageData(view.cols, view.rows);
    for (let i = 0; i < grey.length; i++) {
      pixels.data.set([grey[i], grey[i], grey[i], 255], 4 * i);
    }
    ctx.putImageData(pixels, 0, 0);
    ctx.strokeStyle = COLORS.contour;
    ctx.lineWidth = 1.5;
    ctx.beginPath();
    const c = view.contour;
    for (let k = 0; k < c.length; k += 4) { ctx.moveTo(c[k], c[k + 1]); ctx.lineTo(c[k + 2], c[k + 3]); }
    ctx.stroke();
    canvas.dataset.view = view.name;
    canvas.onclick = (event) => clickView(view, canvas, event);
    const caption = document.createElement('figcaption');
    caption.textContent = view.name;
    figure.append(canvas, caption);
    box.append(figure);
  }
  document.body.dataset.views = String(data.job);
}

// a click on a standard view: the point it shows, placed as a click on a slice would
function clickView(view, canvas, event) {
  const r = canvas.getBoundingClientRect();
  const col = ((event.clientX - r.left) * view.cols) / r.width;
  const row = ((event.clientY - r.top) * view.rows) / r.height;
  const a = (col - (view.cols - 1) / 2) * view.pixel_mm;
  const b = ((view.rows - 1) / 2 - row) * view.pixel_mm;
  const lps = [0, 1, 2].map((i) => view.centre[i] + a * view.u[i] + b * view.v[i]);
  if (state.mode === 'navigate' && !event.shiftKey) {  // the slices go there
    viewChanged();
    nv.scene.crosshairPos = nv.mm2frac(toDisplay(lps));
    drawSlices();
    return;
  }
  if (!inImage(toDisplay(lps))) { note('outside the image: click inside the volume', 'error'); return; }
  place(lps, event.shiftKey);
}

function hideSurface() {
  $('standardviews').replaceChildren();
  state.views = null;
  state.epicardium = null;
  $('caveats').textContent = '';
  state.shown = null;
  state.shownLPS = null;
  drawOverlay();
  schedule3D();
  $('volume').textContent = '-';
  $('detail').textContent = '';
  $('banner').hidden = true;
  document.body.dataset.poor = '0';
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
  const points = allPoints();
  state.labels = [];
  // the 3D tile's place (a drawing of the slices alone leaves it out of screenSlices)
  const render = nv.screenSlices.find((q) => q.axCorSag > 2 && q.leftTopWidthHeight);
  if (render) state.renderTile = [...render.leftTopWidthHeight];
  if (state.renderTile && $('render3d').checked) {
    const [l, t, w] = state.renderTile;
    drawLabel(ctx, '3D', l + w - 6, t + 18, 'right', 3);
  }
  for (const tile of sliceTiles()) {
    const plane = PLANE[tile.axCorSag];
    const level = cross[plane.w];
    const [l, t, w, h] = tile.leftTopWidthHeight;
    ctx.save();
    ctx.beginPath();
    ctx.rect(l, t, w, h);
    ctx.clip();
    if (state.shown) drawContour(ctx, tile, plane, level, state.shown, COLORS.contour);
    if (state.epicardium) drawContour(ctx, tile, plane, level, state.epicardium, COLORS.epicardium);
    for (const point of points) drawPoint(ctx, tile, plane, level, point);
    drawDirections(ctx, tile, plane);
    ctx.restore();
  }
}

// a label readable on speckle: light text on a dark box
function drawLabel(ctx, text, x, y, align, kind) {
  ctx.font = 'bold 15px system-ui, sans-serif';
  const width = ctx.measureText(text).width;
  const left = align === 'left' ? x : align === 'right' ? x - width : x - width / 2;
  ctx.fillStyle = 'rgba(0, 0, 0, 0.7)';
  ctx.fillRect(left - 3, y - 14, width + 6, 19);
  ctx.fillStyle = '#f2f5ff';
  ctx.fillText(text, left, y);
  state.labels.push([kind, text]);
}

// the LPS direction each screen edge points to, so a flipped view stays
// legible, and the tile's name
function drawDirections(ctx, tile, plane) {
  const names = [['R', 'L'], ['A', 'P'], ['I', 'S']];  // LPS axis: negative, positive end
  const s = SIGN[state.echo ? 'echo' : 'anatomical'];
  const [l, t, w, h] = tile.leftTopWidthHeight;
  const label = (axis, positive) => names[axis][(positive === (s[axis] > 0)) ? 1 : 0];
  const kind = tile.axCorSag;
  // on boxes: readable over speckle and over the crosshair's lines
  drawLabel(ctx, label(plane.v, true), l + w / 2, t + 18, 'center', kind);
  drawLabel(ctx, label(plane.v, false), l + w / 2, t + h - 6, 'center', kind);
  drawLabel(ctx, label(plane.u, false), l + 6, t + h / 2, 'left', kind);
  drawLabel(ctx, label(plane.u, true), l + w - 6, t + h / 2, 'right', kind);
  drawLabel(ctx, TILE_NAMES[kind], l + 6, t + 18, 'left', kind);
}

function drawContour(ctx, tile, plane, level, v, color) {
  const f = state.faces;
  ctx.strokeStyle = color;
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
  const off = Math.abs(point.shown[plane.w] - level);
  const [x, y] = toScreen(tile, point.shown[plane.u], point.shown[plane.v]);
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

// -- view: orientation, zoom, colour map -----------------------------------------

function setOrientation(echo) {
  const keep = crosshairLPS();
  state.echo = echo;
  const a = state.affine;
  // echo: 180 degrees about the left-right axis (a rotation: the 3D view is not mirrored)
  nv.volumes[0].setAffine(echo ? a.map((row, i) => (i === 1 || i === 2 ? row.map((x) => -x) : row)) : a);
  nv.updateGLVolume();
  nv.scene.crosshairPos = nv.mm2frac(toDisplay(keep));
  $('flip').textContent = echo ? 'Anatomical view' : 'Echo view';
  document.body.dataset.orientation = echo ? 'echo' : 'anatomical';
  if (state.shownLPS) state.shown = displayVertices(state.shownLPS);
  drawSlices();
  viewChanged();
}

function zoom(factor) {
  // about the crosshair, as NiiVue's own wheel zoom: the pan moves by the
  // zoom's change times the crosshair's mm, so that the crosshair stays put
  // on every tile (zooming about the world's origin would carry the
  // ventricle off the screen); 0 returns to the view as loaded
  const pan = Array.from(nv.scene.pan2Dxyzmm);
  if (factor === null) {
    nv.scene.pan2Dxyzmm = [0, 0, 0, 1];
  } else {
    const next = Math.min(8, Math.max(0.5, pan[3] * factor));
    const mm = nv.frac2mm(nv.scene.crosshairPos);
    nv.scene.pan2Dxyzmm = [0, 1, 2].map((i) => pan[i] + (pan[3] - next) * mm[i]).concat([next]);
  }
  drawSlices();
  viewChanged();
}

function setColormap(name) {
  nv.setColormap(nv.volumes[0].id, name);
  $('colormap').value = name;
  viewChanged();
}

// -- sequences ----------------------------------------------------------------

function setFrame(frame) {
  viewChanged();
  state.frame = frame;
  state.framesShown += 1;
  $('frame').value = String(frame);
  $('framelabel').textContent = `frame ${frame} (0-${state.frames - 1})`;
  if (state.playing && $('render3d').checked) {  // the slices now, the 3D view once below
    nv.opts.multiplanarShowRender = niivue.SHOW_RENDER.NEVER;
    try { nv.setFrame4D(nv.volumes[0].id, frame); } finally {
      nv.opts.multiplanarShowRender = niivue.SHOW_RENDER.ALWAYS;
    }
  } else nv.setFrame4D(nv.volumes[0].id, frame);
  const cached = state.vertices.get(frame);
  if (cached) showSurface(cached.vertices, cached.data);
  else if (complete(state.points) && !state.trackingRun && !state.playing) sendPoints();  // this frame, same points
  else hideSurface();
  drawCurve();
}

function stepFrame(delta) {
  if (state.frames > 1) setFrame((state.frame + delta + state.frames) % state.frames);
}

function showTracking() {
  const t = state.tracking;
  $('indices').textContent = t
    ? `EDV ${t.edv_ml.toFixed(1)} mL (frame ${t.ed_frame}), ESV ${t.esv_ml.toFixed(1)} mL ` +
      `(frame ${t.es_frame}), EF ${t.ef_percent.toFixed(1)} %; tracked from frame ${t.start_frame}`
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
  const x = (k) => 30 + (k / Math.max(1, v.length - 1)) * (canvas.width - 50);
  // the top 12 px are the axis label's: ED's label above its point stays below it
  const y = (ml) => canvas.height - 14 - ((ml - lo) / (hi - lo)) * (canvas.height - 40);
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
    // ED (the largest volume) is labelled above its point, ES beside it (the frame numbers are below)
    const ed = k === t.ed_frame;
    ctx.fillText(label, ed ? Math.min(x(k) - 6, canvas.width - 16) : Math.min(x(k) + 6, canvas.width - 16),
                 ed ? y(v[k]) - 7 : y(v[k]) - 4);
  }
  ctx.fillStyle = '#99a';
  ctx.fillText(`${hi.toFixed(0)} mL`, 0, 10);
  ctx.fillText(`${lo.toFixed(0)} mL`, 0, canvas.height - 18);
  // frame numbers under the curve, as many as fit (the first and the last always)
  const every = Math.max(1, Math.ceil(v.length / 10));
  ctx.textAlign = 'center';
  for (let k = 0; k < v.length; k++) {
    if (k % every === 0 || k === v.length - 1) ctx.fillText(String(k), x(k), canvas.height - 2);
  }
  ctx.textAlign = 'left';
  state.curveTicks = v.length;
}

async function track() {
  state.trackingRun = true;
  say('tracking...', 'running');
  try {
    const reply = await api('/api/track', { frame: state.frame });
    state.job = Math.max(state.job, reply.job);
    adopt(reply.state);
  } catch (error) {
    state.trackingRun = null;
    adopt(error.state);
    say(error.message, 'error');
  }
}

// one frame every PLAY_MS from when Play was pressed: a frame the browser is
// too slow to draw in time is skipped, so the sequence plays at its rate; the
// surfaces are decoded when they arrive, and the 3D view is drawn at most once a frame
function play() {
  if (state.playing) {
    clearTimeout(state.playing.timer);
    state.playing = null;
    $('play').textContent = 'Play';
    schedule3D();
    return;
  }
  $('play').textContent = 'Pause';
  const playing = { t0: performance.now(), first: state.frame, timer: null };
  state.playing = playing;
  const tick = () => {
    if (state.playing !== playing) return;
    const elapsed = performance.now() - playing.t0;
    const frame = (playing.first + Math.floor(elapsed / PLAY_MS)) % state.frames;
    if (frame !== state.frame) {
      state.playLog.push([elapsed, frame, playing.first]);
      setFrame(frame);
      // the 3D view once for this frame, if it can be drawn before the next is due
      const left = PLAY_MS - ((performance.now() - playing.t0) % PLAY_MS);
      if ($('render3d').checked && state.cost3D < left) draw3D({ now: true });
    }
    playing.timer = setTimeout(tick, PLAY_MS - ((performance.now() - playing.t0) % PLAY_MS));
  };
  playing.timer = setTimeout(tick, PLAY_MS);
}

async function save() {
  const folder = $('folder').value;
  viewChanged();
  const before = [$('status').textContent, state.status];
  show('saving...', 'running');
  try {
    const saved = await api('/api/save', { folder, frame: state.frame });
    adopt(saved.state);  // what was saved is what the page lists
    $('saved').textContent = `${saved.files.length} files in ${saved.folder}`;
    document.body.dataset.saved = saved.folder;
    say('saved', 'done');
  } catch (error) {
    $('saved').textContent = error.message;  // the error stays beside Save; the status's goes at the next action
    show(...before);
    note(error.message, 'error');
  }
}

// -- keys: the same whatever has the focus (except a text field) -----------------

function onKey(e) {
  const t = e.target;
  if (t && t.tagName === 'INPUT' && t.type === 'text') return;
  const ctrl = e.ctrlKey || e.metaKey;
  const key = e.key.length === 1 ? e.key.toLowerCase() : e.key;
  let done = true;
  if (ctrl && key === 'z' && !e.shiftKey) undo();
  else if (ctrl && (key === 'y' || (key === 'z' && e.shiftKey))) redo();
  else if (ctrl) done = false;
  else if (e.key === '?') toggleHelp();
  else if (key === 'Escape') { if (!$('help').hidden) toggleHelp(); else userMode('navigate'); }
  else if ({ a: 1, b: 1, m: 1, l: 1 }[key]) userMode({ a: 'apex', b: 'base', m: 'annulus', l: 'landmark' }[key]);
  else if (key === 'n') userMode('navigate');
  else if (key === 'Delete' || key === 'Backspace') deleteSelected();
  else if (key === 'ArrowRight' || key === 'ArrowUp') stepFrame(1);
  else if (key === 'ArrowLeft' || key === 'ArrowDown') stepFrame(-1);
  else if (key === 'f') setOrientation(!state.echo);
  else if (key === '+' || key === '=') zoom(1.25);
  else if (key === '-') zoom(0.8);
  else if (key === '0') zoom(null);
  else done = false;
  if (done) { e.preventDefault(); e.stopPropagation(); }
}

function toggleHelp() {
  viewChanged();
  $('help').hidden = !$('help').hidden;
}

// -- start --------------------------------------------------------------------

async function refresh() {
  // the surface of the current points, if the server has it (after a reload,
  // or when the job ended before this page's event stream opened)
  if (!complete(state.points)) return;
  try { receive(await api(`/api/surface?frame=${state.frame}`)); } catch (error) { /* still running */ }
}

function listen() {
  const events = new EventSource('/api/events');
  events.onopen = refresh;
  events.addEventListener('surface', (e) => receive(JSON.parse(e.data)));
  events.addEventListener('cleared', () => hideSurface());
  events.addEventListener('progress', (e) => {
    const d = JSON.parse(e.data);
    if (d.job >= state.job) settle(`tracking: ${d.done}/${d.total} frames`, 'running');
  });
  events.addEventListener('tracked', (e) => {
    const d = JSON.parse(e.data);
    if (d.job < state.job) return;
    state.tracking = d;
    state.trackingRun = null;
    adopt(d.state);
    showTracking();
    settle('tracked', 'done');
  });
  events.addEventListener('failure', (e) => {
    const d = JSON.parse(e.data);
    if (d.job >= state.job) { state.trackingRun = null; say(d.message, 'error'); }
  });
}

async function start() {
  const study = await api('/api/study');
  state.study = study;
  state.frames = study.frames;
  state.faces = decode(study.faces, Uint32Array);
  state.job = study.job;
  $('source').textContent = study.source;
  $('folder').value = `${study.source.replace(/(\.seq\.nrrd|\.nii\.gz|\.[^.]*)$/, '')}-spheroseg`;
  nv = new niivue.Niivue({
    backColor: [0.06, 0.07, 0.09, 1], crosshairColor: [0.25, 0.55, 1, 0.6], meshThicknessOn2D: 0, meshXRay: 0.35,
    dragAndDropEnabled: false, isSliceMM: true, multiplanarShowRender: niivue.SHOW_RENDER.ALWAYS,
    multiplanarLayout: niivue.MULTIPLANAR_TYPE.GRID, loadingText: 'loading the study...', logLevel: 'warn',
    isOrientationTextVisible: false,  // NiiVue's labels would name the display frame: drawDirections names LPS
    clipPlaneColor: [0.7, 0, 0.7, 0],
  });
  await nv.attachToCanvas($('gl'));
  // the mesh exists before the volume: adding one later rebuilds the volume's textures
  let count = 0;
  for (const i of state.faces) count = Math.max(count, i + 1);
  const mesh = new niivue.NVMesh(new Float32Array(3 * count), state.faces, 'surface',
                                 new Uint8Array([255, 210, 60, 255]), 1.0, false, nv.gl);
  nv.addMesh(mesh);
  const epicardium = new niivue.NVMesh(new Float32Array(3 * count), state.faces, 'epicardium',
                                       new Uint8Array([255, 90, 210, 255]), 0.5, false, nv.gl);
  epicardium.visible = false;
  nv.addMesh(epicardium);
  await nv.loadVolumes([{ url: '/api/volume.nii', name: 'study.nii', colormap: 'gray' }]);
  state.affine = nv.volumes[0].getAffine();
  // the 3D view cut through the middle, facing the viewer: the wall and the
  // cavity around the surface rather than the speckle of the volume's faces
  nv.setClipPlane([0, 270, 0]);
  setOrientation(true);
  const draw = nv.drawScene.bind(nv);  // eslint-disable-line
  nv.drawScene = () => {
    if (nv.opts.multiplanarShowRender !== niivue.SHOW_RENDER.NEVER) state.renders += 1;  // with the 3D view
    const out = draw();
    drawOverlay();
    return out;
  };
  if (state.frames > 1) {
    $('sequence').hidden = false;
    $('frame').max = String(state.frames - 1);
    $('framelabel').textContent = `frame 0 (0-${state.frames - 1})`;
  }
  for (const name of ['gray', 'hot', 'copper', 'bone', 'inferno', 'viridis']) {
    if (nv.colormaps().includes(name)) $('colormap').add(new Option(name, name));
  }
  for (const b of document.querySelectorAll('#modes button')) b.onclick = () => userMode(b.dataset.mode);
  $('undo').onclick = undo;
  $('redo').onclick = redo;
  $('delete').onclick = deleteSelected;
  $('clear').onclick = clearPoints;
  $('find').onclick = find;
  $('flip').onclick = () => setOrientation(!state.echo);
  $('zoomin').onclick = () => zoom(1.25);
  $('zoomout').onclick = () => zoom(0.8);
  $('colormap').onchange = () => setColormap($('colormap').value);
  $('helpbutton').onclick = toggleHelp;
  $('help').onclick = () => { viewChanged(); $('help').hidden = true; };
  $('frame').oninput = () => setFrame(Number($('frame').value));
  $('play').onclick = play;
  $('track').onclick = track;
  $('save').onclick = save;
  $('myocardium').onchange = () => {
    viewChanged();
    const cached = state.vertices.get(state.frame);
    if ($('myocardium').checked && cached && state.shown) showEpicardium(cached.data);
    else {
      state.epicardium = null;
      $('caveats').textContent = '';
      if (cached && state.shown) $('volume').textContent = `${cached.data.volume_ml.toFixed(1)} mL`;
      drawOverlay();
      schedule3D();
    }
  };
  $('standard').onchange = () => { viewChanged(); showViews(); };
  $('render3d').onchange = () => {
    viewChanged();
    nv.opts.multiplanarShowRender = $('render3d').checked ? niivue.SHOW_RENDER.ALWAYS : niivue.SHOW_RENDER.NEVER;
    if ($('render3d').checked) draw3D();
    else nv.drawScene();
  };
  const views = $('views');
  for (const kind of ['pointerdown', 'mousedown']) views.addEventListener(kind, onPress, true);
  window.addEventListener('pointermove', onMove, true);
  window.addEventListener('pointerup', onRelease, true);
  window.addEventListener('keydown', onKey, true);
  adopt(study.state);
  if (study.tracking) { state.tracking = study.tracking; showTracking(); }
  if (complete(state.points)) {
    setMode('navigate');
    say('segmenting the given points...', 'running');
  } else {
    setMode(state.points.apex ? 'base' : 'apex');
    say('', 'ready');
  }
  listen();
  drawOverlay();
}

window.viewer = { state, get nv() { return nv; }, crosshairMM, crosshairLPS, sliceTiles, toScreen, toDisplay,
                  TILE_NAMES };
start().catch((error) => say(`could not start: ${error.message}`, 'error'));

// softplot view: the page. Operator input -> WebSocket -> Plotter.cycle on the server ->
// state (carriages, the mark's scan pixels) -> one frame of the stereo view (gl.js).
// window.softplot is the page's test and scripting interface (see docs/viewer.md).
import { Renderer, VIEW_MODES } from './gl.js';
import { Panel } from './panel.js';

const params = new URLSearchParams(location.search);
const token = params.get('token') || '';
if (token) history.replaceState(null, '', location.pathname);  // keep it out of the history

let resolveReady, rejectReady;
const ready = new Promise((res, rej) => { resolveReady = res; rejectReady = rej; });
ready.catch(() => {});

const app = {
  info: null, st: null, zoom: 1, view: 'anaglyph-dubois', swap: false, frames: 0,
  mark: { shape: 'cross', colour: [1.0, 0.19, 0.13] },  // shapes: cross, cross-dot, dot, circle, none
  features: [[], []], featureList: [], dirty: true, seq: 0, pending: new Map(),
  afterFrame: [], sentAt: new Map(), latencies: [], lastDrawnSeq: 0, stSeq: 0,
  ws: null, renderer: null, readyDone: false, measure: { left: [], right: [] },
  proposal: null, relor: null,
};
const api = {
  ready,
  state: () => ({ ...(app.st || {}), zoom: app.zoom, view: app.view, swap: app.swap,
    frames: app.frames }),
  setView(mode) {
    if (!VIEW_MODES.includes(mode)) return Promise.reject(new Error(`unknown view ${mode}`));
    app.view = mode; panel.sync(); reportClient(); return nextFrame();
  },
  setSwap(b) { app.swap = !!b; panel.sync(); return nextFrame(); },
  setZoom(z) { setZoom(z); reportClient(); return nextFrame(); },
  setMode(mode, height) { return send({ op: 'mode', mode, height: height ?? null }); },
  setHeight(h) { return send({ op: 'height', height: h }); },
  setCarriage(X, Y) { return send({ op: 'cycle', X, Y }); },
  setParallax(px) {
    if (app.st.mode === 'free') return send({ op: 'free', X: app.st.X, Y: app.st.Y, DX: px, DY: app.st.DY });
    return send({ op: 'cycle', X: app.st.X, Y: app.st.Y, px });
  },
  setDXDY(DX, DY) { return send({ op: 'free', X: app.st.X, Y: app.st.Y, DX, DY }); },
  driveTo(X, Y, Z) { return send({ op: 'drive', X, Y, Z }); },
  record(code) { return send({ op: 'record', code }); },
  begin(code, kind) { return send({ op: 'begin', code, kind }); },
  vertex() { return send({ op: 'vertex' }); },
  end(close = false) { return send({ op: 'end', close }); },
  undo() { return send({ op: 'undo' }); },
  setWindow(lo, hi) { setWindow(lo, hi); return nextFrame(); },
  setMark(shape, colour) {
    if (shape) app.mark.shape = shape;
    if (colour) app.mark.colour = colour;
    panel.sync(); return nextFrame();
  },
  features: () => app.featureList,
  // canvas pixels: x, y from the top-left; RGBA bytes, rows from the top
  pixels: (x, y, w, h) => Array.from(app.renderer.pixels(x, y, w, h)),
  compositeTest: (view, left, right) => { const r = app.renderer.compositeTest(view, left, right); app.dirty = true; return r; },
  pixelsBase64(x, y, w, h) {
    const a = app.renderer.pixels(x, y, w, h);
    let s = '';
    for (let i = 0; i < a.length; i += 0x8000) s += String.fromCharCode.apply(null, a.subarray(i, i + 0x8000));
    return btoa(s);
  },
  canvasSize: () => [app.renderer.canvas.width, app.renderer.canvas.height],
  latencies: () => app.latencies.slice(),
  clearLatencies() { app.latencies = []; },
  // latencies end when the GPU has finished the frame (gl.finish), not when it was queued
  setLatencySync(b) { app.finish = !!b; },
  measure: (side, name, x, y) => send({ op: 'measure', side, name, x, y }),
  unmeasure: (side, name) => send({ op: 'unmeasure', side, name }),
  refine: (name) => send({ op: 'refine', name }),
  relor: () => send({ op: 'relor' }),
  measurements: () => app.measure,
  proposal: () => app.proposal,
  relorResult: () => app.relor,
  lastReply: null,
};
window.softplot = api;

function nextFrame() {
  app.dirty = true;
  return new Promise(res => app.afterFrame.push({ res, seq: 0 }));
}

// One message to the plotter; resolved after the first complete frame showing its answer.
function send(msg) {
  const seq = ++app.seq;
  msg.seq = seq;
  return new Promise((res, rej) => {
    app.pending.set(seq, { res, rej });
    app.sentAt.set(seq, performance.now());
    app.ws.send(JSON.stringify(msg));
  });
}

function setZoom(z) {
  const sc = app.info.scans.right;
  const fit = Math.min(innerWidth / sc.width, innerHeight / sc.height);
  app.zoom = Math.min(8, Math.max(Math.min(fit, 1) * 0.5, Number(z) || 1));
  app.dirty = true;
  panel.sync();
  if (api.lastReply) panel.status(api.lastReply);
}

function setWindow(lo, hi) {
  for (const c of app.renderer.tiles) {
    const full = c.info.full;
    const l = Math.max(0, Math.min(full - 1, Math.round(lo))), h = Math.max(l + 1, Math.min(full, Math.round(hi)));
    c.setWindow(l, h);
  }
  app.dirty = true;
}

function onReply(m) {
  api.lastReply = m;
  if (m.state) { app.st = m.state; app.stSeq = m.seq || app.stSeq; }
  if (m.features) app.featureList = m.features;
  if (m.measure) app.measure = m.measure;
  if (m.proposal) app.proposal = m.proposal;
  if (m.relor) app.relor = m.relor;
  if (m.features || m.measure) {
    // recorded features (object vertices projected into each scan) and measured points
    const meas = side => (app.measure[side] || []).map(([, x, y]) => ({ kind: 'measured', px: [[x, y]] }));
    app.features = [app.featureList.map(f => ({ kind: f.kind, px: f.left })).concat(meas('left')),
      app.featureList.map(f => ({ kind: f.kind, px: f.right })).concat(meas('right'))];
  }
  panel.status(m);
  app.dirty = true;
  const p = app.pending.get(m.seq);
  if (p) {
    app.pending.delete(m.seq);
    if (m.type === 'error') { p.rej(new Error(m.message)); return; }
    app.afterFrame.push({ res: () => p.res(m), seq: m.seq });
  }
}

function frame() {
  requestAnimationFrame(frame);
  panel.flush();
  if (!app.dirty || !app.st) return;
  app.dirty = false;
  const complete = app.renderer.draw(app.st, app.zoom, app.view, app.swap,
    { mark: app.mark, features: app.features });
  app.frames++;
  if (app.finish) app.renderer.gl.finish();  // count the GPU's work in the latency too
  const now = performance.now();
  // input-to-frame latency: carriage message out, state back, this frame drawn
  for (const [seq, t0] of app.sentAt) {
    if (seq <= app.stSeq) { app.latencies.push(now - t0); app.sentAt.delete(seq); }
  }
  if (app.latencies.length > 5000) app.latencies.splice(0, 1000);
  if (!complete) return;  // tiles still loading: another frame follows when they arrive
  const waiting = app.afterFrame;
  app.afterFrame = [];
  for (const w of waiting) w.res();
  if (!app.readyDone) { app.readyDone = true; resolveReady(api); }
  if (app.frames % 30 === 0) reportClient();
}

function reportClient() {
  if (app.ws && app.ws.readyState === 1)
    app.ws.send(JSON.stringify({ op: 'client', zoom: app.zoom, view: app.view, frames: app.frames }));
}

function noWebGL(why) {
  document.getElementById('nogl').hidden = false;
  document.getElementById('panel').hidden = true;
  document.getElementById('view').hidden = true;
  rejectReady(new Error(`WebGL2 unavailable: ${why}`));
}

let panel = null;
async function start() {
  const canvas = document.getElementById('view');
  const probe = document.createElement('canvas').getContext('webgl2');
  if (!probe) { noWebGL('this browser has no WebGL2 context'); return; }
  const r = await fetch('/api/info', { credentials: 'same-origin' });
  if (!r.ok) { document.getElementById('conn').textContent = `server: HTTP ${r.status}`; rejectReady(new Error(`info ${r.status}`)); return; }
  app.info = await r.json();
  try {
    app.renderer = new Renderer(canvas, app.info, () => { app.dirty = true; });
  } catch (e) { noWebGL(String(e)); return; }
  panel = new Panel(app, api, { setZoom, setWindow, send, nextFrame });
  const sc = app.info.scans.right;
  app.zoom = Math.min(1, Math.min(innerWidth / sc.width, innerHeight / sc.height));
  panel.sync();
  const ws = new WebSocket(`ws://${location.host}/ws` + (token ? `?token=${encodeURIComponent(token)}` : ''));
  app.ws = ws;
  ws.onopen = () => { document.getElementById('conn').textContent = 'connected'; send({ op: 'features' }); };
  ws.onclose = () => { document.getElementById('conn').textContent = 'disconnected (server stopped?)'; };
  ws.onmessage = ev => onReply(JSON.parse(ev.data));
  addEventListener('resize', () => { app.dirty = true; });
  requestAnimationFrame(frame);
}
start();

// The operator's controls: pointer-locked mouse for the carriages, wheel and keys for Z or
// the parallax handwheel, the small panel (modes, codes, recording, view, mark, window) and
// mono measurement clicks. Input is gathered per display frame and sent as one message.
import { VIEW_MODES } from './gl.js';

const $ = id => document.getElementById(id);
const hex = c => '#' + c.map(v => Math.round(v * 255).toString(16).padStart(2, '0')).join('');
const rgb = h => [1, 3, 5].map(i => parseInt(h.slice(i, i + 2), 16) / 255);

export class Panel {
  constructor(app, api, fn) {
    this.app = app; this.api = api; this.fn = fn;
    this.move = null;       // pending carriage target {X, Y, px?, DX?, DY?}
    this.inflight = 0;
    const canvas = $('view');
    $('title').textContent = `softplot: ${app.info.session}`;
    const sc = app.info.scans.left;
    $('lo').value = sc.window[0]; $('hi').value = sc.window[1];
    $('view-mode').onchange = e => { app.view = e.target.value; app.dirty = true; };
    $('swap').onchange = e => { app.swap = e.target.checked; app.dirty = true; };
    $('mode').onchange = e => this.setMode(e.target.value);
    this.codeTyped = false;
    $('code').oninput = () => { this.codeTyped = $('code').value.trim() !== ''; };
    $('height').onchange = e => {
      const h = parseFloat(e.target.value);
      if (Number.isFinite(h)) this.act(app.st.mode === 'contour' ? { op: 'mode', mode: 'contour', height: h } : null);
    };
    $('mark-shape').onchange = e => { app.mark.shape = e.target.value; app.dirty = true; };
    $('mark-colour').oninput = e => { app.mark.colour = rgb(e.target.value); app.dirty = true; };
    const win = () => fn.setWindow(+$('lo').value, +$('hi').value);
    $('lo').onchange = win; $('hi').onchange = win;
    $('b-record').onclick = () => this.act({ op: 'record', code: this.code() });
    $('b-begin').onclick = () => this.act({ op: 'begin', code: this.code() });
    $('b-vertex').onclick = () => this.act({ op: 'vertex' });
    $('b-end').onclick = () => this.act({ op: 'end', close: false });
    $('b-undo').onclick = () => this.act({ op: 'undo' });
    $('b-refine').onclick = () => this.act({ op: 'refine', name: $('pname').value });
    $('b-relor').onclick = () => this.act({ op: 'relor' });
    $('b-accept').onclick = () => {
      const p = app.proposal;
      if (p) this.act({ op: 'measure', side: 'right', name: p.name, x: p.x, y: p.y });
      app.proposal = null;
    };

    canvas.addEventListener('click', e => {
      if ($('measure').checked) return this.measureClick(e);
      if (document.pointerLockElement !== canvas && canvas.requestPointerLock) canvas.requestPointerLock();
    });
    document.addEventListener('mousemove', e => {
      if (document.pointerLockElement !== canvas) return;
      this.nudge(e.movementX, e.movementY, e.shiftKey);
    });
    canvas.addEventListener('wheel', e => {
      e.preventDefault();
      this.turn(e.deltaY < 0 ? 1 : -1, e.shiftKey);
    }, { passive: false });
    document.addEventListener('keydown', e => this.key(e));
  }

  // the feature code: what the operator typed, else the mode's default (a spot height in
  // single mode, a contour line in contour mode), which follows the mode until one is typed
  code() { return $('code').value.trim() || this.defaultCode(); }

  defaultCode() { return this.app.st && this.app.st.mode === 'contour' ? 'CONTOUR' : 'SPOT'; }

  act(msg) {
    if (!msg) return;
    this.fn.send(msg).catch(err => { $('message').textContent = String(err.message || err); });
  }

  setMode(mode) {
    const st = this.app.st;
    let h = parseFloat($('height').value);
    if (!Number.isFinite(h)) h = st.object ? st.object[2] : 0;
    this.act({ op: 'mode', mode, height: h });
  }

  // the carriage being commanded: the last one sent while messages are in flight (their
  // answers are not back yet), else the plotter's state
  target() {
    if (!this.move) {
      const st = this.inflight > 0 && this.sent ? this.sent : this.app.st;
      this.move = { X: st.X, Y: st.Y, DX: st.DX, DY: st.DY, px: st.px, height: st.height };
    }
    return this.move;
  }

  // mouse: carriage X, Y (instrument mm; y up, so the mouse's down is -Y); in free mode
  // with shift: DX, DY
  nudge(mx, my, shift) {
    const st = this.app.st; if (!st) return;
    const mm = this.app.info.scans.right.pixel_mm / this.app.zoom;
    const t = this.target();
    if (st.mode === 'free' && shift) { t.DX += mx * mm; t.DY -= my * mm; t.free = true; }
    else { t.X += mx * mm; t.Y -= my * mm; }
    t.moved = true;
  }

  // wheel / [ ]: Z in contour mode, the x-parallax handwheel in single, DX (shift: DY) in free
  turn(sign, shift) {
    const st = this.app.st; if (!st) return;
    const t = this.target();
    const pxStep = this.app.info.scans.left.pixel_mm / Math.max(this.app.zoom, 0.25) * 0.5;
    if (st.mode === 'contour') { t.height = (t.height ?? 0) + sign * (parseFloat($('zstep').value) || 1); t.dz = true; }
    else if (st.mode === 'single') { t.px += sign * pxStep; t.moved = true; }
    else { if (shift) t.DY += sign * pxStep; else t.DX += sign * pxStep; t.free = true; t.moved = true; }
  }

  // once per display frame: at most two carriage messages in flight
  flush() {
    const t = this.move;
    if (!t || this.inflight >= 2) return;
    this.move = null;
    this.sent = { X: t.X, Y: t.Y, DX: t.DX, DY: t.DY, px: t.px, height: t.height };
    const done = () => { this.inflight--; };
    const go = msg => { this.inflight++; this.fn.send(msg).then(done, err => { done(); $('message').textContent = String(err.message || err); }); };
    if (t.dz) go({ op: 'height', height: t.height });
    if (t.free) go({ op: 'free', X: t.X, Y: t.Y, DX: t.DX, DY: t.DY });
    else if (t.moved) go({ op: 'cycle', X: t.X, Y: t.Y, px: this.app.st.mode === 'single' ? t.px : null });
  }

  key(e) {
    if (e.target.tagName === 'INPUT' || e.target.tagName === 'SELECT') return;
    const app = this.app, k = e.key;
    if (k === '+' || k === '=') this.fn.setZoom(app.zoom * 2);
    else if (k === '-') this.fn.setZoom(app.zoom / 2);
    else if (k >= '1' && k <= '7') { app.view = VIEW_MODES[+k - 1]; app.dirty = true; }
    else if (k === 's') { app.swap = !app.swap; app.dirty = true; }
    else if (k === '[' || k === ']') this.turn(k === ']' ? 1 : -1, e.shiftKey);
    else if (k === 'm') this.setMode({ single: 'contour', contour: 'free', free: 'single' }[app.st.mode]);
    else if (k === 'r') this.act({ op: 'record', code: this.code() });
    else if (k === 'b') this.act({ op: 'begin', code: this.code() });
    else if (k === 'v' || k === ' ') this.act({ op: 'vertex' });
    else if (k === 'n') this.act({ op: 'end', close: false });
    else if (k === 'c') this.act({ op: 'end', close: true });
    else if (k === 'Backspace') this.act({ op: 'undo' });
    else if (k === 'h') $('panel').classList.toggle('hidden');
    else return;
    e.preventDefault();
    this.sync();
  }

  // mono measurement: the scan pixel under the click (mono-left / mono-right views)
  measureClick(e) {
    const app = this.app, v = app.view;
    if (v !== 'mono-left' && v !== 'mono-right') { $('message').textContent = 'measure in a mono view (mono-left or mono-right)'; return; }
    const side = v === 'mono-left' ? 'left' : 'right';
    const c = app.renderer.canvas, dpr = c.width / c.clientWidth;
    const r = c.getBoundingClientRect();
    const sx = (e.clientX - r.left) * dpr, sy = (e.clientY - r.top) * dpr;
    const centre = side === 'left' ? app.st.left_px : app.st.right_px;
    const x = centre[0] + (sx - c.width / 2) / app.zoom, y = centre[1] + (sy - c.height / 2) / app.zoom;
    this.act({ op: 'measure', side, name: $('pname').value.trim(), x, y });
  }

  sync() {
    const app = this.app;
    $('view-mode').value = app.view; $('swap').checked = app.swap;
    $('mark-shape').value = app.mark.shape; $('mark-colour').value = hex(app.mark.colour);
    if (app.st) $('mode').value = app.st.mode;
  }

  status(m) {
    const st = m.state; if (!st) return;
    const f = v => (v == null ? '-' : Number(v).toFixed(3));
    $('status').textContent =
      `${st.mode}${st.height != null ? ` Z=${f(st.height)}` : ''}  zoom ${this.app.zoom.toFixed(3)}\n` +
      `X ${f(st.X)}  Y ${f(st.Y)}  DX ${f(st.DX)}  DY ${f(st.DY)} mm\n` +
      `object ${st.object.map(f).join(', ')}  py ${f(st.py)}\n` +
      `left px ${st.left_px.map(f).join(', ')}  right px ${st.right_px.map(f).join(', ')}\n` +
      `${st.features} feature(s)${st.open_vertices ? `, line open: ${st.open_vertices} vertices` : ''}` +
      (st.in_travel ? '' : '\nDX/DY outside the travel') + (st.halted ? `\nHALTED: ${st.halted}` : '');
    $('message').textContent = m.type === 'error' ? m.message : (m.note || '');
    $('b-accept').hidden = !(m.proposal || (this.app.proposal && !m.measure));
    if (m.relor) {
      $('message').textContent += '\n' + m.relor.points.map(p => `${p.name}: py ${(p.py * 1000).toFixed(1)} um`).join('\n');
    }
    if (document.activeElement !== $('height') && st.height != null) $('height').value = st.height;
    if (document.activeElement !== $('mode')) $('mode').value = st.mode;
    if (!this.codeTyped && document.activeElement !== $('code')) $('code').value = this.defaultCode();
  }
}

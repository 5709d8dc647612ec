// WebGL2 renderer of the stereo view: one framebuffer per eye, one composite pass.
//
// Coordinates. Scan pixels: x right (column), y down (row), (0, 0) the centre of the top-left
// pixel (float64, CPU only). Eye framebuffer: `ew` x `eh` px (odd), y down, its centre (the
// floating mark) at (ew / 2, eh / 2). Everything reaches the GPU relative to the view centre
// (scan px minus the centre, times the zoom), computed in float64 here, so deep zoom into a
// large scan does not shimmer.

const TILE_VS = `#version 300 es
in vec2 a_corner;
uniform vec4 u_rect;   // x0, y0, x1, y1: screen px relative to the eye centre, y down
uniform vec4 u_uv;     // u0, v0, u1, v1
uniform vec2 u_half;   // ew / 2, eh / 2
out vec2 v_uv;
void main() {
  vec2 p = mix(u_rect.xy, u_rect.zw, a_corner);
  v_uv = mix(u_uv.xy, u_uv.zw, a_corner);
  gl_Position = vec4(p.x / u_half.x, -p.y / u_half.y, 0.0, 1.0);
}`;
const TILE_FS = `#version 300 es
precision highp float;
in vec2 v_uv;
uniform sampler2D u_tex;
out vec4 o;
void main() { float g = texture(u_tex, v_uv).r; o = vec4(g, g, g, 1.0); }`;

const LINE_VS = `#version 300 es
in vec2 a_pos;          // screen px relative to the eye centre, y down
uniform vec2 u_half;
void main() { gl_Position = vec4(a_pos.x / u_half.x, -a_pos.y / u_half.y, 0.0, 1.0);
  gl_PointSize = 1.0; }`;
const LINE_FS = `#version 300 es
precision highp float;
uniform vec4 u_colour;
out vec4 o;
void main() { o = u_colour; }`;

const COMP_VS = `#version 300 es
out vec2 v_uv;
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  v_uv = p;
  gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}`;
// Dubois (2001) least-squares red-cyan anaglyph matrices, rows = output r, g, b.
const COMP_FS = `#version 300 es
precision highp float;
in vec2 v_uv;
uniform sampler2D u_left;
uniform sampler2D u_right;
uniform int u_mode;     // 0 Dubois, 1 pure red/cyan, 2 grey, 3 mono (u_left only)
out vec4 o;
const vec3 L0 = vec3( 0.437,  0.449,  0.164), R0 = vec3(-0.011, -0.032, -0.007);
const vec3 L1 = vec3(-0.062, -0.062, -0.024), R1 = vec3( 0.377,  0.761,  0.009);
const vec3 L2 = vec3(-0.048, -0.050, -0.017), R2 = vec3(-0.026, -0.093,  1.234);
const vec3 LUM = vec3(0.299, 0.587, 0.114);
void main() {
  vec3 l = texture(u_left, v_uv).rgb;
  if (u_mode == 3) { o = vec4(l, 1.0); return; }
  vec3 r = texture(u_right, v_uv).rgb;
  vec3 c;
  if (u_mode == 0) c = vec3(dot(L0, l) + dot(R0, r), dot(L1, l) + dot(R1, r), dot(L2, l) + dot(R2, r));
  else if (u_mode == 1) c = vec3(l.r, r.g, r.b);
  else c = vec3(dot(LUM, l), dot(LUM, r), dot(LUM, r));
  o = vec4(clamp(c, 0.0, 1.0), 1.0);
}`;

export const VIEW_MODES = ['anaglyph-dubois', 'anaglyph-pure', 'anaglyph-grey', 'sbs-parallel',
  'sbs-cross', 'mono-left', 'mono-right'];

function compile(gl, vs, fs) {
  const prog = gl.createProgram();
  for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const sh = gl.createShader(type);
    gl.shaderSource(sh, src);
    gl.compileShader(sh);
    if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(sh));
    gl.attachShader(prog, sh);
  }
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  const u = {};
  const n = gl.getProgramParameter(prog, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < n; i++) {
    const name = gl.getActiveUniform(prog, i).name;
    u[name] = gl.getUniformLocation(prog, name);
  }
  return { prog, u };
}

// Pyramid tiles of one scan: textures fetched on demand, least recently used dropped.
export class TileCache {
  constructor(gl, eye, info, onload, max = 600) {
    this.gl = gl; this.eye = eye; this.info = info; this.onload = onload; this.max = max;
    this.T = info.tile; this.map = new Map(); this.inflight = 0; this.queue = [];
    this.lo = info.window[0]; this.hi = info.window[1];
  }
  setWindow(lo, hi) {
    this.lo = lo; this.hi = hi;
    for (const t of this.map.values()) if (t.tex) this.gl.deleteTexture(t.tex);
    this.map.clear(); this.queue = [];
  }
  key(L, tx, ty) { return `${L}/${tx}/${ty}`; }
  get(L, tx, ty, want) {
    const k = this.key(L, tx, ty);
    let t = this.map.get(k);
    if (t) { this.map.delete(k); this.map.set(k, t); return t.tex ? t : null; }
    if (!want) return null;
    t = { tex: null, L, tx, ty, gen: `${this.lo}/${this.hi}` };
    this.map.set(k, t);
    this.queue.push(t);
    this.pump();
    return null;
  }
  pump() {
    while (this.inflight < 6 && this.queue.length) {
      const t = this.queue.pop();
      this.inflight++;
      const url = `/tile/${this.eye}/${t.L}/${t.tx}/${t.ty}?lo=${this.lo}&hi=${this.hi}`;
      fetch(url, { credentials: 'same-origin' }).then(r => {
        if (!r.ok) throw new Error(`tile ${url}: HTTP ${r.status}`);
        return r.arrayBuffer();
      }).then(buf => {
        if (t.gen !== `${this.lo}/${this.hi}` || this.map.get(this.key(t.L, t.tx, t.ty)) !== t) return;
        const gl = this.gl, n = this.T + 2;
        const tex = gl.createTexture();
        gl.bindTexture(gl.TEXTURE_2D, tex);
        gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
        gl.texImage2D(gl.TEXTURE_2D, 0, gl.R8, n, n, 0, gl.RED, gl.UNSIGNED_BYTE, new Uint8Array(buf));
        gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
        gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
        gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
        gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
        t.tex = tex;
        this.evict();
      }).catch(err => {
        this.map.delete(this.key(t.L, t.tx, t.ty));
        console.warn(String(err));
      }).finally(() => { this.inflight--; this.pump(); this.onload(); });
    }
  }
  evict() {
    while (this.map.size > this.max) {
      const [k, t] = this.map.entries().next().value;
      if (t.tex) this.gl.deleteTexture(t.tex);
      this.map.delete(k);
    }
  }
  get pending() { return this.inflight + this.queue.length; }
}

function odd(n) { n = Math.max(1, Math.floor(n)); return n % 2 ? n : n - 1; }

export class Renderer {
  constructor(canvas, info, onload) {
    const gl = canvas.getContext('webgl2', { antialias: false, preserveDrawingBuffer: true,
      premultipliedAlpha: false, alpha: false });
    if (!gl) throw new Error('no WebGL2');
    this.gl = gl; this.canvas = canvas; this.info = info;
    this.tileProg = compile(gl, TILE_VS, TILE_FS);
    this.lineProg = compile(gl, LINE_VS, LINE_FS);
    this.compProg = compile(gl, COMP_VS, COMP_FS);
    this.quad = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.quad);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([0, 0, 1, 0, 0, 1, 1, 1]), gl.STATIC_DRAW);
    this.quadVao = gl.createVertexArray();
    gl.bindVertexArray(this.quadVao);
    gl.enableVertexAttribArray(0);
    gl.bindAttribLocation(this.tileProg.prog, 0, 'a_corner');
    gl.vertexAttribPointer(gl.getAttribLocation(this.tileProg.prog, 'a_corner'), 2, gl.FLOAT, false, 0, 0);
    this.lineBuf = gl.createBuffer();
    this.lineVao = gl.createVertexArray();
    gl.bindVertexArray(this.lineVao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.lineBuf);
    const la = gl.getAttribLocation(this.lineProg.prog, 'a_pos');
    gl.enableVertexAttribArray(la);
    gl.vertexAttribPointer(la, 2, gl.FLOAT, false, 0, 0);
    this.emptyVao = gl.createVertexArray();
    gl.bindVertexArray(null);
    this.tiles = [new TileCache(gl, 0, info.scans.left, onload),
      new TileCache(gl, 1, info.scans.right, onload)];
    this.eyes = [null, null];
  }

  // Size the canvas backing store (odd both ways, so one pixel sits on the mark).
  resize() {
    const dpr = window.devicePixelRatio || 1;
    const W = odd(window.innerWidth * dpr), H = odd(window.innerHeight * dpr);
    const c = this.canvas;
    if (c.width !== W || c.height !== H) {
      c.width = W; c.height = H;
      c.style.width = `${W / dpr}px`; c.style.height = `${H / dpr}px`;
    }
    return [W, H];
  }

  eyeTarget(k, w, h) {
    const gl = this.gl;
    let e = this.eyes[k];
    if (e && e.w === w && e.h === h) return e;
    if (e) { gl.deleteTexture(e.tex); gl.deleteFramebuffer(e.fb); }
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA8, w, h, 0, gl.RGBA, gl.UNSIGNED_BYTE, null);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    const fb = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
    e = { tex, fb, w, h };
    this.eyes[k] = e;
    return e;
  }

  // Draw one eye: its scan around `centre` (scan px, float64) at `zoom`, then the overlays.
  // Returns true when every tile of the wanted level was there.
  drawEye(k, target, centre, zoom, overlays) {
    const gl = this.gl, cache = this.tiles[k], sc = cache.info, T = cache.T;
    gl.bindFramebuffer(gl.FRAMEBUFFER, target.fb);
    gl.viewport(0, 0, target.w, target.h);
    gl.clearColor(0.08, 0.08, 0.1, 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    const hw = target.w / 2, hh = target.h / 2;
    const nL = sc.levels.length;
    const L = Math.min(nL - 1, Math.max(0, Math.floor(Math.log2(1 / zoom) + 1e-9)));
    const s = 2 ** L, [wL, hL] = sc.levels[L];
    const [cx, cy] = centre;
    const xmin = cx - hw / zoom, xmax = cx + hw / zoom, ymin = cy - hh / zoom, ymax = cy + hh / zoom;
    const ntx = Math.ceil(wL / T), nty = Math.ceil(hL / T);
    const tx0 = Math.max(0, Math.floor(Math.floor((xmin + 0.5) / s) / T));
    const tx1 = Math.min(ntx - 1, Math.floor(Math.floor((xmax + 0.5) / s) / T));
    const ty0 = Math.max(0, Math.floor(Math.floor((ymin + 0.5) / s) / T));
    const ty1 = Math.min(nty - 1, Math.floor(Math.floor((ymax + 0.5) / s) / T));
    const P = this.tileProg;
    gl.useProgram(P.prog);
    gl.uniform2f(P.u.u_half, hw, hh);
    gl.uniform1i(P.u.u_tex, 0);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindVertexArray(this.quadVao);
    let complete = true;
    const W0 = sc.width - 0.5, H0 = sc.height - 0.5;
    for (let ty = ty0; ty <= ty1; ty++) {
      for (let tx = tx0; tx <= tx1; tx++) {
        // the tile's content, level-0 continuous coords, clipped to the scan
        const X0 = tx * T * s - 0.5, Y0 = ty * T * s - 0.5;
        const X1 = Math.min((tx * T + Math.min(T, wL - tx * T)) * s - 0.5, W0);
        const Y1 = Math.min((ty * T + Math.min(T, hL - ty * T)) * s - 0.5, H0);
        let t = cache.get(L, tx, ty, true), La = L, ax = tx, ay = ty;
        if (!t) {
          complete = false;
          while (!t && La < nL - 1) {  // a coarser tile that holds this one, while loading
            La++; ax >>= 1; ay >>= 1;
            t = cache.get(La, ax, ay, false);
          }
          if (!t) continue;
        }
        const sa = 2 ** La, n = T + 2;
        const u = X => (1 + (X + 0.5) / sa - ax * T) / n;
        const v = Y => (1 + (Y + 0.5) / sa - ay * T) / n;
        gl.bindTexture(gl.TEXTURE_2D, t.tex);
        gl.uniform4f(P.u.u_rect, (X0 - cx) * zoom, (Y0 - cy) * zoom, (X1 - cx) * zoom, (Y1 - cy) * zoom);
        gl.uniform4f(P.u.u_uv, u(X0), v(Y0), u(X1), v(Y1));
        gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
      }
    }
    this.drawOverlays(target, centre, zoom, overlays);
    return complete;
  }

  lines(mode, pts, colour, hw, hh) {
    if (!pts.length) return;
    const gl = this.gl, P = this.lineProg;
    gl.useProgram(P.prog);
    gl.uniform2f(P.u.u_half, hw, hh);
    gl.uniform4f(P.u.u_colour, colour[0], colour[1], colour[2], 1);
    gl.bindVertexArray(this.lineVao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.lineBuf);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(pts), gl.STREAM_DRAW);
    gl.drawArrays(mode, 0, pts.length / 2);
  }

  drawOverlays(target, centre, zoom, ov) {
    const gl = this.gl, hw = target.w / 2, hh = target.h / 2;
    const [cx, cy] = centre;
    // recorded features at their image positions (this eye's scan px)
    for (const f of ov.features) {
      const pts = [];
      for (const [x, y] of f.px) pts.push((x - cx) * zoom, (y - cy) * zoom);
      const col = f.kind === 'open' ? [0.2, 0.9, 1.0] : f.kind === 'measured' ? [1.0, 0.3, 1.0] : [1.0, 0.85, 0.1];
      if (f.kind === 'measured') {
        const [x, y] = pts, a = 6;
        this.lines(gl.LINES, [x - a, y, x - 1, y, x + 1, y, x + a, y, x, y - a, x, y - 1, x, y + 1, x, y + a], col, hw, hh);
      } else if (f.kind === 'point' || pts.length === 2) {
        const [x, y] = pts, a = 5;
        this.lines(gl.LINES, [x - a, y - a, x + a + 1, y + a + 1, x - a, y + a, x + a + 1, y - a - 1], col, hw, hh);
      } else this.lines(gl.LINE_STRIP, pts, col, hw, hh);
    }
    // the floating mark, fixed at the eye centre (open in the middle, except 'dot' and
    // 'cross-dot', so the pixel under it stays visible)
    const m = ov.mark, c = m.colour, h = 0.5;
    if (m.shape === 'none') return;
    if (m.shape === 'dot') {
      this.lines(gl.TRIANGLE_STRIP, [-1.5, -1.5, 1.5, -1.5, -1.5, 1.5, 1.5, 1.5], c, hw, hh);
    } else if (m.shape === 'circle') {
      const ring = [];
      for (let i = 0; i <= 32; i++) { const a = i * Math.PI / 16; ring.push(6 * Math.cos(a), 6 * Math.sin(a)); }
      this.lines(gl.LINE_STRIP, ring, c, hw, hh);
    } else {
      const g = 3, a = 12;
      this.lines(gl.LINES, [-a - h, 0, -g + h, 0, g - h, 0, a + h, 0, 0, -a - h, 0, -g + h, 0, g - h, 0, a + h], c, hw, hh);
      if (m.shape === 'cross-dot') this.lines(gl.POINTS, [0, 0], c, hw, hh);
    }
  }

  // The composite pass alone over two constant eyes (rgb 0..1): the canvas centre pixel.
  compositeTest(view, left, right) {
    const gl = this.gl, [W, H] = this.resize();
    for (const [k, col] of [[0, left], [1, right]]) {
      const t = this.eyeTarget(k, W, H);
      gl.bindFramebuffer(gl.FRAMEBUFFER, t.fb);
      gl.viewport(0, 0, W, H);
      gl.clearColor(col[0], col[1], col[2], 1);
      gl.clear(gl.COLOR_BUFFER_BIT);
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, W, H);
    const P = this.compProg;
    gl.useProgram(P.prog);
    gl.bindVertexArray(this.emptyVao);
    gl.uniform1i(P.u.u_left, 0); gl.uniform1i(P.u.u_right, 1);
    gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D, this.eyes[0].tex);
    gl.activeTexture(gl.TEXTURE1); gl.bindTexture(gl.TEXTURE_2D, this.eyes[1].tex);
    gl.uniform1i(P.u.u_mode, { 'anaglyph-dubois': 0, 'anaglyph-pure': 1, 'anaglyph-grey': 2 }[view]);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.activeTexture(gl.TEXTURE0);
    return Array.from(this.pixels((W - 1) / 2, (H - 1) / 2, 1, 1)).slice(0, 3);
  }

  // The whole view. st: {left_px, right_px}, view: VIEW_MODES item, swap: bool.
  draw(st, zoom, view, swap, overlays) {
    const gl = this.gl;
    const [W, H] = this.resize();
    const sbs = view.startsWith('sbs');
    const ew = sbs ? odd(W / 2) : W, eh = H;
    const centres = [st.left_px, st.right_px];
    let complete = true;
    const need = view === 'mono-left' ? [0] : view === 'mono-right' ? [1] : [0, 1];
    for (const k of need) {
      const t = this.eyeTarget(k, ew, eh);
      const ov = { mark: overlays.mark, features: overlays.features[k] };
      complete = this.drawEye(k, t, centres[k], zoom, ov) && complete;
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, W, H);
    gl.clearColor(0, 0, 0, 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    const P = this.compProg;
    gl.useProgram(P.prog);
    gl.bindVertexArray(this.emptyVao);
    gl.uniform1i(P.u.u_left, 0);
    gl.uniform1i(P.u.u_right, 1);
    const bind = (a, b) => {
      gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D, this.eyes[a].tex);
      gl.activeTexture(gl.TEXTURE1); gl.bindTexture(gl.TEXTURE_2D, this.eyes[b].tex);
    };
    let [A, B] = swap ? [1, 0] : [0, 1];
    if (view.startsWith('mono')) {
      const k = view === 'mono-left' ? 0 : 1;
      bind(k, k); gl.uniform1i(P.u.u_mode, 3);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
    } else if (sbs) {
      if (view === 'sbs-cross') [A, B] = [B, A];
      gl.uniform1i(P.u.u_mode, 3);
      gl.viewport(0, 0, ew, eh); bind(A, A); gl.drawArrays(gl.TRIANGLES, 0, 3);
      gl.viewport(W - ew, 0, ew, eh); bind(B, B); gl.drawArrays(gl.TRIANGLES, 0, 3);
    } else {
      bind(A, B);
      gl.uniform1i(P.u.u_mode, { 'anaglyph-dubois': 0, 'anaglyph-pure': 1, 'anaglyph-grey': 2 }[view]);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
    }
    gl.activeTexture(gl.TEXTURE0);
    return complete;
  }

  // Canvas pixels (x, y from the top-left, y down), RGBA bytes row by row from the top.
  pixels(x, y, w, h) {
    const gl = this.gl, H = this.canvas.height;
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    const buf = new Uint8Array(w * h * 4);
    gl.readPixels(x, H - y - h, w, h, gl.RGBA, gl.UNSIGNED_BYTE, buf);
    const out = new Uint8Array(w * h * 4);
    for (let r = 0; r < h; r++) out.set(buf.subarray((h - 1 - r) * w * 4, (h - r) * w * 4), r * w * 4);
    return out;
  }
}

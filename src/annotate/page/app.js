// nerflabel annotate: place oriented 3D boxes on a scan's point cloud and
// check the masks they give. Plain WebGL and DOM, no library; talks to the
// server's /api (see src/annotate/api.rs).
'use strict';

const $ = (id) => document.getElementById(id);
const STEP = 0.01; // nudge, metres
const YAW_STEP = Math.PI / 180;

// ---------- small vector and matrix helpers (column-major 4x4 for WebGL) ----------
const v3 = {
  add: (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]],
  sub: (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]],
  mul: (a, s) => [a[0] * s, a[1] * s, a[2] * s],
  dot: (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2],
  cross: (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]],
  norm: (a) => { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; },
};
function mat4Mul(a, b) {
  const o = new Float32Array(16);
  for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
    let s = 0;
    for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
    o[c * 4 + r] = s;
  }
  return o;
}
function lookAt(eye, target, up) {
  const f = v3.norm(v3.sub(target, eye));
  const s = v3.norm(v3.cross(f, up));
  const u = v3.cross(s, f);
  return new Float32Array([s[0], u[0], -f[0], 0, s[1], u[1], -f[1], 0, s[2], u[2], -f[2], 0,
    -v3.dot(s, eye), -v3.dot(u, eye), v3.dot(f, eye), 1]);
}
function perspective(fovy, aspect, near, far) {
  const f = 1 / Math.tan(fovy / 2);
  return new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) / (near - far), -1, 0, 0, 2 * far * near / (near - far), 0]);
}
function ortho(hw, hh, near, far) {
  return new Float32Array([1 / hw, 0, 0, 0, 0, 1 / hh, 0, 0, 0, 0, -2 / (far - near), 0, 0, 0, -(far + near) / (far - near), 1]);
}
// Rotation about unit axis `a` by angle t, as rows of a 3x3.
function axisRotation(a, t) {
  const c = Math.cos(t), s = Math.sin(t), C = 1 - c;
  const [x, y, z] = a;
  return [[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
    [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
    [z * x * C - y * s, z * y * C + x * s, c + z * z * C]];
}
const m3Mul = (a, b) => a.map((row) => [0, 1, 2].map((j) => row[0] * b[0][j] + row[1] * b[1][j] + row[2] * b[2][j]));
const col = (r, j) => [r[0][j], r[1][j], r[2][j]];

// The instance colour (same hues as the server's previews).
function colour(id) {
  const h = (id * 0.618033988749895) % 1, s = 0.75, v = 1;
  const h6 = h * 6, f = h6 - Math.floor(h6);
  const p = v * (1 - s), q = v * (1 - s * f), t = v * (1 - s * (1 - f));
  return [[v, t, p], [q, v, p], [p, v, t], [p, q, v], [t, p, v], [v, p, q]][Math.floor(h6) % 6];
}
const css = (c) => `rgb(${c.map((x) => Math.round(x * 255)).join(',')})`;

// ---------- state ----------
const state = {
  boxes: [], selected: -1, undo: [], redo: [],
  up: [0, 0, 1], gx: [1, 0, 0], gy: [0, 1, 0],
  cloud: null, frames: [], info: null,
  view: 'orbit', drawing: false, drag: null, rect: null,
  target: [0, 0, 0], dist: 3, azimuth: -Math.PI / 2, elevation: 0.6,
  dirty: false,
};

function groundFrame(up) {
  up = v3.norm(up);
  const seed = Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
  const gx = v3.norm(v3.sub(seed, v3.mul(up, v3.dot(seed, up))));
  return { up, gx, gy: v3.cross(up, gx) };
}

function status(text, kind) {
  const el = $('status');
  el.textContent = text;
  el.className = kind || '';
}

async function api(method, url, body) {
  const res = await fetch(url, { method, body: body === undefined ? undefined : JSON.stringify(body), headers: { 'Content-Type': 'application/json' } });
  const type = res.headers.get('Content-Type') || '';
  const data = type.includes('json') ? await res.json() : await res.blob();
  if (!res.ok) throw new Error((data && data.error) || `${method} ${url}: ${res.status}`);
  return data;
}

// ---------- boxes ----------
const copyBoxes = () => JSON.parse(JSON.stringify(state.boxes));
function commit(before) {
  state.undo.push(before);
  if (state.undo.length > 200) state.undo.shift();
  state.redo = [];
  changed();
}
function edit(fn) {
  if (state.selected < 0) return;
  const before = copyBoxes();
  fn(state.boxes[state.selected]);
  commit(before);
}
function changed() {
  state.dirty = true;
  refreshPanel();
  draw();
  drawOrthos();
  schedulePreview();
}
function boxesDocument() {
  return { boxes: state.boxes.map((b) => ({ label: b.label, center: b.center, size: b.size, rotation: b.rotation })) };
}
function yawOf(b) {
  const x = col(b.rotation, 0);
  return Math.atan2(v3.dot(x, state.gy), v3.dot(x, state.gx));
}
function rotateYaw(b, t) {
  b.rotation = m3Mul(axisRotation(state.up, t), b.rotation);
}
function moveGround(b, dx, dy, dz) {
  b.center = v3.add(b.center, v3.add(v3.add(v3.mul(state.gx, dx), v3.mul(state.gy, dy)), v3.mul(state.up, dz)));
}
function resize(b, axis, delta) {
  b.size[axis] = Math.max(0.005, b.size[axis] + delta);
}
function corners(b) {
  const h = b.size.map((s) => s / 2);
  const out = [];
  for (let i = 0; i < 8; i++) {
    const s = [i & 1 ? h[0] : -h[0], i & 2 ? h[1] : -h[1], i & 4 ? h[2] : -h[2]];
    out.push([0, 1, 2].map((k) => b.center[k] + b.rotation[k][0] * s[0] + b.rotation[k][1] * s[1] + b.rotation[k][2] * s[2]));
  }
  return out;
}
const toLocal = (b, p) => { const d = v3.sub(p, b.center); return [0, 1, 2].map((j) => d[0] * b.rotation[0][j] + d[1] * b.rotation[1][j] + d[2] * b.rotation[2][j]); };

async function fitRegion(body) {
  status('fitting...');
  try {
    const res = await api('POST', '/api/fit', body);
    return res.box;
  } catch (e) {
    status(e.message, 'error');
    return null;
  }
}

async function createFromRect(a, b) {
  const c = state.target;
  const h = v3.dot(c, state.up);
  const p = (u, v) => v3.add(v3.add(v3.mul(state.gx, u), v3.mul(state.gy, v)), v3.mul(state.up, h));
  const [u0, u1] = [Math.min(a[0], b[0]), Math.max(a[0], b[0])];
  const [w0, w1] = [Math.min(a[1], b[1]), Math.max(a[1], b[1])];
  const label = lastLabel();
  // A click (no drag) fits the object nearest the clicked point.
  const click = u1 - u0 < 0.005 || w1 - w0 < 0.005;
  const region = click ? { seed: p(a[0], a[1]) } : { polygon: [p(u0, w0), p(u1, w0), p(u1, w1), p(u0, w1)] };
  const box = await fitRegion({ ...region, label });
  if (!box) return;
  const before = copyBoxes();
  state.boxes.push(box);
  state.selected = state.boxes.length - 1;
  commit(before);
  status(`box ${state.boxes.length} fitted: ${box.size.map((s) => s.toFixed(3)).join(' x ')} m`, 'ok');
}

async function shrinkSelected() {
  if (state.selected < 0) return;
  const b = state.boxes[state.selected];
  const fitted = await fitRegion({ shrink: { label: b.label, center: b.center, size: b.size, rotation: b.rotation } });
  if (!fitted) return;
  edit((s) => Object.assign(s, fitted));
  status('shrunk to the points inside', 'ok');
}

function lastLabel() {
  for (let i = state.boxes.length - 1; i >= 0; i--) if (state.boxes[i].label) return state.boxes[i].label;
  return 'object';
}

async function save() {
  try {
    const res = await api('PUT', '/api/boxes', boxesDocument());
    state.dirty = false;
    status(`saved ${res.saved} boxes to ${res.file}`, 'ok');
  } catch (e) {
    status(`not saved: ${e.message}`, 'error');
  }
}

function undo() {
  if (!state.undo.length) return;
  state.redo.push(copyBoxes());
  state.boxes = state.undo.pop();
  state.selected = Math.min(state.selected, state.boxes.length - 1);
  changed();
}
function redo() {
  if (!state.redo.length) return;
  state.undo.push(copyBoxes());
  state.boxes = state.redo.pop();
  state.selected = Math.min(state.selected, state.boxes.length - 1);
  changed();
}

// ---------- WebGL ----------
const canvas = $('scene');
const gl = canvas.getContext('webgl', { antialias: true, preserveDrawingBuffer: true });
function program(vs, fs) {
  const p = gl.createProgram();
  for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    gl.attachShader(p, s);
  }
  gl.linkProgram(p);
  return p;
}
const VS = `attribute vec3 pos; attribute vec3 col; uniform mat4 mvp; uniform float size; varying vec3 c;
void main() { gl_Position = mvp * vec4(pos, 1.0); gl_PointSize = size; c = col; }`;
const FS = `precision mediump float; varying vec3 c; void main() { gl_FragColor = vec4(c, 1.0); }`;
let prog = null, cloudBuf = null, colourBuf = null, lineBuf = null;
if (gl) {
  prog = program(VS, FS);
  cloudBuf = gl.createBuffer(); colourBuf = gl.createBuffer(); lineBuf = gl.createBuffer();
}

function matrices() {
  const w = canvas.clientWidth || 1, h = canvas.clientHeight || 1;
  const aspect = w / h;
  if (state.view === 'top') {
    const eye = v3.add(state.target, v3.mul(state.up, 50));
    const view = lookAt(eye, state.target, state.gy);
    const hh = state.dist * 0.5;
    return { mvp: mat4Mul(ortho(hh * aspect, hh, 0.01, 200), view), w, h };
  }
  const { up, gx, gy } = state;
  const ce = Math.cos(state.elevation);
  const dir = v3.add(v3.add(v3.mul(gx, ce * Math.cos(state.azimuth)), v3.mul(gy, ce * Math.sin(state.azimuth))), v3.mul(up, Math.sin(state.elevation)));
  const eye = v3.add(state.target, v3.mul(dir, state.dist));
  const view = lookAt(eye, state.target, up);
  return { mvp: mat4Mul(perspective(0.8, aspect, state.dist * 0.01, state.dist * 20), view), w, h };
}

// World point to canvas pixels (CSS), or null behind the camera.
function project(p, m) {
  m = m || matrices();
  const x = m.mvp, q = [p[0], p[1], p[2], 1];
  const r = [0, 1, 2, 3].map((i) => x[i] * q[0] + x[4 + i] * q[1] + x[8 + i] * q[2] + x[12 + i] * q[3]);
  if (r[3] <= 0) return null;
  return [(r[0] / r[3] * 0.5 + 0.5) * m.w, (1 - (r[1] / r[3] * 0.5 + 0.5)) * m.h];
}
// Canvas pixels to ground (u, v) in the top view.
function topGround(px, py) {
  const w = canvas.clientWidth, h = canvas.clientHeight;
  const hh = state.dist * 0.5, hw = hh * w / h;
  const nx = px / w * 2 - 1, ny = 1 - py / h * 2;
  return [v3.dot(state.target, state.gx) + nx * hw, v3.dot(state.target, state.gy) + ny * hh];
}

function lines() {
  const pos = [], cols = [];
  const seg = (a, b, c) => { pos.push(...a, ...b); cols.push(...c, ...c); };
  const EDGES = [[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]];
  state.boxes.forEach((b, i) => {
    const c = i === state.selected ? [1, 1, 1] : colour(i + 1);
    const k = corners(b);
    for (const [a, e] of EDGES) seg(k[a], k[e], c);
    const front = v3.add(b.center, v3.mul(col(b.rotation, 0), b.size[0] / 2));
    seg(b.center, front, c);
  });
  const traj = state.frames.map((f) => f.position);
  for (let i = 1; i < traj.length; i++) seg(traj[i - 1], traj[i], [1, 0.85, 0.2]);
  for (const f of state.frames) seg(f.position, v3.add(f.position, v3.mul(v3.norm(f.forward), 0.05)), [1, 0.6, 0.1]);
  if (state.rect) {
    const [a, b] = state.rect;
    const h = v3.dot(state.target, state.up);
    const p = (u, v) => v3.add(v3.add(v3.mul(state.gx, u), v3.mul(state.gy, v)), v3.mul(state.up, h));
    const q = [p(a[0], a[1]), p(b[0], a[1]), p(b[0], b[1]), p(a[0], b[1])];
    for (let i = 0; i < 4; i++) seg(q[i], q[(i + 1) % 4], [0.3, 1, 0.4]);
  }
  return { pos: new Float32Array(pos), cols: new Float32Array(cols) };
}

function draw() {
  if (!gl) return;
  const dpr = window.devicePixelRatio || 1;
  const W = Math.round(canvas.clientWidth * dpr), H = Math.round(canvas.clientHeight * dpr);
  if (canvas.width !== W || canvas.height !== H) { canvas.width = W; canvas.height = H; }
  gl.viewport(0, 0, W, H);
  gl.clearColor(0.08, 0.09, 0.1, 1);
  gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  gl.enable(gl.DEPTH_TEST);
  gl.useProgram(prog);
  const m = matrices();
  gl.uniformMatrix4fv(gl.getUniformLocation(prog, 'mvp'), false, m.mvp);
  const posLoc = gl.getAttribLocation(prog, 'pos'), colLoc = gl.getAttribLocation(prog, 'col');
  gl.enableVertexAttribArray(posLoc);
  gl.enableVertexAttribArray(colLoc);
  if (state.cloud) {
    gl.uniform1f(gl.getUniformLocation(prog, 'size'), Math.max(1.5, 2 * dpr));
    gl.bindBuffer(gl.ARRAY_BUFFER, cloudBuf);
    gl.vertexAttribPointer(posLoc, 3, gl.FLOAT, false, 0, 0);
    gl.bindBuffer(gl.ARRAY_BUFFER, colourBuf);
    gl.vertexAttribPointer(colLoc, 3, gl.UNSIGNED_BYTE, true, 0, 0);
    gl.drawArrays(gl.POINTS, 0, state.cloud.count);
  }
  const l = lines();
  gl.disable(gl.DEPTH_TEST);
  gl.bindBuffer(gl.ARRAY_BUFFER, lineBuf);
  gl.bufferData(gl.ARRAY_BUFFER, l.pos.byteLength + l.cols.byteLength, gl.DYNAMIC_DRAW);
  gl.bufferSubData(gl.ARRAY_BUFFER, 0, l.pos);
  gl.bufferSubData(gl.ARRAY_BUFFER, l.pos.byteLength, l.cols);
  gl.vertexAttribPointer(posLoc, 3, gl.FLOAT, false, 0, 0);
  gl.vertexAttribPointer(colLoc, 3, gl.FLOAT, false, 0, l.pos.byteLength);
  gl.drawArrays(gl.LINES, 0, l.pos.length / 3);
}

// ---------- orthographic views of the selected box ----------
const ORTHO = [['ortho-top', 0, 1], ['ortho-side', 0, 2], ['ortho-front', 1, 2]];
function orthoScale(b, a, c, cv) {
  const ext = Math.max(b.size[a], b.size[c]) * 1.6 || 0.1;
  return cv.width / ext;
}
function drawOrthos() {
  if (state.selected < 0 || !state.cloud) return;
  const b = state.boxes[state.selected];
  const pos = state.cloud.positions, rgb = state.cloud.colours;
  const reach = b.size.map((s) => s * 0.8);
  const r2 = v3.dot(reach, reach);
  for (const [id, a, c] of ORTHO) {
    const cv = $(id), ctx = cv.getContext('2d');
    const s = orthoScale(b, a, c, cv), cx = cv.width / 2, cy = cv.height / 2;
    ctx.fillStyle = '#111';
    ctx.fillRect(0, 0, cv.width, cv.height);
    for (let i = 0; i < state.cloud.count; i++) {
      const dx = pos[3 * i] - b.center[0], dy = pos[3 * i + 1] - b.center[1], dz = pos[3 * i + 2] - b.center[2];
      if (dx * dx + dy * dy + dz * dz > r2) continue;
      const l = toLocal(b, [pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]]);
      if (Math.abs(l[0]) > reach[0] || Math.abs(l[1]) > reach[1] || Math.abs(l[2]) > reach[2]) continue;
      ctx.fillStyle = `rgb(${rgb[3 * i]},${rgb[3 * i + 1]},${rgb[3 * i + 2]})`;
      ctx.fillRect(cx + l[a] * s - 1, cy - l[c] * s - 1, 2, 2);
    }
    ctx.strokeStyle = css(colour(state.selected + 1));
    ctx.lineWidth = 2;
    ctx.strokeRect(cx - b.size[a] / 2 * s, cy - b.size[c] / 2 * s, b.size[a] * s, b.size[c] * s);
    if (a === 0) { // heading tick and the yaw handle
      ctx.beginPath(); ctx.moveTo(cx, cy); ctx.lineTo(cx + b.size[0] / 2 * s, cy); ctx.stroke();
    }
    if (id === 'ortho-top') {
      ctx.beginPath(); ctx.arc(cx + b.size[0] / 2 * s + 10, cy, 5, 0, 2 * Math.PI); ctx.stroke();
    }
  }
}
// Dragging in an ortho view: an edge resizes that face, the circle rotates, inside moves.
function orthoDrag(id, a, c) {
  const cv = $(id);
  let drag = null;
  const at = (e) => { const r = cv.getBoundingClientRect(); return [(e.clientX - r.left) * cv.width / r.width, (e.clientY - r.top) * cv.height / r.height]; };
  cv.addEventListener('mousedown', (e) => {
    if (state.selected < 0) return;
    const b = state.boxes[state.selected];
    const s = orthoScale(b, a, c, cv), [px, py] = at(e), cx = cv.width / 2, cy = cv.height / 2;
    const u = (px - cx) / s, v = (cy - py) / s, tol = 6 / s;
    let mode = 'move';
    if (id === 'ortho-top' && Math.hypot(px - (cx + b.size[0] / 2 * s + 10), py - cy) < 8) mode = 'rotate';
    else if (Math.abs(Math.abs(u) - b.size[a] / 2) < tol) mode = ['face', a, Math.sign(u)];
    else if (Math.abs(Math.abs(v) - b.size[c] / 2) < tol) mode = ['face', c, Math.sign(v)];
    drag = { mode, start: [u, v], before: copyBoxes(), box: JSON.parse(JSON.stringify(b)), s };
    e.preventDefault();
  });
  window.addEventListener('mousemove', (e) => {
    if (!drag) return;
    const [px, py] = at(e), cx = cv.width / 2, cy = cv.height / 2;
    const u = (px - cx) / drag.s, v = (cy - py) / drag.s;
    const b = state.boxes[state.selected], o = drag.box;
    b.center = o.center.slice(); b.size = o.size.slice(); b.rotation = o.rotation.map((r) => r.slice());
    const du = u - drag.start[0], dv = v - drag.start[1];
    if (drag.mode === 'move') {
      b.center = v3.add(b.center, v3.add(v3.mul(col(b.rotation, a), du), v3.mul(col(b.rotation, c), dv)));
    } else if (drag.mode === 'rotate') {
      rotateYaw(b, Math.atan2(v, u));
    } else {
      const [, axis, sign] = drag.mode;
      const d = axis === a ? du : dv;
      const grow = Math.max(0.005 - o.size[axis], sign * d);
      b.size[axis] = o.size[axis] + grow;
      b.center = v3.add(b.center, v3.mul(col(b.rotation, axis), sign * grow / 2));
    }
    refreshFields();
    draw();
    drawOrthos();
  });
  window.addEventListener('mouseup', () => {
    if (!drag) return;
    const before = drag.before;
    drag = null;
    commit(before);
  });
}
ORTHO.forEach(([id, a, c]) => orthoDrag(id, a, c));

// ---------- side panel ----------
function refreshFields() {
  const b = state.boxes[state.selected];
  if (!b) return;
  const set = (id, v) => { if (document.activeElement !== $(id)) $(id).value = v; };
  ['cx', 'cy', 'cz'].forEach((id, k) => set(id, b.center[k].toFixed(3)));
  ['sx', 'sy', 'sz'].forEach((id, k) => set(id, b.size[k].toFixed(3)));
  set('yaw', (yawOf(b) * 180 / Math.PI).toFixed(1));
  set('box-label', b.label);
}
function refreshPanel() {
  const list = $('box-list');
  list.innerHTML = '';
  state.boxes.forEach((b, i) => {
    const li = document.createElement('li');
    li.innerHTML = `<span class="swatch" style="background:${css(colour(i + 1))}"></span>`;
    li.append(`${b.label} (${b.size.map((s) => s.toFixed(2)).join(' x ')})`);
    if (i === state.selected) li.className = 'selected';
    li.onclick = () => select(i);
    list.append(li);
  });
  const labels = [...new Set(state.boxes.map((b) => b.label).filter(Boolean))].sort();
  $('labels').innerHTML = '';
  for (const l of labels) { const o = document.createElement('option'); o.value = l; $('labels').append(o); }
  $('editor').hidden = state.selected < 0;
  refreshFields();
}
function select(i) {
  state.selected = i;
  refreshPanel();
  draw();
  drawOrthos();
}
function fieldEdit(id, apply) {
  $(id).addEventListener('change', () => {
    const v = parseFloat($(id).value);
    if (!Number.isFinite(v)) { refreshFields(); return; }
    edit((b) => apply(b, v));
  });
}
['cx', 'cy', 'cz'].forEach((id, k) => fieldEdit(id, (b, v) => { b.center[k] = v; }));
['sx', 'sy', 'sz'].forEach((id, k) => fieldEdit(id, (b, v) => { b.size[k] = Math.max(0.001, v); }));
fieldEdit('yaw', (b, v) => rotateYaw(b, v * Math.PI / 180 - yawOf(b)));
$('box-label').addEventListener('change', () => {
  const v = $('box-label').value.trim();
  if (v) edit((b) => { b.label = v; });
});

// ---------- live check ----------
let previewTimer = null, previewSeq = 0;
function schedulePreview() {
  if (!$('live').checked) return;
  clearTimeout(previewTimer);
  previewTimer = setTimeout(preview, 350);
}
async function preview() {
  const stem = $('frame').value;
  if (!stem) return;
  const seq = ++previewSeq;
  try {
    const blob = await api('POST', `/api/frames/${stem}/preview.png`, boxesDocument());
    if (seq !== previewSeq) return;
    const old = $('preview').src;
    $('preview').src = URL.createObjectURL(blob);
    if (old.startsWith('blob:')) URL.revokeObjectURL(old);
  } catch (e) {
    status(`preview: ${e.message}`, 'error');
  }
}
$('frame').addEventListener('change', preview);
$('live').addEventListener('change', schedulePreview);

// ---------- mouse and keys on the 3D view ----------
function setView(v) {
  state.view = v;
  $('view-3d').classList.toggle('active', v === 'orbit');
  $('view-top').classList.toggle('active', v === 'top');
  draw();
}
function setDrawing(on) {
  state.drawing = on;
  if (on) setView('top');
  $('tool-box').classList.toggle('active', on);
  canvas.classList.toggle('drawing', on);
}
canvas.addEventListener('contextmenu', (e) => e.preventDefault());
canvas.addEventListener('mousedown', (e) => {
  const r = canvas.getBoundingClientRect();
  const px = e.clientX - r.left, py = e.clientY - r.top;
  if (state.drawing && e.button === 0 && state.view === 'top') {
    const g = topGround(px, py);
    state.rect = [g, g];
    state.drag = { kind: 'rect' };
  } else {
    const pan = e.button === 2 || e.shiftKey || state.view === 'top';
    state.drag = { kind: pan ? 'pan' : 'orbit', x: e.clientX, y: e.clientY, moved: 0, px, py };
  }
  e.preventDefault();
});
window.addEventListener('mousemove', (e) => {
  const d = state.drag;
  if (!d) return;
  const r = canvas.getBoundingClientRect();
  if (d.kind === 'rect') {
    state.rect[1] = topGround(e.clientX - r.left, e.clientY - r.top);
    draw();
    return;
  }
  const dx = e.clientX - d.x, dy = e.clientY - d.y;
  d.x = e.clientX; d.y = e.clientY; d.moved += Math.abs(dx) + Math.abs(dy);
  if (d.kind === 'orbit') {
    state.azimuth -= dx * 0.008;
    state.elevation = Math.max(-1.5, Math.min(1.5, state.elevation + dy * 0.008));
  } else {
    const k = state.dist / canvas.clientHeight * (state.view === 'top' ? 1 : 0.8);
    let right, upv;
    if (state.view === 'top') { right = state.gx; upv = state.gy; } else {
      const a = state.azimuth;
      right = v3.add(v3.mul(state.gx, -Math.sin(a)), v3.mul(state.gy, Math.cos(a)));
      upv = state.up;
    }
    state.target = v3.add(state.target, v3.add(v3.mul(right, -dx * k), v3.mul(upv, dy * k)));
  }
  draw();
});
window.addEventListener('mouseup', (e) => {
  const d = state.drag;
  state.drag = null;
  if (!d) return;
  if (d.kind === 'rect') {
    const [a, b] = state.rect;
    state.rect = null;
    setDrawing(false);
    createFromRect(a, b);
    draw();
  } else if (d.moved < 4) {
    pick(d.px, d.py);
  }
});
canvas.addEventListener('wheel', (e) => {
  state.dist *= Math.exp(e.deltaY * 0.001);
  state.dist = Math.max(0.05, Math.min(500, state.dist));
  e.preventDefault();
  draw();
}, { passive: false });
function pick(px, py) {
  const m = matrices();
  let best = -1, bestD = 40;
  state.boxes.forEach((b, i) => {
    for (const p of [b.center, ...corners(b)]) {
      const s = project(p, m);
      if (!s) continue;
      const dd = Math.hypot(s[0] - px, s[1] - py);
      if (dd < bestD) { bestD = dd; best = i; }
    }
  });
  select(best);
}
window.addEventListener('keydown', (e) => {
  if (e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement) return;
  const ctrl = e.ctrlKey || e.metaKey;
  if (ctrl && e.key.toLowerCase() === 'z') { e.shiftKey ? redo() : undo(); e.preventDefault(); return; }
  if (ctrl && e.key.toLowerCase() === 'y') { redo(); e.preventDefault(); return; }
  if (ctrl && e.key.toLowerCase() === 's') { save(); e.preventDefault(); return; }
  if (ctrl) return;
  const k = e.key;
  if (k === 'b' || k === 'B') { setDrawing(!state.drawing); return; }
  if (k === 't' || k === 'T') { setView(state.view === 'top' ? 'orbit' : 'top'); return; }
  if (k === 'Escape') { setDrawing(false); select(-1); return; }
  if (state.selected < 0) return;
  const step = e.shiftKey ? 5 * STEP : STEP;
  const nudges = {
    ArrowLeft: [0, -1], ArrowRight: [0, 1], ArrowDown: [1, -1], ArrowUp: [1, 1], PageDown: [2, -1], PageUp: [2, 1],
  };
  if (k in nudges) {
    const [axis, sign] = nudges[k];
    if (e.altKey) edit((b) => resize(b, axis, sign * step));
    else edit((b) => moveGround(b, axis === 0 ? sign * step : 0, axis === 1 ? sign * step : 0, axis === 2 ? sign * step : 0));
  } else if (k === 'q' || k === 'Q') edit((b) => rotateYaw(b, (e.shiftKey ? 5 : 1) * YAW_STEP));
  else if (k === 'e' || k === 'E') edit((b) => rotateYaw(b, -(e.shiftKey ? 5 : 1) * YAW_STEP));
  else if (k === 'f' || k === 'F') edit((b) => rotateYaw(b, Math.PI));
  else if (k === 's' || k === 'S') shrinkSelected();
  else if (k === 'Delete' || k === 'Backspace') deleteSelected();
  else return;
  e.preventDefault();
});
function deleteSelected() {
  if (state.selected < 0) return;
  const before = copyBoxes();
  state.boxes.splice(state.selected, 1);
  state.selected = -1;
  commit(before);
}
$('view-3d').onclick = () => setView('orbit');
$('view-top').onclick = () => setView('top');
$('tool-box').onclick = () => setDrawing(!state.drawing);
$('undo').onclick = undo;
$('redo').onclick = redo;
$('save').onclick = save;
$('shrink').onclick = shrinkSelected;
$('flip').onclick = () => edit((b) => rotateYaw(b, Math.PI));
$('delete').onclick = deleteSelected;
window.addEventListener('resize', draw);
window.addEventListener('beforeunload', (e) => { if (state.dirty) e.preventDefault(); });

// ---------- start ----------
async function load() {
  status('loading...');
  const [info, doc, frames, cloud] = await Promise.all([
    api('GET', '/api/info'), api('GET', '/api/boxes'), api('GET', '/api/frames'),
    fetch('/api/cloud.bin').then((r) => r.arrayBuffer()),
  ]);
  state.info = info;
  Object.assign(state, groundFrame(info.up));
  state.boxes = doc.boxes;
  state.frames = frames.frames;
  $('source').textContent = `(${info.source} depth)`;
  const magic = new TextDecoder().decode(new Uint8Array(cloud, 0, 8));
  if (magic !== 'NLCLOUD1') throw new Error('the point cloud has an unknown format');
  const count = new DataView(cloud).getUint32(8, true);
  state.cloud = { count, positions: new Float32Array(cloud, 32, 3 * count), colours: new Uint8Array(cloud, 32 + 12 * count, 3 * count) };
  if (gl) {
    gl.bindBuffer(gl.ARRAY_BUFFER, cloudBuf);
    gl.bufferData(gl.ARRAY_BUFFER, state.cloud.positions, gl.STATIC_DRAW);
    gl.bindBuffer(gl.ARRAY_BUFFER, colourBuf);
    gl.bufferData(gl.ARRAY_BUFFER, state.cloud.colours, gl.STATIC_DRAW);
  }
  // Frame the robust middle of the cloud.
  const p = state.cloud.positions, n = count, lo = [1e9, 1e9, 1e9], hi = [-1e9, -1e9, -1e9];
  const stride = Math.max(1, Math.floor(n / 20000));
  const xs = [[], [], []];
  for (let i = 0; i < n; i += stride) for (let k = 0; k < 3; k++) xs[k].push(p[3 * i + k]);
  xs.forEach((a, k) => { a.sort((x, y) => x - y); lo[k] = a[Math.floor(a.length * 0.02)] || 0; hi[k] = a[Math.floor(a.length * 0.98)] || 0; });
  state.target = v3.mul(v3.add(lo, hi), 0.5);
  state.dist = Math.max(0.3, Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) * 0.6);
  for (const f of frames.frames) {
    const o = document.createElement('option');
    o.value = f.stem; o.textContent = `${f.stem} (${f.width}x${f.height})`;
    $('frame').append(o);
  }
  $('frame').selectedIndex = Math.floor(frames.frames.length / 2);
  setView('orbit');
  refreshPanel();
  draw();
  preview();
  status(gl ? `${count} points, ${frames.frames.length} frames, ${state.boxes.length} boxes` : 'WebGL is unavailable in this browser', gl ? '' : 'error');
  document.body.dataset.ready = '1';
}

// Hooks for scripts and tests.
window.annotate = {
  state,
  boxes: () => state.boxes,
  worldToScreen: (p) => { const s = project(p); const r = canvas.getBoundingClientRect(); return s && [s[0] + r.left, s[1] + r.top]; },
  setView, select, save,
};
load().catch((e) => { status(`cannot load: ${e.message}`, 'error'); document.body.dataset.ready = 'error'; });

// livebridge render client: a small WebGL2 renderer for the live face.
// The mesh, its normals and the basis elements arrive once as float textures;
// each frame brings only the contractions, and the vertex shader computes
// E = E0 + sum_i x_i e_i (and the matching normal) on the GPU.
// Wire format: see livebridge/output/render_server.py.
"use strict";

const MAX_MUSCLES = 64;
const HISTORY = 180;

const lb = {              // state, also read by the browser test
  connected: false, ready: false, framesReceived: 0, seq: -1, drawnSeq: -1,
  init: null, contractions: null, markers: null, errors: [NaN, NaN], servos: null, head: null,
  latencyMs: NaN, status: null, error: null,
};
window.livebridge = lb;

const history = { x: [], errors: [] };

// ------------------------------------------------------------------ small matrix helpers (column-major)
const mat4 = {
  perspective(fovy, aspect, near, far) {
    const f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
    return new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1, 0, 0, 2 * far * near * nf, 0]);
  },
  lookAt(eye, target, up) {
    let zx = eye[0] - target[0], zy = eye[1] - target[1], zz = eye[2] - target[2];
    let l = Math.hypot(zx, zy, zz); zx /= l; zy /= l; zz /= l;
    let xx = up[1] * zz - up[2] * zy, xy = up[2] * zx - up[0] * zz, xz = up[0] * zy - up[1] * zx;
    l = Math.hypot(xx, xy, xz); xx /= l; xy /= l; xz /= l;
    const yx = zy * xz - zz * xy, yy = zz * xx - zx * xz, yz = zx * xy - zy * xx;
    return new Float32Array([xx, yx, zx, 0, xy, yy, zy, 0, xz, yz, zz, 0,
      -(xx * eye[0] + xy * eye[1] + xz * eye[2]), -(yx * eye[0] + yy * eye[1] + yz * eye[2]),
      -(zx * eye[0] + zy * eye[1] + zz * eye[2]), 1]);
  },
  multiply(a, b) {
    const out = new Float32Array(16);
    for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
      let s = 0; for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k]; out[c * 4 + r] = s;
    }
    return out;
  },
};

// ------------------------------------------------------------------ WebGL
const canvas = document.getElementById("face");
const gl = canvas.getContext("webgl2", { preserveDrawingBuffer: true, antialias: true });

const FACE_VS = `#version 300 es
precision highp float; precision highp int; precision highp sampler2D;
in vec3 aPosition; in vec3 aNormal;
uniform sampler2D uElements; uniform sampler2D uNormalElements;
uniform float uX[${MAX_MUSCLES}]; uniform int uMuscles; uniform int uWidth; uniform int uRows;
uniform mat4 uView; uniform mat4 uProjection;
out vec3 vNormal; out vec3 vEye;
void main() {
  vec3 p = aPosition, n = aNormal;
  int col = gl_VertexID % uWidth, row = gl_VertexID / uWidth;
  for (int m = 0; m < ${MAX_MUSCLES}; m++) {
    if (m >= uMuscles) break;
    float x = uX[m];
    if (x != 0.0) {
      ivec2 texel = ivec2(col, m * uRows + row);
      p += x * texelFetch(uElements, texel, 0).xyz;
      n += x * texelFetch(uNormalElements, texel, 0).xyz;
    }
  }
  vec4 eye = uView * vec4(p, 1.0);
  vEye = eye.xyz; vNormal = mat3(uView) * n;
  gl_Position = uProjection * eye;
}`;
const FACE_FS = `#version 300 es
precision highp float;
in vec3 vNormal; in vec3 vEye; out vec4 color;
void main() {
  vec3 n = normalize(vNormal);
  if (!gl_FrontFacing) n = -n;
  vec3 v = normalize(-vEye);
  vec3 key = normalize(vec3(0.4, 0.5, 1.0)), fill = normalize(vec3(-0.7, -0.1, 0.6));
  vec3 skin = vec3(0.86, 0.68, 0.58);
  float d = max(dot(n, key), 0.0) * 0.75 + max(dot(n, fill), 0.0) * 0.25;
  float s = pow(max(dot(n, normalize(key + v)), 0.0), 40.0) * 0.18;
  float rim = pow(1.0 - max(dot(n, v), 0.0), 3.0) * 0.15;
  color = vec4(skin * (0.18 + d) + vec3(s + rim), 1.0);
}`;
const MARKER_VS = `#version 300 es
precision highp float;
in vec4 aMarker; in vec3 aColor;
uniform mat4 uView; uniform mat4 uProjection; uniform float uSize;
out vec3 vColor;
void main() {
  vColor = aColor;
  gl_Position = uProjection * uView * vec4(aMarker.xyz, 1.0);
  gl_Position.z -= 0.003 * gl_Position.w;
  gl_PointSize = aMarker.w > 0.5 ? uSize : 0.0;
}`;
const MARKER_FS = `#version 300 es
precision highp float;
in vec3 vColor; out vec4 color;
void main() {
  vec2 c = gl_PointCoord * 2.0 - 1.0;
  float r = dot(c, c);
  if (r > 1.0) discard;
  color = vec4(mix(vColor, vec3(1.0), 0.35 * (1.0 - r)), 1.0);
}`;

function compile(vs, fs) {
  const program = gl.createProgram();
  for (const [type, source] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const shader = gl.createShader(type);
    gl.shaderSource(shader, source); gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(shader));
    gl.attachShader(program, shader);
  }
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
  const u = {}, n = gl.getProgramParameter(program, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < n; i++) {
    const name = gl.getActiveUniform(program, i).name.replace(/\[0\]$/, "");
    u[name] = gl.getUniformLocation(program, name);
  }
  return { program, u };
}

let faceProgram = null, markerProgram = null, mesh = null, markerBuffer = null, markerColors = null;
const camera = { yaw: 0, pitch: 0, distance: 1, center: [0, 0, 0], radius: 100 };

function floatTexture(data, width, height) {
  const texture = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, texture);
  gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB32F, width, height, 0, gl.RGB, gl.FLOAT, data);
  for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  return texture;
}

function loadMesh(buffer) {
  const [kind, V, T, M] = new Uint32Array(buffer, 0, 4);
  if (kind !== 1) throw new Error("expected the mesh message");
  if (M > MAX_MUSCLES) throw new Error(`${M} muscles; this page draws at most ${MAX_MUSCLES}`);
  let offset = 16;
  const take = (Type, count) => { const a = new Type(buffer, offset, count); offset += 4 * count; return a; };
  const neutral = take(Float32Array, V * 3), normals = take(Float32Array, V * 3);
  const triangles = take(Uint32Array, T * 3);
  const elements = take(Float32Array, M * V * 3), normalElements = take(Float32Array, M * V * 3);

  // Element e_m of vertex v sits at texel (v % width, m * rows + v / width).
  const width = Math.min(V, 2048), rows = Math.ceil(V / width);
  const pack = (source) => {
    const packed = new Float32Array(width * rows * M * 3);
    for (let m = 0; m < M; m++) packed.set(source.subarray(m * V * 3, (m + 1) * V * 3), m * width * rows * 3);
    return packed;
  };
  const vao = gl.createVertexArray();
  gl.bindVertexArray(vao);
  for (const [name, data] of [["aPosition", neutral], ["aNormal", normals]]) {
    const location = gl.getAttribLocation(faceProgram.program, name);
    gl.bindBuffer(gl.ARRAY_BUFFER, gl.createBuffer());
    gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(location);
    gl.vertexAttribPointer(location, 3, gl.FLOAT, false, 0, 0);
  }
  gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, gl.createBuffer());
  gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, triangles, gl.STATIC_DRAW);
  gl.bindVertexArray(null);

  let lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < V; i++) for (let d = 0; d < 3; d++) {
    const v = neutral[3 * i + d]; if (v < lo[d]) lo[d] = v; if (v > hi[d]) hi[d] = v;
  }
  camera.center = [0, 1, 2].map((d) => (lo[d] + hi[d]) / 2);
  camera.radius = 0.5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
  resetCamera();
  mesh = {
    vao, V, T, M, width, rows,
    elements: floatTexture(pack(elements), width, rows * M),
    normalElements: floatTexture(pack(normalElements), width, rows * M),
  };
  lb.contractions = new Float32Array(M);
}

function resetCamera() { camera.yaw = 0; camera.pitch = 0.08; camera.distance = 2.6 * camera.radius; }

function setupMarkers(init) {
  const n = init.markers.length;
  markerBuffer = gl.createBuffer();
  gl.bindBuffer(gl.ARRAY_BUFFER, markerBuffer);
  gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(Math.max(n, 1) * 4), gl.DYNAMIC_DRAW);
  const colors = new Float32Array(Math.max(n, 1) * 3);
  for (let i = 0; i < n; i++) {
    const c = init.marker_roles[i] === "head" ? [0.95, 0.85, 0.2]
      : init.marker_regions[i] === "upper" ? [0.25, 0.75, 1.0] : [0.35, 1.0, 0.45];
    colors.set(c, 3 * i);
  }
  markerColors = gl.createBuffer();
  gl.bindBuffer(gl.ARRAY_BUFFER, markerColors);
  gl.bufferData(gl.ARRAY_BUFFER, colors, gl.STATIC_DRAW);
}

function draw() {
  const w = canvas.width, h = canvas.height;
  gl.viewport(0, 0, w, h);
  gl.clearColor(0.114, 0.129, 0.153, 1);
  gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  if (!mesh) return;
  const c = camera, cp = Math.cos(c.pitch);
  const eye = [c.center[0] + c.distance * cp * Math.sin(c.yaw), c.center[1] + c.distance * Math.sin(c.pitch),
    c.center[2] + c.distance * cp * Math.cos(c.yaw)];
  const view = mat4.multiply(mat4.lookAt(eye, c.center, [0, 1, 0]), headRotation());
  const projection = mat4.perspective(0.6, w / h, c.distance * 0.05, c.distance * 4);

  gl.enable(gl.DEPTH_TEST);
  gl.useProgram(faceProgram.program);
  const u = faceProgram.u;
  gl.uniformMatrix4fv(u.uView, false, view);
  gl.uniformMatrix4fv(u.uProjection, false, projection);
  const x = new Float32Array(MAX_MUSCLES);
  x.set(lb.contractions.subarray(0, mesh.M).map((v) => (Number.isFinite(v) ? v : 0)));
  gl.uniform1fv(u.uX, x);
  gl.uniform1i(u.uMuscles, mesh.M); gl.uniform1i(u.uWidth, mesh.width); gl.uniform1i(u.uRows, mesh.rows);
  gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D, mesh.elements); gl.uniform1i(u.uElements, 0);
  gl.activeTexture(gl.TEXTURE1); gl.bindTexture(gl.TEXTURE_2D, mesh.normalElements);
  gl.uniform1i(u.uNormalElements, 1);
  gl.bindVertexArray(mesh.vao);
  gl.drawElements(gl.TRIANGLES, mesh.T * 3, gl.UNSIGNED_INT, 0);
  gl.bindVertexArray(null);

  const n = lb.init ? lb.init.markers.length : 0;
  if (n && lb.markers) {
    const data = new Float32Array(n * 4);
    for (let i = 0; i < n; i++) {
      const p = lb.markers.subarray(3 * i, 3 * i + 3);
      const seen = Number.isFinite(p[0]) && Number.isFinite(p[1]) && Number.isFinite(p[2]);
      data.set(seen ? [p[0], p[1], p[2], 1] : [0, 0, 0, 0], 4 * i);
    }
    gl.useProgram(markerProgram.program);
    gl.uniformMatrix4fv(markerProgram.u.uView, false, view);
    gl.uniformMatrix4fv(markerProgram.u.uProjection, false, projection);
    gl.uniform1f(markerProgram.u.uSize, Math.max(3, 0.012 * h * (2.6 * c.radius / c.distance)));
    gl.bindBuffer(gl.ARRAY_BUFFER, markerBuffer);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, data);
    const loc = gl.getAttribLocation(markerProgram.program, "aMarker");
    gl.enableVertexAttribArray(loc); gl.vertexAttribPointer(loc, 4, gl.FLOAT, false, 0, 0);
    gl.bindBuffer(gl.ARRAY_BUFFER, markerColors);
    const cl = gl.getAttribLocation(markerProgram.program, "aColor");
    gl.enableVertexAttribArray(cl); gl.vertexAttribPointer(cl, 3, gl.FLOAT, false, 0, 0);
    gl.drawArrays(gl.POINTS, 0, n);
    gl.disableVertexAttribArray(loc); gl.disableVertexAttribArray(cl);
  }
}

// The head pose's rotation (row-major 4x4 on the wire) as a column-major model matrix; its translation is left
// out so the face stays where the camera looks. Identity while the pose is unknown (NaN).
function headRotation() {
  const h = lb.head, m = new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);
  if (!h || h.length < 16 || !h.every(Number.isFinite)) return m;
  for (let r = 0; r < 3; r++) for (let c = 0; c < 3; c++) m[c * 4 + r] = h[r * 4 + c];
  return m;
}

// ------------------------------------------------------------------ 2D panels
function drawBars() {
  const bars = document.getElementById("bars"), g = bars.getContext("2d");
  const init = lb.init; if (!init) return;
  const names = init.muscles, M = names.length, rowH = Math.max(14, Math.floor(bars.height / Math.max(M, 1)));
  if (bars.height !== rowH * M) bars.height = rowH * M;
  g.clearRect(0, 0, bars.width, bars.height);
  g.font = "11px system-ui, sans-serif"; g.textBaseline = "middle";
  const labelW = 130, barW = 90, curveX = labelW + barW + 10, curveW = bars.width - curveX - 4;
  for (let m = 0; m < M; m++) {
    const y = m * rowH, v = lb.contractions ? lb.contractions[m] : 0;
    const color = init.regions[m] === "upper" ? "#4fb6ff" : "#5fe07a";
    g.fillStyle = "#aab3bd"; g.fillText(names[m], 4, y + rowH / 2);
    g.fillStyle = "#2a3038"; g.fillRect(labelW, y + 3, barW, rowH - 6);
    g.fillStyle = color; g.fillRect(labelW, y + 3, barW * Math.max(0, Math.min(1, v || 0)), rowH - 6);
    g.strokeStyle = color; g.lineWidth = 1; g.beginPath();
    const hx = history.x, k0 = Math.max(0, hx.length - HISTORY);
    for (let k = k0; k < hx.length; k++) {
      const px = curveX + ((k - k0) / (HISTORY - 1)) * curveW;
      const py = y + rowH - 2 - Math.max(0, Math.min(1, hx[k][m] || 0)) * (rowH - 4);
      if (k === k0) g.moveTo(px, py); else g.lineTo(px, py);
    }
    g.stroke();
  }
}

function drawErrors() {
  const canvasE = document.getElementById("errors"), g = canvasE.getContext("2d");
  g.clearRect(0, 0, canvasE.width, canvasE.height);
  const he = history.errors; if (!he.length) return;
  let top = 0.5; for (const e of he) for (const v of e) if (Number.isFinite(v)) top = Math.max(top, v);
  const colors = ["#4fb6ff", "#5fe07a"], labels = ["upper", "lower"];
  g.font = "11px system-ui, sans-serif";
  for (let r = 0; r < 2; r++) {
    g.strokeStyle = colors[r]; g.beginPath();
    for (let k = 0; k < he.length; k++) {
      const px = 4 + (k / (HISTORY - 1)) * (canvasE.width - 120);
      const py = canvasE.height - 4 - ((he[k][r] || 0) / top) * (canvasE.height - 8);
      if (k === 0) g.moveTo(px, py); else g.lineTo(px, py);
    }
    g.stroke();
    g.fillStyle = colors[r];
    const last = he[he.length - 1][r];
    g.fillText(`${labels[r]} ${Number.isFinite(last) ? last.toFixed(3) : "—"} mm`, canvasE.width - 110, 16 + 20 * r);
  }
}

function drawServos() {
  const canvasS = document.getElementById("servos"), g = canvasS.getContext("2d");
  const names = lb.init ? lb.init.servos : [];
  const rowH = 14; if (canvasS.height !== Math.max(1, names.length) * rowH) canvasS.height = Math.max(1, names.length) * rowH;
  g.clearRect(0, 0, canvasS.width, canvasS.height);
  g.font = "11px system-ui, sans-serif"; g.textBaseline = "middle";
  if (!names.length) { g.fillStyle = "#777"; g.fillText("no servo rig", 4, 7); return; }
  for (let i = 0; i < names.length; i++) {
    const v = lb.servos ? lb.servos[i] : NaN, y = i * rowH;
    g.fillStyle = "#aab3bd"; g.fillText(names[i], 4, y + rowH / 2);
    g.fillStyle = "#2a3038"; g.fillRect(130, y + 3, 240, rowH - 6);
    if (Number.isFinite(v)) { g.fillStyle = "#ffb347"; g.fillRect(130 + 240 * Math.max(0, Math.min(1, v)) - 2, y + 2, 4, rowH - 4); }
  }
}

function showStatus() {
  const el = document.getElementById("status"), s = lb.status;
  const latency = Number.isFinite(lb.latencyMs) ? `${lb.latencyMs.toFixed(2)} ms` : "—";
  el.textContent = (s && s.line ? s.line + "\n" : "") + `frame ${lb.seq} · received ${lb.framesReceived} · pipeline→page ${latency}`;
}

// ------------------------------------------------------------------ network
function onFrame(buffer) {
  const [kind, seq, M, n, S] = new Uint32Array(buffer, 0, 5);
  if (kind !== 2) return;
  const f = new Float32Array(buffer, 20);
  lb.errors = [f[0], f[1]]; lb.latencyMs = f[2];
  lb.contractions = f.slice(3, 3 + M);
  lb.markers = f.slice(3 + M, 3 + M + 3 * n);
  lb.servos = f.slice(3 + M + 3 * n, 3 + M + 3 * n + S);
  lb.head = f.slice(3 + M + 3 * n + S, 3 + M + 3 * n + S + 16);
  lb.seq = seq; lb.framesReceived++;
  history.x.push(lb.contractions); if (history.x.length > HISTORY) history.x.shift();
  history.errors.push(lb.errors); if (history.errors.length > HISTORY) history.errors.shift();
  requestDraw();
}

function connect() {
  const socket = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  socket.binaryType = "arraybuffer";
  const badge = document.getElementById("connection");
  socket.onopen = () => { lb.connected = true; badge.textContent = "live"; badge.className = "badge live"; };
  socket.onclose = () => {
    lb.connected = false; badge.textContent = "disconnected — retrying"; badge.className = "badge down";
    setTimeout(connect, 1000);
  };
  socket.onmessage = (event) => {
    try {
      if (typeof event.data === "string") {
        const message = JSON.parse(event.data);
        if (message.type === "init") { lb.init = message; setupMarkers(message); }
        else if (message.type === "status") { lb.status = message; showStatus(); }
        else if (message.type === "character" && window.livebridgeCharacter) window.livebridgeCharacter.onInit(message);
        return;
      }
      const kind = new Uint32Array(event.data, 0, 1)[0];
      if (kind === 1) { loadMesh(event.data); lb.ready = true; requestDraw(); }
      else if (kind === 2 && mesh) onFrame(event.data);
      else if (kind >= 3 && window.livebridgeCharacter) window.livebridgeCharacter.onBinary(kind, event.data);
    } catch (error) { lb.error = String(error); console.error(error); }
  };
}

let drawRequested = false;
function requestDraw() {
  if (drawRequested) return;
  drawRequested = true;
  requestAnimationFrame(() => {
    drawRequested = false;
    draw(); drawBars(); drawErrors(); drawServos(); showStatus();
    lb.drawnSeq = lb.seq;
  });
}

// ------------------------------------------------------------------ orbit controls
let drag = null;
canvas.addEventListener("mousedown", (e) => { drag = [e.clientX, e.clientY]; });
window.addEventListener("mouseup", () => { drag = null; });
window.addEventListener("mousemove", (e) => {
  if (!drag) return;
  camera.yaw -= (e.clientX - drag[0]) * 0.01;
  camera.pitch = Math.max(-1.4, Math.min(1.4, camera.pitch + (e.clientY - drag[1]) * 0.01));
  drag = [e.clientX, e.clientY]; requestDraw();
});
canvas.addEventListener("wheel", (e) => {
  e.preventDefault();
  camera.distance = Math.max(0.5 * camera.radius, Math.min(10 * camera.radius, camera.distance * Math.exp(e.deltaY * 0.001)));
  requestDraw();
}, { passive: false });
canvas.addEventListener("dblclick", () => { resetCamera(); requestDraw(); });

if (!gl) {
  lb.error = "WebGL2 is not available in this browser";
  document.getElementById("connection").textContent = lb.error;
} else {
  try {
    faceProgram = compile(FACE_VS, FACE_FS);
    markerProgram = compile(MARKER_VS, MARKER_FS);
    connect();
  } catch (error) { lb.error = String(error); console.error(error); }
}

// wiggly edit: the browser side. The server holds the scene (source of truth); this file
// draws it, turns user gestures into edits ({op: ...} JSON, see wiggly/editor/state.py),
// and plays the frames the server solves (float32 buffers, newest request wins).
import * as THREE from 'three';
import { OrbitControls } from './vendor/OrbitControls.js';
import { TransformControls } from './vendor/TransformControls.js';

const $ = (id) => document.getElementById(id);
const BASE = new THREE.Color(0.70, 0.74, 0.80);
const SELECTED = new THREE.Color(1.0, 0.86, 0.25);
const KEY_WINDOW = 0.25;       // s: a keyframed group is highlighted this close to its key time
const STAGE_RANK = { linear: 0, warped: 1 };
const VEL_SCALE = 0.25;        // s: the velocity arrow is v * VEL_SCALE long (metres)

// ------------------------------------------------------------------------------------------
// server access

async function request(method, path, body) {
  const init = { method, headers: {} };
  if (body !== undefined) {
    init.headers['Content-Type'] = 'application/json';
    init.body = JSON.stringify(body);
  }
  const res = await fetch(path, init);
  const text = await res.text();
  let data = {};
  try { data = text ? JSON.parse(text) : {}; } catch { data = { error: text }; }
  if (!res.ok) throw new Error(data.error || `${res.status} ${res.statusText}`);
  return data;
}
const api = {
  get: (p) => request('GET', p),
  post: (p, b = {}) => request('POST', p, b),
  async bin(p) {
    const res = await fetch(p);
    if (!res.ok) throw new Error(`${p}: ${res.status}`);
    return { buf: await res.arrayBuffer(), meta: res.headers.get('X-Wiggly-Frames') };
  },
};

// ------------------------------------------------------------------------------------------
// state kept in the browser (everything else is the server's)

const S = {
  desc: null,            // /api/state
  meshKey: null,
  rest: null,            // Float32Array n*3 (rest positions)
  faces: null,
  n: 0,
  frames: null,          // {meta, data: Float32Array}
  shown: { seq: -1, rank: -1, id: -1 },
  t: 0, playing: false, lastTick: 0,
  tool: 'orbit',
  selection: new Uint8Array(0),
  selectedGroup: null,
  selectedKey: null,     // keyframe id
  groupVerts: {},        // name -> Int32Array
  posing: null,          // {id, mode, center, group}
  dragging: false,
  previewInFlight: false, previewPending: null,
  release: null,         // {t, version}: latency measurement of a gizmo release
  velBase: new THREE.Vector3(),  // where the selected keyframe's velocity arrow starts
};
window.wiggly = {                 // test and benchmark hooks (read-only use)
  S, latencies: [], framesApplied: 0,
  gizmoHandle: (axis) => gizmoHandle(axis),
  projectGroup: (name) => projectGroup(name),
  screenBox: (indices) => screenBox(indices),
  rigidOfPose: () => poseTarget(),
  redraw: () => redraw(),
  ready: false,
  softwareGL: false,
};

// ------------------------------------------------------------------------------------------
// three.js scene

const canvas = $('canvas');
// Software GL (SwiftShader, llvmpipe: headless browsers, machines without a GPU) draws a frame
// in ~0.1 s at full quality; there, skip MSAA and draw at one pixel per CSS pixel.
const SOFTWARE_GL = (() => {
  try {
    const gl = document.createElement('canvas').getContext('webgl2');
    const info = gl && gl.getExtension('WEBGL_debug_renderer_info');
    const name = info ? gl.getParameter(info.UNMASKED_RENDERER_WEBGL) : '';
    gl && gl.getExtension('WEBGL_lose_context') && gl.getExtension('WEBGL_lose_context').loseContext();
    return /swiftshader|llvmpipe|software/i.test(name);
  } catch { return false; }
})();
const renderer = new THREE.WebGLRenderer({ canvas, antialias: !SOFTWARE_GL, preserveDrawingBuffer: true });
renderer.setPixelRatio(SOFTWARE_GL ? 1 : Math.min(window.devicePixelRatio, 2));
const scene3 = new THREE.Scene();
scene3.background = new THREE.Color(0x2a2f37);
const camera = new THREE.PerspectiveCamera(40, 1, 0.01, 100);
camera.position.set(1.6, 1.1, 2.2);
const controls = new OrbitControls(camera, canvas);
controls.enableDamping = false;
scene3.add(new THREE.HemisphereLight(0xdde6ff, 0x3a3530, 1.6));
const sun = new THREE.DirectionalLight(0xffffff, 1.8);
sun.position.set(2, 4, 3);
scene3.add(sun);
const fill = new THREE.DirectionalLight(0xaabbff, 0.5);
fill.position.set(-3, 1, -2);
scene3.add(fill);

const geometry = new THREE.BufferGeometry();
const material = new THREE.MeshStandardMaterial({ vertexColors: true, roughness: 0.65, metalness: 0.0,
                                                  side: THREE.DoubleSide });
const body = new THREE.Mesh(geometry, material);
body.frustumCulled = false;
scene3.add(body);
let ground = null;

const ghostGeom = new THREE.BufferGeometry();
const ghost = new THREE.Points(ghostGeom, new THREE.PointsMaterial({ size: 4, sizeAttenuation: false,
  color: 0xffffff, transparent: true, opacity: 0.85, depthTest: false }));
ghost.frustumCulled = false;
ghost.renderOrder = 2;
scene3.add(ghost);
const velArrow = new THREE.ArrowHelper(new THREE.Vector3(1, 0, 0), new THREE.Vector3(), 0.2, 0xffd24d);
velArrow.visible = false;
scene3.add(velArrow);

const pivot = new THREE.Object3D();
scene3.add(pivot);
const gizmo = new TransformControls(camera, canvas);
gizmo.setSize(0.9);
const gizmoHelper = gizmo.getHelper ? gizmo.getHelper() : gizmo;
scene3.add(gizmoHelper);
gizmo.addEventListener('dragging-changed', (e) => {
  controls.enabled = !e.value && S.tool === 'orbit';
  S.dragging = e.value;
  if (e.value) S.release = null;  // a new drag: stop measuring the previous release
  if (!e.value) commitPose();
});
gizmo.addEventListener('objectChange', () => { if (S.dragging) dragPose(); });

function resize() {
  const r = $('view').getBoundingClientRect();
  renderer.setSize(Math.max(1, r.width), Math.max(1, r.height), false);
  camera.aspect = r.width / Math.max(1, r.height);
  camera.updateProjectionMatrix();
  S.needsRender = true;
}
window.addEventListener('resize', () => { resize(); drawTimeline(); });

// ------------------------------------------------------------------------------------------
// loading the mesh, the state and frames

async function loadMesh() {
  const { buf } = await api.bin('/api/mesh');
  const head = new Uint32Array(buf, 0, 2);
  const n = head[0], m = head[1];
  S.n = n;
  S.rest = new Float32Array(buf, 8, n * 3).slice();
  S.faces = new Uint32Array(buf, 8 + n * 12, m * 3).slice();
  geometry.setIndex(new THREE.BufferAttribute(S.faces, 1));
  geometry.setAttribute('position', new THREE.BufferAttribute(S.rest.slice(), 3));
  geometry.setAttribute('color', new THREE.BufferAttribute(new Float32Array(n * 3), 3));
  geometry.computeVertexNormals();
  geometry.computeBoundingSphere();
  geometry.computeBoundingBox();
  S.selection = new Uint8Array(n);
  S.frames = null;
  S.shown = { seq: -1, rank: -1, id: -1 };
  frameCamera();
  makeGround();
}

function frameCamera() {
  const bb = geometry.boundingBox;
  const c = bb.getCenter(new THREE.Vector3());
  const size = bb.getSize(new THREE.Vector3()).length();
  controls.target.copy(c);
  camera.position.copy(c).add(new THREE.Vector3(0.75, 0.5, 1.0).normalize().multiplyScalar(size * 1.6));
  camera.near = size / 200; camera.far = size * 50;
  camera.updateProjectionMatrix();
  controls.update();
  $('brush-radius').max = (size * 0.3).toFixed(3);
  $('brush-radius').step = (size / 400).toFixed(4);
  $('brush-radius').value = (size * 0.05).toFixed(3);
}

function makeGround() {
  if (ground) scene3.remove(ground);
  const bb = geometry.boundingBox;
  const size = bb.getSize(new THREE.Vector3()).length();
  const y = bb.min.y;
  ground = new THREE.Group();
  const plane = new THREE.Mesh(new THREE.PlaneGeometry(size * 8, size * 8),
    new THREE.MeshStandardMaterial({ color: 0x3b414b, roughness: 1 }));
  plane.rotation.x = -Math.PI / 2;
  plane.position.y = y - 1e-4 * size;
  const grid = new THREE.GridHelper(size * 8, 32, 0x59616e, 0x474e59);
  grid.position.y = y;
  ground.add(plane, grid);
  ground.name = 'ground';
  scene3.add(ground);
  S.needsRender = true;
}

let stateBusy = false, stateAgain = false;
async function refreshState() {
  if (stateBusy) { stateAgain = true; return; }
  stateBusy = true;
  try {
    do {
      stateAgain = false;
      const d = await api.get('/api/state');
      if (!d.open) { S.desc = d; setStatus('no scene open: Open… a scene or a mesh', ''); openDialog(); continue; }
      if (d.mesh_key !== S.meshKey) {
        S.meshKey = d.mesh_key;
        await loadMesh();
        const late = S.lateFrames;
        S.lateFrames = null;
        if (late) offerFrames(late);
      }
      S.desc = d;
      S.groupVerts = {};
      for (const [name, idx] of Object.entries(d.groups)) S.groupVerts[name] = Int32Array.from(idx);
      if (S.selectedGroup && !(S.selectedGroup in d.scene.groups)) S.selectedGroup = null;
      if (S.selectedKey !== null && !d.scene.keyframes.some((k) => k.id === S.selectedKey)) selectKey(null);
      renderPanels();
      if (d.group_error) setStatus(d.group_error, 'err');
    } while (stateAgain);
  } catch (err) { setStatus(`cannot reach the editor server: ${err.message}`, 'err'); }
  finally { stateBusy = false; }
  window.wiggly.ready = true;
}

let framesWanted = null, framesBusy = false;
function offerFrames(meta) {
  // right after a gizmo release, frames of the drag previews are stale: skip them
  if (S.committing && meta.version <= S.committing.base) return;
  if (S.committing && meta.version > S.committing.base && !S.committing.event) S.committing.event = performance.now();
  const rank = STAGE_RANK[meta.stage] * 2 + (meta.final ? 1 : 0);
  const best = framesWanted || S.shown;
  if (meta.seq < best.seq || (meta.seq === best.seq && rank <= best.rank)) return;
  framesWanted = { ...meta, rank };
  if (!S.n) { S.lateFrames = framesWanted; framesWanted = null; return; }
  if (!framesBusy) fetchFrames();
}
async function fetchFrames() {
  framesBusy = true;
  try {
    while (framesWanted) {
      const meta = framesWanted;
      framesWanted = null;
      if (meta.seq < S.shown.seq || (meta.seq === S.shown.seq && meta.rank <= S.shown.rank)) continue;
      if (S.committing && meta.version <= S.committing.base) continue;
      let buf;
      const requested = performance.now();
      try { ({ buf } = await api.bin(`/api/frames/${meta.id}`)); } catch { continue; }
      const fetched = performance.now();
      if (S.committing && meta.version <= S.committing.base) continue;
      if (meta.n_vertices !== S.n) { S.lateFrames = meta; continue; }  // mesh not loaded yet
      S.frames = { meta, data: new Float32Array(buf) };
      S.shown = { seq: meta.seq, rank: meta.rank, id: meta.id };
      window.wiggly.framesApplied += 1;
      showFrame();
      if (S.committing) flushState();  // the committed edit's frames: panels may update now
      if (S.release && meta.version >= S.release.version) {
        const rel = S.release;
        const stage = meta.stage + (meta.final ? ' (final)' : '');
        const applied = performance.now();
        requestAnimationFrame(() => {   // the frame is drawn in this callback (tick renders)
          const ms = performance.now() - rel.t;
          window.wiggly.latencies.push({ ms, stage, version: meta.version, first: !rel.done,
            posted: rel.posted, requested: requested - rel.t,
            event: S.lastCommit && S.lastCommit.t === rel.t && S.lastCommit.event ? S.lastCommit.event - rel.t : null,
            fetched: fetched - rel.t, applied: applied - rel.t,
            server_seconds: meta.seconds });
          rel.done = true;
        });
        if (meta.final) S.release = null;
      }
    }
  } finally { framesBusy = false; }
}

// ------------------------------------------------------------------------------------------
// events from the server

function connect() {
  const es = new EventSource('/api/events');
  es.onmessage = (m) => {
    const e = JSON.parse(m.data);
    if (e.type === 'state') {
      if (S.committing) { S.stateDeferred = true; setTimeout(flushState, 1000); }  // frames first
      else refreshState();
    }
    else if (e.type === 'frames') offerFrames(e);
    else if (e.type === 'solve') onSolve(e);
    else if (e.type === 'physics') onPhysics(e);
    else if (e.type === 'export') { setStatus(e.message, e.stage === 'error' ? 'err' : e.stage === 'done' ? 'ok' : 'busy'); if (e.stage !== 'running') toast(e.message, e.stage === 'error'); }
    else if (e.type === 'notice') toast(e.message, e.level === 'error');
  };
  es.onerror = () => setStatus('connection to the editor server lost; retrying…', 'err');
  es.onopen = () => refreshState();
}

function fmt(x, d = 3) { return x === null || x === undefined || Number.isNaN(x) ? '–' : Number(x).toPrecision(d); }
function onSolve(e) {
  if (e.seq < S.shown.seq && e.stage !== 'error') return;
  const res = e.residual_max != null ? `, max keyframe residual ${fmt(e.residual_max * 1000)} mm` : '';
  if (e.stage === 'error') setStatus(e.message, 'err');
  else if (e.stage === 'linear') setStatus('solving… (linear)', 'busy');
  else if (e.stage === 'warped') setStatus(`solving… warped: ${e.iterations} Gauss-Newton iterations, objective ${fmt(e.objective, 4)}`, 'busy');
  else if (e.stage === 'done') setStatus(`${e.converged === undefined ? 'linear solve' : 'warped: ' + e.message} in ${fmt(e.seconds)} s${res}`, e.converged === false ? '' : 'ok');
}
function onPhysics(e) {
  const bar = $('phys-progress');
  const busy = e.stage !== 'ready' && e.stage !== 'error';
  bar.hidden = !busy;
  bar.firstElementChild.style.width = `${Math.round(100 * e.fraction)}%`;
  bar.classList.toggle('indeterminate', busy && e.stage === 'mesh');
  $('phys-state').textContent = busy ? `${e.message}… ${e.elapsed.toFixed(1)} s` : e.message;
  if (busy) setStatus(`recomputing: ${e.message}…`, 'busy');
  else if (e.stage === 'error') setStatus(e.message, 'err');
}

// ------------------------------------------------------------------------------------------
// status, toast, modal

function setStatus(text, cls) {
  const el = $('status-text');
  el.textContent = text;
  el.className = cls || '';
}
let toastTimer = null;
function toast(text, err = false) {
  const el = $('toast');
  el.textContent = text;
  el.className = err ? 'err' : '';
  el.hidden = false;
  clearTimeout(toastTimer);
  toastTimer = setTimeout(() => { el.hidden = true; }, err ? 7000 : 3500);
}
async function act(fn) {
  try { return await fn(); } catch (err) { toast(err.message, true); setStatus(err.message.split('\n')[0], 'err'); return null; }
}
function edit(op) { return act(() => api.post('/api/edit', op)); }

function modal(title, bodyEl, onOk) {
  $('modal-title').textContent = title;
  const body = $('modal-body');
  body.replaceChildren(bodyEl);
  $('modal').hidden = false;
  const close = () => { $('modal').hidden = true; };
  $('modal-cancel').onclick = close;
  $('modal-ok').onclick = async () => { if (await onOk() !== false) close(); };
  const first = body.querySelector('input');
  if (first) first.focus();
}
async function openDialog() {
  const files = await act(() => api.get('/api/files'));
  if (!files) return;
  const wrap = document.createElement('div');
  const input = document.createElement('input');
  input.type = 'text'; input.placeholder = 'scene.toml, mesh.obj or builtin:critter';
  const upload = document.createElement('input');
  upload.type = 'file'; upload.accept = '.obj,.ply,.stl,.off,.glb,.gltf,.msh,.vtu,.vtk,.mesh';
  upload.title = 'upload a mesh into the editor folder (uploads/)';
  upload.onchange = async () => {
    const f = upload.files[0];
    if (!f) return;
    const name = f.name.replace(/[^A-Za-z0-9_.-]/g, '_');
    const r = await act(async () => {
      const res = await fetch(`/api/upload?name=${encodeURIComponent(name)}`, {
        method: 'PUT', body: f, headers: { 'X-Wiggly-Upload': '1', 'Content-Type': 'application/octet-stream' } });
      const d = await res.json();
      if (!res.ok) throw new Error(d.error || res.statusText);
      return d;
    });
    if (r) { input.value = r.path; toast(`uploaded ${r.path}`); }
  };
  wrap.append(input, upload);
  const label = (f) => (files.unsaved.includes(f) ? `${f}  (unsaved: recover from autosave)` : f);
  for (const f of [...files.unsaved, ...files.scenes, ...files.meshes, ...files.builtin]) {
    const d = document.createElement('div');
    d.className = 'file'; d.textContent = label(f);
    d.onclick = () => { input.value = f; };
    d.ondblclick = () => $('modal-ok').click();
    wrap.append(d);
  }
  modal('Open a scene or a mesh', wrap, async () => {
    const r = await act(() => api.post('/api/open', { path: input.value.trim() }));
    if (!r) return false;
    for (const n of r.notices || []) toast(n);
    selectKey(null); S.selectedGroup = null;
    return true;
  });
}
function promptDialog(title, value, onOk) {
  const input = document.createElement('input');
  input.type = 'text'; input.value = value;
  input.onkeydown = (e) => { if (e.key === 'Enter') $('modal-ok').click(); };
  modal(title, input, () => onOk(input.value.trim()));
}

// ------------------------------------------------------------------------------------------
// panels

function scene() { return S.desc && S.desc.open ? S.desc.scene : null; }
function groupColor(name) {
  const g = scene().groups[name];
  return (g && g.color) || '#ff7f0e';
}
function keyKind(k) {
  const p = k.position;
  if (p === undefined) return 'velocity only';
  if (p === 'rest') return 'rest';
  if (p.offset) return `offset [${p.offset.map((x) => x.toFixed(3)).join(', ')}]`;
  if (p.absolute) return `absolute (${p.absolute.length} points)`;
  return `rigid: rot [${p.rotation.map((x) => x.toFixed(1)).join(', ')}]°, move [${(p.translation || [0, 0, 0]).map((x) => x.toFixed(3)).join(', ')}]`;
}

function renderPanels() {
  if (!S.desc || !S.desc.open) return;
  const d = S.desc, sc = d.scene;
  $('file-name').textContent = d.path || sc.name;
  $('dirty').textContent = d.dirty ? '●' : '';
  $('btn-undo').disabled = !d.can_undo;
  $('btn-redo').disabled = !d.can_redo;
  document.title = `${d.dirty ? '● ' : ''}${sc.name} — wiggly edit`;
  // groups
  const ul = $('groups');
  ul.replaceChildren();
  for (const [name, g] of Object.entries(sc.groups)) {
    const li = document.createElement('li');
    li.dataset.group = name;
    if (name === S.selectedGroup) li.classList.add('sel');
    const color = document.createElement('input');
    color.type = 'color'; color.value = g.color || '#ff7f0e'; color.title = 'color';
    color.onchange = () => edit({ op: 'recolor_group', name, color: color.value });
    const label = document.createElement('span');
    label.className = 'name';
    label.textContent = `${name} (${(S.groupVerts[name] || []).length})`;
    label.title = 'click: select; double-click: rename';
    label.ondblclick = () => promptDialog(`Rename group ${name}`, name, (v) => edit({ op: 'rename_group', name, new_name: v }));
    const fixed = document.createElement('label');
    fixed.className = 'small'; fixed.title = 'hold these vertices at rest';
    const cb = document.createElement('input');
    cb.type = 'checkbox'; cb.checked = sc.simulation.fixed.includes(name);
    cb.onchange = () => edit({ op: 'set_fixed', name, fixed: cb.checked });
    fixed.append(cb, ' fixed');
    const del = document.createElement('button');
    del.className = 'x'; del.textContent = '✕'; del.title = 'delete group (and its keyframes)';
    del.onclick = (e) => { e.stopPropagation(); deleteGroup(name); };
    li.onclick = (e) => { if (e.target === li || e.target === label) selectGroup(name, true); };
    li.append(color, label, fixed, del);
    ul.append(li);
  }
  // keyframes
  const kl = $('keys');
  kl.replaceChildren();
  const keys = [...sc.keyframes].sort((a, b) => a.time - b.time);
  for (const k of keys) {
    const li = document.createElement('li');
    li.dataset.key = k.id;
    if (k.id === S.selectedKey) li.classList.add('sel');
    const sw = document.createElement('span');
    sw.className = 'swatch'; sw.style.background = groupColor(k.group);
    const label = document.createElement('span');
    label.className = 'name';
    label.textContent = `${k.time.toFixed(3)} s  ${k.name || k.group}  · ${keyKind(k).split(':')[0]}${k.velocity ? ' · v' : ''}`;
    li.onclick = () => selectKey(k.id, true);
    li.append(sw, label);
    kl.append(li);
  }
  // physics
  for (const el of document.querySelectorAll('[data-set]')) {
    if (document.activeElement === el) continue;
    const v = getPath(sc, el.dataset.set);
    if (el.type === 'checkbox') el.checked = !!v;
    else el.value = v === undefined || v === null ? '' : v;
  }
  if (sc.time.end === undefined) document.querySelector('[data-set="time.end"]').value = sc.time_range[1];
  renderKeyPanel();
  updatePoseHelpers();
  drawTimeline();
  updateColors();
}

function getPath(obj, path) {
  return path.split('.').reduce((o, k) => (o == null ? undefined : o[k]), obj);
}

function currentKey() {
  if (S.selectedKey === null || !scene()) return null;
  return scene().keyframes.find((k) => k.id === S.selectedKey) || null;
}
function renderKeyPanel() {
  const k = currentKey();
  $('key-panel').hidden = !k;
  if (!k) return;
  const sel = $('key-group');
  sel.replaceChildren(...Object.keys(scene().groups).map((g) => new Option(g, g, false, g === k.group)));
  if (document.activeElement !== $('key-time')) $('key-time').value = k.time;
  if (document.activeElement !== $('key-stiffness')) $('key-stiffness').value = k.stiffness ?? '';
  if (document.activeElement !== $('key-name')) $('key-name').value = k.name || '';
  $('key-kind').textContent = keyKind(k);
  $('key-vel-on').checked = !!k.velocity;
  const v = k.velocity || [0, 0, 0];
  ['key-vx', 'key-vy', 'key-vz'].forEach((id, i) => { if (document.activeElement !== $(id)) $(id).value = v[i]; });
  $('btn-pose-t').classList.toggle('active', !!S.posing && S.posing.mode === 'translate');
  $('btn-pose-r').classList.toggle('active', !!S.posing && S.posing.mode === 'rotate');
  $('btn-pose-v').classList.toggle('active', !!S.posing && S.posing.mode === 'velocity');
}

function selectGroup(name, alsoSelection) {
  S.selectedGroup = name;
  if (alsoSelection && S.groupVerts[name]) {
    S.selection.fill(0);
    for (const i of S.groupVerts[name]) S.selection[i] = 1;
    $('group-name').value = name;
    updateSelCount();
  }
  renderPanels();
}
function selectKey(id, seek) {
  S.selectedKey = id;
  const k = currentKey();
  if (!k) { stopPosing(); }
  else {
    S.selectedGroup = k.group;
    if (seek) { S.playing = false; setTime(k.time); }
    if (S.posing && S.posing.id !== id) startPosing(S.posing.mode);
  }
  if (S.desc) renderPanels();
}
async function deleteGroup(name) {
  const n = scene().keyframes.filter((k) => k.group === name).length;
  if (n && !confirm(`Delete group ${name} and its ${n} keyframe(s)?`)) return;
  await edit({ op: 'delete_group', name });
}

// ------------------------------------------------------------------------------------------
// playback

function range() { return scene() ? scene().time_range : [0, 1]; }
function setTime(t) {
  const [a, b] = range();
  S.t = Math.min(Math.max(t, a), b);
  showFrame();
}
function frameIndex() {
  const f = S.frames;
  if (!f) return -1;
  const i = Math.round((S.t - f.meta.start) * f.meta.fps);
  return Math.min(Math.max(i, 0), f.meta.n_frames - 1);
}
function showFrame() {
  const pos = geometry.getAttribute('position');
  if (!pos) return;
  const i = frameIndex();
  if (i >= 0) pos.array.set(S.frames.data.subarray(i * S.n * 3, (i + 1) * S.n * 3));
  else pos.array.set(S.rest);
  pos.needsUpdate = true;
  geometry.computeVertexNormals();
  updateColors();
  S.needsRender = true;
  $('time-readout').textContent = `${S.t.toFixed(3)} s  ·  frame ${Math.max(i, 0)}${S.frames ? ' / ' + (S.frames.meta.n_frames - 1) : ''}  ·  ${S.frames ? S.frames.meta.stage : 'rest'}`;
  drawTimeline();
}
function updateColors() {
  const col = geometry.getAttribute('color');
  if (!col || !scene()) return;
  const c = col.array;
  for (let i = 0; i < S.n; i++) { c[3 * i] = BASE.r; c[3 * i + 1] = BASE.g; c[3 * i + 2] = BASE.b; }
  const tint = new THREE.Color();
  const weights = {};
  for (const name of Object.keys(scene().groups)) weights[name] = name === S.selectedGroup ? 0.45 : 0.18;
  for (const k of scene().keyframes) {
    const w = Math.max(0, 1 - Math.abs(S.t - k.time) / KEY_WINDOW);
    weights[k.group] = Math.max(weights[k.group] || 0, 0.18 + 0.82 * w);
  }
  for (const [name, w] of Object.entries(weights)) {
    const idx = S.groupVerts[name];
    if (!idx) continue;
    tint.set(groupColor(name));
    for (const i of idx) {
      c[3 * i] = BASE.r + (tint.r - BASE.r) * w;
      c[3 * i + 1] = BASE.g + (tint.g - BASE.g) * w;
      c[3 * i + 2] = BASE.b + (tint.b - BASE.b) * w;
    }
  }
  for (let i = 0; i < S.n; i++) {
    if (S.selection[i]) { c[3 * i] = SELECTED.r; c[3 * i + 1] = SELECTED.g; c[3 * i + 2] = SELECTED.b; }
  }
  col.needsUpdate = true;
  S.needsRender = true;
}
function togglePlay() {
  S.playing = !S.playing;
  const [a, b] = range();
  if (S.playing && S.t >= b - 1e-9) S.t = a;
  S.lastTick = performance.now();
  $('btn-play').textContent = S.playing ? '❚❚' : '▶';
}
function step(dt) {
  if (!S.playing) return;
  const [a, b] = range();
  let t = S.t + dt;
  if (t > b) {
    if ($('loop').checked) t = a + ((t - a) % Math.max(b - a, 1e-6));
    else { t = b; togglePlay(); }
  }
  setTime(t);
}

// ------------------------------------------------------------------------------------------
// timeline: scrub, keyframe markers (drag in time, select, delete)

const tl = $('timeline');
const TL_PAD = 14;
function tlX(t) { const [a, b] = range(); return TL_PAD + (t - a) / Math.max(b - a, 1e-9) * (tl.clientWidth - 2 * TL_PAD); }
function tlT(x) { const [a, b] = range(); return a + (x - TL_PAD) / Math.max(tl.clientWidth - 2 * TL_PAD, 1) * (b - a); }
let tlDrag = null;
function drawTimeline() {
  const w = tl.clientWidth, h = tl.clientHeight;
  if (tl.width !== w * devicePixelRatio) { tl.width = w * devicePixelRatio; tl.height = h * devicePixelRatio; }
  const g = tl.getContext('2d');
  g.setTransform(devicePixelRatio, 0, 0, devicePixelRatio, 0, 0);
  g.clearRect(0, 0, w, h);
  g.fillStyle = '#1a1d22'; g.fillRect(TL_PAD, 8, w - 2 * TL_PAD, h - 16);
  if (!scene()) return;
  const [a, b] = range();
  g.fillStyle = '#8d95a3'; g.font = '10px system-ui'; g.strokeStyle = '#3a3f48';
  const stepT = niceStep((b - a) / 10);
  for (let t = Math.ceil(a / stepT) * stepT; t <= b + 1e-9; t += stepT) {
    const x = tlX(t);
    g.beginPath(); g.moveTo(x, 8); g.lineTo(x, h - 8); g.stroke();
    g.fillText(`${+t.toFixed(3)}`, x + 2, h - 1);
  }
  for (const k of scene().keyframes) {
    const t = tlDrag && tlDrag.id === k.id ? tlDrag.t : k.time;
    const x = tlX(t), y = h / 2;
    g.save(); g.translate(x, y); g.rotate(Math.PI / 4);
    g.fillStyle = groupColor(k.group);
    g.fillRect(-5, -5, 10, 10);
    if (k.id === S.selectedKey) { g.strokeStyle = '#fff'; g.lineWidth = 2; g.strokeRect(-6, -6, 12, 12); }
    g.restore();
  }
  const x = tlX(S.t);
  g.strokeStyle = '#4da3ff'; g.lineWidth = 2;
  g.beginPath(); g.moveTo(x, 2); g.lineTo(x, h - 4); g.stroke();
  g.lineWidth = 1;
}
function niceStep(x) { const p = 10 ** Math.floor(Math.log10(x)); const m = x / p; return (m < 1.5 ? 1 : m < 3.5 ? 2 : m < 7.5 ? 5 : 10) * p; }
function keyAt(x) {
  let best = null, dist = 8;
  for (const k of scene().keyframes) { const d = Math.abs(tlX(k.time) - x); if (d < dist) { dist = d; best = k; } }
  return best;
}
function snap(t) { const fps = scene().time.fps; const [a, b] = range(); return Math.min(Math.max(a + Math.round((t - a) * fps) / fps, a), b); }
tl.addEventListener('pointerdown', (e) => {
  if (!scene()) return;
  tl.setPointerCapture(e.pointerId);
  const k = keyAt(e.offsetX);
  if (k) { selectKey(k.id, false); tlDrag = { id: k.id, t: k.time, moved: false, x0: e.offsetX }; }
  else { tlDrag = { scrub: true }; S.playing = false; $('btn-play').textContent = '▶'; setTime(tlT(e.offsetX)); }
});
tl.addEventListener('pointermove', (e) => {
  if (!tlDrag) return;
  if (tlDrag.scrub) { setTime(tlT(e.offsetX)); return; }
  if (Math.abs(e.offsetX - tlDrag.x0) > 3) tlDrag.moved = true;
  if (tlDrag.moved) { tlDrag.t = snap(tlT(e.offsetX)); drawTimeline(); }
});
tl.addEventListener('pointerup', async () => {
  const d = tlDrag; tlDrag = null;
  if (!d || d.scrub) return;
  if (d.moved) { await edit({ op: 'update_keyframe', id: d.id, time: d.t }); setTime(d.t); }
  else setTime(scene().keyframes.find((k) => k.id === d.id).time);
  drawTimeline();
});

// ------------------------------------------------------------------------------------------
// selection tools: brush, box, lasso (screen-space, through the body)

function setTool(tool) {
  S.tool = tool;
  for (const b of document.querySelectorAll('.tool')) b.classList.toggle('active', b.dataset.tool === tool);
  controls.enabled = tool === 'orbit' && !S.dragging;
  canvas.style.cursor = tool === 'orbit' ? '' : 'crosshair';
}
function updateSelCount() {
  let n = 0; for (let i = 0; i < S.n; i++) n += S.selection[i];
  $('sel-count').textContent = `${n} vertices`;
  updateColors();
  return n;
}
function selectedIndices() { const out = []; for (let i = 0; i < S.n; i++) if (S.selection[i]) out.push(i); return out; }
function screenPositions() {
  const pos = geometry.getAttribute('position').array;
  const r = canvas.getBoundingClientRect();
  const v = new THREE.Vector3(), out = new Float32Array(S.n * 3);
  for (let i = 0; i < S.n; i++) {
    v.set(pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]).project(camera);
    out[3 * i] = (v.x + 1) / 2 * r.width; out[3 * i + 1] = (1 - v.y) / 2 * r.height; out[3 * i + 2] = v.z;
  }
  return out;
}
function pointInPolygon(x, y, poly) {
  let inside = false;
  for (let i = 0, j = poly.length - 1; i < poly.length; j = i++) {
    const [xi, yi] = poly[i], [xj, yj] = poly[j];
    if ((yi > y) !== (yj > y) && x < (xj - xi) * (y - yi) / (yj - yi) + xi) inside = !inside;
  }
  return inside;
}
const raycaster = new THREE.Raycaster();
function brushAt(e, value) {
  const r = canvas.getBoundingClientRect();
  const ndc = new THREE.Vector2((e.clientX - r.left) / r.width * 2 - 1, -((e.clientY - r.top) / r.height) * 2 + 1);
  raycaster.setFromCamera(ndc, camera);
  geometry.computeBoundingSphere();
  const hit = raycaster.intersectObject(body, false)[0];
  if (!hit) return;
  const rad = parseFloat($('brush-radius').value), r2 = rad * rad;
  const pos = geometry.getAttribute('position').array, p = hit.point;
  for (let i = 0; i < S.n; i++) {
    const dx = pos[3 * i] - p.x, dy = pos[3 * i + 1] - p.y, dz = pos[3 * i + 2] - p.z;
    if (dx * dx + dy * dy + dz * dz <= r2) S.selection[i] = value;
  }
  updateSelCount();
}
let toolDrag = null;
canvas.addEventListener('pointerdown', (e) => {
  if (S.tool === 'orbit' || e.button !== 0 || S.dragging) return;
  canvas.setPointerCapture(e.pointerId);
  const value = e.altKey || e.ctrlKey ? 0 : 1;
  const r = canvas.getBoundingClientRect();
  const x = e.clientX - r.left, y = e.clientY - r.top;
  if (S.tool !== 'brush' && !e.shiftKey && value === 1) S.selection.fill(0);
  toolDrag = { value, x0: x, y0: y, pts: [[x, y]] };
  if (S.tool === 'brush') brushAt(e, value);
});
canvas.addEventListener('pointermove', (e) => {
  if (!toolDrag) return;
  const r = canvas.getBoundingClientRect();
  const x = e.clientX - r.left, y = e.clientY - r.top;
  if (S.tool === 'brush') brushAt(e, toolDrag.value);
  else if (S.tool === 'box') {
    const m = $('marquee'); m.hidden = false;
    Object.assign(m.style, { left: `${Math.min(x, toolDrag.x0)}px`, top: `${Math.min(y, toolDrag.y0)}px`,
      width: `${Math.abs(x - toolDrag.x0)}px`, height: `${Math.abs(y - toolDrag.y0)}px` });
    toolDrag.x1 = x; toolDrag.y1 = y;
  } else if (S.tool === 'lasso') {
    toolDrag.pts.push([x, y]);
    $('lasso').hidden = false;
    $('lasso').firstElementChild.setAttribute('points', toolDrag.pts.map((p) => p.join(',')).join(' '));
  }
});
canvas.addEventListener('pointerup', () => {
  const d = toolDrag; toolDrag = null;
  $('marquee').hidden = true; $('lasso').hidden = true;
  if (!d || S.tool === 'brush') return;
  const sp = screenPositions();
  if (S.tool === 'box' && d.x1 !== undefined) {
    const [x0, x1] = [Math.min(d.x0, d.x1), Math.max(d.x0, d.x1)], [y0, y1] = [Math.min(d.y0, d.y1), Math.max(d.y0, d.y1)];
    for (let i = 0; i < S.n; i++) {
      const x = sp[3 * i], y = sp[3 * i + 1];
      if (x >= x0 && x <= x1 && y >= y0 && y <= y1 && sp[3 * i + 2] < 1) S.selection[i] = d.value;
    }
  } else if (S.tool === 'lasso' && d.pts.length > 2) {
    for (let i = 0; i < S.n; i++) if (sp[3 * i + 2] < 1 && pointInPolygon(sp[3 * i], sp[3 * i + 1], d.pts)) S.selection[i] = d.value;
  }
  updateSelCount();
});

async function newGroupFromSelection() {
  const idx = selectedIndices();
  if (!idx.length) { toast('select some vertices first (Brush B, Box X, Lasso L)', true); return; }
  let name = $('group-name').value.trim();
  if (!name) { let k = Object.keys(scene().groups).length + 1; while (`group${k}` in scene().groups) k++; name = `group${k}`; }
  if (name in scene().groups && !confirm(`Replace the vertices of group ${name}?`)) return;
  const r = await edit({ op: 'set_group', name, indices: idx });
  if (r) { S.selectedGroup = name; $('group-name').value = ''; S.selection.fill(0); updateSelCount(); }
}
async function setGroupFromSelection() {
  if (!S.selectedGroup) { toast('select a group in the list first', true); return; }
  const idx = selectedIndices();
  if (!idx.length) { toast('the selection is empty', true); return; }
  await edit({ op: 'set_group', name: S.selectedGroup, indices: idx });
}

// ------------------------------------------------------------------------------------------
// keyframes and posing (translate/rotate gizmo; ghost of the target pose)

async function addKey() {
  const name = S.selectedGroup;
  if (!name) { toast('select a group first (click it in the list)', true); return; }
  const r = await edit({ op: 'add_keyframe', time: snap(S.t), group: name, position: 'current' });
  if (r && r.id !== undefined) { S.selectedKey = r.id; await refreshState(); selectKey(r.id, false); }
}
function groupCentroid(name) {
  const idx = S.groupVerts[name], c = new THREE.Vector3();
  if (!idx || !idx.length) return c;
  for (const i of idx) c.x += S.rest[3 * i], c.y += S.rest[3 * i + 1], c.z += S.rest[3 * i + 2];
  return c.divideScalar(idx.length);
}
// A keyframe's position as a rigid transform {rotation (deg, extrinsic XYZ), translation, center}.
function rigidOf(k) {
  const center = groupCentroid(k.group);
  const p = k.position;
  const out = { rotation: [0, 0, 0], translation: [0, 0, 0], center: center.toArray() };
  if (!p || p === 'rest') return out;
  if (p.offset) { out.translation = [...p.offset]; return out; }
  if (p.absolute) return null;
  out.rotation = [...p.rotation];
  out.translation = [...(p.translation || [0, 0, 0])];
  if (p.center) out.center = [...p.center];
  return out;
}
const D2R = Math.PI / 180;
function rigidMatrix(rg) {   // x = R (X - c) + c + t, R = Rz Ry Rx (three.js Euler order 'ZYX')
  const R = new THREE.Matrix4().makeRotationFromEuler(new THREE.Euler(rg.rotation[0] * D2R, rg.rotation[1] * D2R, rg.rotation[2] * D2R, 'ZYX'));
  const c = new THREE.Vector3(...rg.center), t = new THREE.Vector3(...rg.translation);
  return new THREE.Matrix4().makeTranslation(c.x + t.x, c.y + t.y, c.z + t.z).multiply(R).multiply(new THREE.Matrix4().makeTranslation(-c.x, -c.y, -c.z));
}
function setGhost(k, rg) {
  const idx = S.groupVerts[k.group];
  if (!idx) { ghost.visible = false; return; }
  const arr = new Float32Array(idx.length * 3);
  const v = new THREE.Vector3();
  if (rg) {
    const M = rigidMatrix(rg);
    idx.forEach((i, j) => { v.set(S.rest[3 * i], S.rest[3 * i + 1], S.rest[3 * i + 2]).applyMatrix4(M); arr.set([v.x, v.y, v.z], 3 * j); });
  } else if (k.position && k.position.absolute) {
    k.position.absolute.forEach((p, j) => arr.set(p, 3 * j));
  }
  ghostGeom.setAttribute('position', new THREE.BufferAttribute(arr, 3));
  ghostGeom.computeBoundingSphere();
  ghost.material.color.set(groupColor(k.group));
  ghost.visible = !!k.position;
  S.needsRender = true;
  const c = new THREE.Vector3(); for (let j = 0; j < idx.length; j++) c.x += arr[3 * j], c.y += arr[3 * j + 1], c.z += arr[3 * j + 2];
  S.velBase = c.divideScalar(Math.max(idx.length, 1));
  showVelocity(k.velocity);
}
function showVelocity(v) {
  const vel = new THREE.Vector3(...(v || [0, 0, 0])), len = vel.length() * VEL_SCALE;
  velArrow.position.copy(S.velBase);
  velArrow.visible = !!v && len > 1e-6;
  if (velArrow.visible) { velArrow.setDirection(vel.normalize()); velArrow.setLength(len, Math.min(0.04, 0.4 * len), Math.min(0.025, 0.25 * len)); }
  S.needsRender = true;
}
function updatePoseHelpers() {
  const k = currentKey();
  S.needsRender = true;
  if (!k) { ghost.visible = false; velArrow.visible = false; gizmo.detach(); return; }
  if (S.dragging) return;
  const rg = rigidOf(k);
  setGhost(k, rg);
  if (S.posing && S.posing.mode === 'velocity') {
    pivot.position.copy(S.velBase).addScaledVector(new THREE.Vector3(...(k.velocity || [0, 0, 0])), VEL_SCALE);
    pivot.updateMatrixWorld();
  } else if (S.posing && rg) placePivot(rg);
}
function placePivot(rg) {
  const c = new THREE.Vector3(...rg.center), t = new THREE.Vector3(...rg.translation);
  pivot.position.copy(c).add(t);
  pivot.quaternion.setFromEuler(new THREE.Euler(rg.rotation[0] * D2R, rg.rotation[1] * D2R, rg.rotation[2] * D2R, 'ZYX'));
  pivot.updateMatrixWorld();
  S.posing.center = rg.center;
}
function startPosing(mode) {
  const k = currentKey();
  if (!k) { toast('select a keyframe first', true); return; }
  if (mode === 'velocity') {
    S.posing = { id: k.id, mode };
    S.playing = false; $('btn-play').textContent = '▶';
    setTime(k.time);
    setGhost(k, rigidOf(k));
    const v = new THREE.Vector3(...(k.velocity || [0, 0, 0]));
    pivot.position.copy(S.velBase).addScaledVector(v, VEL_SCALE);
    pivot.quaternion.identity();
    pivot.updateMatrixWorld();
    gizmo.setMode('translate');
    gizmo.setSpace('world');
    gizmo.attach(pivot);
    renderKeyPanel();
    return;
  }
  const rg = rigidOf(k);
  if (!rg) { toast('absolute targets cannot be posed with the gizmo; press Rest to start from the rest pose', true); return; }
  S.posing = { id: k.id, mode, center: rg.center };
  S.playing = false; $('btn-play').textContent = '▶';
  setTime(k.time);
  placePivot(rg);
  gizmo.setMode(mode);
  gizmo.setSpace(mode === 'rotate' ? 'local' : 'world');
  gizmo.attach(pivot);
  renderKeyPanel();
}
function stopPosing() { S.posing = null; gizmo.detach(); S.needsRender = true; }
function velocityTarget() {
  const r4 = (x) => Math.round(x * 1e4) / 1e4;
  return pivot.position.clone().sub(S.velBase).divideScalar(VEL_SCALE).toArray().map(r4);
}
function poseOp(k) {
  return S.posing.mode === 'velocity' ? { op: 'update_keyframe', id: k.id, velocity: velocityTarget() }
    : { op: 'update_keyframe', id: k.id, position: poseTarget() };
}
function poseTarget() {
  if (!S.posing) return null;
  const e = new THREE.Euler().setFromQuaternion(pivot.quaternion, 'ZYX');
  const c = S.posing.center;
  const r6 = (x) => Math.round(x * 1e6) / 1e6;
  return {
    rotation: [r6(e.x / D2R), r6(e.y / D2R), r6(e.z / D2R)],
    translation: [r6(pivot.position.x - c[0]), r6(pivot.position.y - c[1]), r6(pivot.position.z - c[2])],
    center: c.map(r6),
  };
}
function dragPose() {
  const k = currentKey();
  if (!k || !S.posing) return;
  if (S.posing.mode === 'velocity') showVelocity(velocityTarget());
  else setGhost(k, poseTarget());
  const op = poseOp(k);
  if (S.previewInFlight) { S.previewPending = op; return; }
  sendPreview(op);
}
async function sendPreview(op) {
  S.previewInFlight = true;
  try { await api.post('/api/preview', op); } catch { /* the commit on release reports errors */ }
  S.previewInFlight = false;
  if (S.previewPending && S.dragging) { const next = S.previewPending; S.previewPending = null; sendPreview(next); }
  else S.previewPending = null;
}
let releaseT = null;
window.addEventListener('pointerup', () => {
  if (!S.dragging) return;
  releaseT = performance.now();
  S.committing = { base: S.desc.version, t: releaseT, event: null };
  S.lastCommit = S.committing;
}, true);
function flushState() {
  S.committing = null;
  if (S.stateDeferred) { S.stateDeferred = false; refreshState(); }
}
async function commitPose() {
  const k = currentKey();
  if (!k || !S.posing) return;
  const t0 = releaseT ?? performance.now();
  releaseT = null;
  S.previewPending = null;
  const r = await edit(poseOp(k));
  if (r && r.changed) S.release = { t: t0, version: r.version, done: false, posted: performance.now() - t0 };
  else flushState();
}
function gizmoHandle(axis) {   // screen point of the gizmo and the direction of an axis (tests)
  const r = canvas.getBoundingClientRect();
  const p = pivot.position.clone();
  const dir = { X: [1, 0, 0], Y: [0, 1, 0], Z: [0, 0, 1] }[axis] || [0, 0, 0];
  const len = camera.position.distanceTo(p) * 0.05;
  const q = p.clone().add(new THREE.Vector3(...dir).multiplyScalar(len)).project(camera);
  const o = p.clone().project(camera);
  const ox = r.left + (o.x + 1) / 2 * r.width, oy = r.top + (1 - o.y) / 2 * r.height;
  const dx = r.left + (q.x + 1) / 2 * r.width - ox, dy = r.top + (1 - q.y) / 2 * r.height - oy;
  const n = Math.hypot(dx, dy) || 1;
  return { x: ox, y: oy, dx: dx / n, dy: dy / n, axis: gizmo.axis };
}
function projectGroup(name) { return screenBox(S.groupVerts[name] || []); }
function screenBox(indices) {  // page-space bounding box of some vertices (tests)
  const sp = screenPositions(), r = canvas.getBoundingClientRect();
  let x0 = 1e9, y0 = 1e9, x1 = -1e9, y1 = -1e9;
  for (const i of indices) { x0 = Math.min(x0, sp[3 * i]); x1 = Math.max(x1, sp[3 * i]); y0 = Math.min(y0, sp[3 * i + 1]); y1 = Math.max(y1, sp[3 * i + 1]); }
  return { x0: x0 + r.left, y0: y0 + r.top, x1: x1 + r.left, y1: y1 + r.top };
}

// ------------------------------------------------------------------------------------------
// wiring

$('btn-open').onclick = openDialog;
async function save() {
  const r = await act(() => api.post('/api/save', {}));
  if (r) { toast(`saved ${r.path}`); setStatus(`saved ${r.path}`, 'ok'); }
}
$('btn-save').onclick = save;
$('btn-saveas').onclick = () => promptDialog('Save scene as (.toml)', S.desc.path || 'scene.toml', async (p) => {
  const r = await act(() => api.post('/api/save', { path: p }));
  if (r) toast(`saved ${r.path}`);
  return !!r;
});
$('btn-export').onclick = () => {
  const n = scene().name;
  promptDialog('Export (comma-separated: .glb .usd .usda .usdc .npz .obj .mp4 .gif .png)', `out/${n}.glb, out/${n}.mp4`, async (v) => {
    const paths = v.split(',').map((s) => s.trim()).filter(Boolean);
    const r = await act(() => api.post('/api/export', { paths, overwrite: true }));
    if (r) setStatus(`exporting ${r.paths.join(', ')}…`, 'busy');
    return !!r;
  });
};
const undo = () => act(() => api.post('/api/undo'));
const redo = () => act(() => api.post('/api/redo'));
$('btn-undo').onclick = undo;
$('btn-redo').onclick = redo;
for (const b of document.querySelectorAll('.tool')) b.onclick = () => setTool(b.dataset.tool);
$('btn-group-new').onclick = newGroupFromSelection;
$('btn-group-set').onclick = setGroupFromSelection;
$('btn-sel-clear').onclick = () => { S.selection.fill(0); updateSelCount(); };
$('btn-key-add').onclick = addKey;
$('btn-pose-t').onclick = () => (S.posing && S.posing.mode === 'translate' ? stopPosing() : startPosing('translate'), renderKeyPanel());
$('btn-pose-r').onclick = () => (S.posing && S.posing.mode === 'rotate' ? stopPosing() : startPosing('rotate'), renderKeyPanel());
$('btn-pose-v').onclick = () => (S.posing && S.posing.mode === 'velocity' ? stopPosing() : startPosing('velocity'), renderKeyPanel());
$('btn-pose-rest').onclick = () => { const k = currentKey(); if (k) edit({ op: 'update_keyframe', id: k.id, position: 'rest' }); };
$('btn-key-del').onclick = () => { const k = currentKey(); if (k) edit({ op: 'delete_keyframe', id: k.id }); };
$('btn-play').onclick = togglePlay;
const keyField = (id, fn) => { $(id).onchange = () => { const k = currentKey(); if (k) edit({ op: 'update_keyframe', id: k.id, ...fn($(id)) }); }; };
keyField('key-time', (el) => ({ time: parseFloat(el.value) }));
keyField('key-group', (el) => ({ group: el.value }));
keyField('key-stiffness', (el) => ({ stiffness: el.value === '' ? null : parseFloat(el.value) }));
keyField('key-name', (el) => ({ name: el.value || null }));
const velocity = () => ($('key-vel-on').checked ? ['key-vx', 'key-vy', 'key-vz'].map((id) => parseFloat($(id).value) || 0) : null);
for (const id of ['key-vel-on', 'key-vx', 'key-vy', 'key-vz']) keyField(id, () => ({ velocity: velocity() }));
for (const el of document.querySelectorAll('[data-set]')) {
  el.onchange = () => {
    const [section, key, index] = el.dataset.set.split('.');
    let v = el.type === 'checkbox' ? el.checked : parseFloat(el.value);
    if (el.type !== 'checkbox' && Number.isNaN(v)) { toast(`${section}.${key}: not a number`, true); return; }
    if (key === 'modes') v = Math.round(v);
    if (index !== undefined) { const vec = [...getPath(scene(), `${section}.${key}`)]; vec[+index] = v; v = vec; }
    edit({ op: 'set', section, values: { [key]: v } });
  };
}
$('btn-help').onclick = () => toast([
  'Space play/pause · ←/→ step a frame · Home/End',
  'Q/Esc orbit · B brush · X box · L lasso (Shift adds, Alt removes) · [ ] brush radius',
  'G new group from selection · K keyframe the selected group at the current time',
  'W move / E rotate the selected keyframe (gizmo) · V drag its velocity arrow · Delete removes it',
  'Ctrl+Z undo · Ctrl+Shift+Z / Ctrl+Y redo · Ctrl+S save'].join('\n'));

window.addEventListener('keydown', (e) => {
  const typing = ['INPUT', 'SELECT', 'TEXTAREA'].includes(document.activeElement.tagName) && document.activeElement.type !== 'checkbox';
  const mod = e.ctrlKey || e.metaKey;
  if (mod && e.key.toLowerCase() === 's') { e.preventDefault(); save(); return; }
  if (!$('modal').hidden) { if (e.key === 'Escape') $('modal-cancel').click(); return; }
  if (typing && (e.key === 'Enter' || e.key === 'Escape') && document.activeElement.id !== 'group-name') {
    document.activeElement.blur();   // commit the field, give the keys back to the shortcuts
    canvas.focus();
    return;
  }
  if (typing) return;
  if (mod && e.key.toLowerCase() === 'z') { e.preventDefault(); (e.shiftKey ? redo : undo)(); return; }
  if (mod && e.key.toLowerCase() === 'y') { e.preventDefault(); redo(); return; }
  if (mod) return;
  const fps = scene() ? scene().time.fps : 30;
  switch (e.key) {
    case ' ': e.preventDefault(); togglePlay(); break;
    case 'ArrowRight': setTime(S.t + 1 / fps); break;
    case 'ArrowLeft': setTime(S.t - 1 / fps); break;
    case 'Home': setTime(range()[0]); break;
    case 'End': setTime(range()[1]); break;
    case 'Delete': case 'Backspace': { const k = currentKey(); if (k) edit({ op: 'delete_keyframe', id: k.id }); else if (S.selectedGroup) deleteGroup(S.selectedGroup); break; }
    case 'Escape': stopPosing(); setTool('orbit'); renderKeyPanel(); break;
    case 'q': case 'Q': setTool('orbit'); break;
    case 'b': case 'B': setTool('brush'); break;
    case 'x': case 'X': setTool('box'); break;
    case 'l': case 'L': setTool('lasso'); break;
    case 'g': case 'G': newGroupFromSelection(); break;
    case 'k': case 'K': addKey(); break;
    case 'w': case 'W': startPosing('translate'); break;
    case 'e': case 'E': startPosing('rotate'); break;
    case 'v': case 'V': startPosing('velocity'); break;
    case '[': $('brush-radius').stepDown(5); break;
    case ']': $('brush-radius').stepUp(5); break;
    default: return;
  }
});

// Render on demand: only when something changed (software GL in a headless browser draws a
// few frames per second, and an idle editor should leave the main thread to the network).
function tick(now) {
  const dt = Math.min((now - S.lastTick) / 1000, 0.1);
  S.lastTick = now;
  step(dt);
  if (S.needsRender || S.playing) {
    S.needsRender = false;
    renderer.render(scene3, camera);
    window.wiggly.renders = (window.wiggly.renders || 0) + 1;
    window.wiggly.renderedT = S.t;   // the time the canvas shows (tests wait for it)
    window.wiggly.renderMs = performance.now() - now;
  }
  requestAnimationFrame(tick);
}
function redraw() { S.needsRender = true; }
controls.addEventListener('change', redraw);
gizmo.addEventListener('change', redraw);
window.wiggly.softwareGL = SOFTWARE_GL;
resize();
connect();
requestAnimationFrame((now) => { S.lastTick = now; tick(now); });

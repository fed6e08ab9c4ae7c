// Shared by the editor's modules: server access, the browser-side state S, the three.js
// scene (renderer, camera, body), status and toast, and small helpers.  The server holds the
// scene (source of truth); S holds only what this tab shows and how.
import * as THREE from 'three';
import { OrbitControls } from './vendor/OrbitControls.js';

export const $ = (id) => document.getElementById(id);

// Each tab has its own undo history on the server, named by an id kept in sessionStorage (a
// reload keeps it; a new tab gets a new one).  A duplicated tab copies sessionStorage while
// the original is open: the 'live' mark, set while a page of the tab is shown and cleared as
// it goes (a reload), tells the copy to take an id of its own.
export const TAB = (() => {
  let t = sessionStorage.getItem('wiggly-tab');
  if (!t || !/^[A-Za-z0-9_-]{1,64}$/.test(t) || sessionStorage.getItem('wiggly-tab-live')) {
    t = (crypto.randomUUID ? crypto.randomUUID() : `${Date.now()}-${Math.random()}`).replace(/[^A-Za-z0-9_-]/g, '');
    sessionStorage.setItem('wiggly-tab', t);
  }
  sessionStorage.setItem('wiggly-tab-live', '1');
  addEventListener('pagehide', () => sessionStorage.removeItem('wiggly-tab-live'));
  addEventListener('pageshow', () => sessionStorage.setItem('wiggly-tab-live', '1'));
  return t;
})();
// Each page load has its own id (a reload is a new page): the server abandons the drag of a
// page whose event stream ends, so other tabs never keep showing its preview.
export const PAGE = (crypto.randomUUID ? crypto.randomUUID() : `${Date.now()}-${Math.random()}`).replace(/[^A-Za-z0-9_-]/g, '').slice(0, 64);

// ------------------------------------------------------------------------------------------
// server access

async function request(method, path, body) {
  const init = { method, headers: { 'X-Wiggly-Tab': TAB, 'X-Wiggly-Page': PAGE } };
  if (S.leaving) init.keepalive = true;  // sent from pagehide: it outlives the page
  if (body !== undefined) {
    init.headers['Content-Type'] = 'application/json';
    init.body = JSON.stringify(body);
  }
  let res;
  try { res = await fetch(path, init); }
  catch {  // no answer at all (fetch's own message is "Failed to fetch")
    throw new Error('the editor server did not answer (stopped or restarting?): this change may not be made; the page shows the server\'s scene again when it is back');
  }
  const text = await res.text();
  let data = {};
  try { data = text ? JSON.parse(text) : {}; } catch { data = { error: text }; }
  if (!res.ok) { const err = new Error(data.error || `${res.status} ${res.statusText}`); err.status = res.status; throw err; }
  return data;
}
export const api = {
  get: (p) => request('GET', p),
  post: (p, b = {}) => request('POST', p, b),
  // a request that outlives the page (sent from pagehide), fire and forget
  beacon(p) {
    fetch(p, { method: 'POST', keepalive: true, body: '{}', headers: {
      'Content-Type': 'application/json', 'X-Wiggly-Tab': TAB, 'X-Wiggly-Page': PAGE } }).catch(() => {});
  },
  async bin(p) {
    let res;
    try { res = await fetch(p); }
    catch {  // no answer at all: the frames come again when the server is back
      throw new Error('the editor server did not answer (stopped or restarting?): the motion is shown again when it is back');
    }
    if (!res.ok) throw new Error(`${p}: ${res.status}`);
    return { buf: await res.arrayBuffer(), meta: res.headers.get('X-Wiggly-Frames') };
  },
};

// ------------------------------------------------------------------------------------------
// the tab's state (everything else is the server's)

export const S = {
  desc: null,            // /api/state
  leaving: false,        // the page is being hidden (reload, close): requests keep alive
  instance: null,        // the server process whose frames and sequence numbers we hold
  meshKey: null,
  rest: null,            // Float32Array n*3 (rest positions)
  faces: null,
  n: 0,
  frames: null,          // {meta, data: Float32Array}
  shown: { seq: -1, rank: -1, id: -1 },
  t: 0, playing: false, lastTick: 0,
  tool: 'orbit',
  selection: new Uint8Array(0),
  selectedGroup: null,   // the active group (last clicked)
  groups: new Set(),     // selected groups (keying several at once)
  selectedKey: null,     // the active keyframe id (its panel, posing)
  keys: new Set(),       // selected keyframe ids (dope sheet)
  clipboard: null,       // copied keyframes {keys: [...], t0}
  groupVerts: {},        // name -> Int32Array
  driver: null,          // the [drive] driver's keyed frames {meta: {times, groups, ...}, data}
  keying: null,          // a key being added (K): its edit's promise, until it is answered
  posing: null,          // {id, mode, center}
  dragging: false,
  xform: null,           // the running gizmo drag: axis, typed value, start pose
  previewInFlight: false, previewPending: null,
  committing: null,      // {base, t}: a released drag waiting for its frames
  release: null,         // {t, base}: latency measurement of a gizmo release
  cursor: null,          // the 3D cursor (a pivot choice), THREE.Vector3
  velBase: new THREE.Vector3(),
  view: {                // how this tab shows things (not part of the scene)
    onion: false, onionCount: 3, onionStep: 5,
    paths: false, driver: true, xray: false, snap: false, snapMove: 0.01, snapTurn: 15,
    pivot: 'centroid', speed: 1, range: null,
  },
  needsRender: true,
};

// Functions the modules register for each other (set in app.js), so that modules do not
// import each other in circles.
export const hooks = {};

// ------------------------------------------------------------------------------------------
// three.js scene

export const canvas = $('canvas');
// Software GL (SwiftShader, llvmpipe: headless browsers, machines without a GPU) draws a frame
// in ~0.1 s at full quality; there, skip MSAA and draw at one pixel per CSS pixel.
export const SOFTWARE_GL = (() => {
  try {
    const gl = document.createElement('canvas').getContext('webgl2');
    const info = gl && gl.getExtension('WEBGL_debug_renderer_info');
    const name = info ? gl.getParameter(info.UNMASKED_RENDERER_WEBGL) : '';
    gl && gl.getExtension('WEBGL_lose_context') && gl.getExtension('WEBGL_lose_context').loseContext();
    return /swiftshader|llvmpipe|software/i.test(name);
  } catch { return false; }
})();
export const renderer = new THREE.WebGLRenderer({ canvas, antialias: !SOFTWARE_GL });
renderer.setPixelRatio(SOFTWARE_GL ? 1 : Math.min(window.devicePixelRatio, 2));
export const scene3 = new THREE.Scene();
scene3.background = new THREE.Color(0x2a2f37);
export const camera = new THREE.PerspectiveCamera(40, 1, 0.01, 100);
camera.position.set(1.6, 1.1, 2.2);
export const controls = new OrbitControls(camera, canvas);
controls.enableDamping = false;
scene3.add(new THREE.HemisphereLight(0xdde6ff, 0x3a3530, 1.6));
const sun = new THREE.DirectionalLight(0xffffff, 1.8);
sun.position.set(2, 4, 3);
scene3.add(sun);
const fill = new THREE.DirectionalLight(0xaabbff, 0.5);
fill.position.set(-3, 1, -2);
scene3.add(fill);

export const geometry = new THREE.BufferGeometry();
// Physically based shading costs software GL most of its time per frame (12 instead of 60
// frames per second on a 20k-tet body): there, Lambert shading.
export function surfaceMaterial(options) {
  return SOFTWARE_GL ? new THREE.MeshLambertMaterial(options)
    : new THREE.MeshStandardMaterial({ roughness: 0.65, metalness: 0.0, ...options });
}
const material = surfaceMaterial({ vertexColors: true, side: THREE.DoubleSide });
export const body = new THREE.Mesh(geometry, material);
body.frustumCulled = false;
scene3.add(body);

export function redraw() { S.needsRender = true; }
controls.addEventListener('change', redraw);

// ------------------------------------------------------------------------------------------
// status, toast, actions

export function setStatus(text, cls) {
  const el = $('status-text');
  el.textContent = text;
  el.className = cls || '';
}
let toastTimer = null;
export function toast(text, err = false) {
  const el = $('toast');
  el.textContent = text;
  el.className = err ? 'err' : '';
  el.hidden = false;
  clearTimeout(toastTimer);
  toastTimer = setTimeout(() => { el.hidden = true; }, err ? 7000 : 3500);
}
export function clearError() {
  const el = $('toast');
  if (!el.hidden && el.className === 'err') { el.hidden = true; clearTimeout(toastTimer); }
  if ($('status-text').className === 'err') setStatus('', '');  // an edit since stands over it
}
// Run a request; errors (the server's 4xx message) go to the toast and the status line.
export async function act(fn) {
  try { return await fn(); } catch (err) { toast(err.message, true); setStatus(err.message.split('\n')[0], 'err'); return null; }
}
export async function edit(op) {
  const r = await act(() => api.post('/api/edit', op));
  if (r) clearError();  // an earlier refusal's message no longer stands over this edit
  if (r && r.notice) toast(r.notice);  // e.g. undo's depth reached
  return r;
}

// ------------------------------------------------------------------------------------------
// the scene as the server describes it

export function scene() { return S.desc && S.desc.open ? S.desc.scene : null; }
export function range() { return scene() ? scene().time_range : [0, 1]; }
export function fps() { return scene() ? scene().time.fps : 30; }
export function groupColor(name) {
  const sc = scene();
  return (sc && sc.group_colors && sc.group_colors[name]) || '#ff7f0e';
}
export function keyById(id) { return scene() ? scene().keyframes.find((k) => k.id === id) || null : null; }
export function currentKey() { return S.selectedKey === null ? null : keyById(S.selectedKey); }
// The time t on the frame grid of the shot.
export function snapTime(t) {
  const [a, b] = range();
  return Math.min(Math.max(a + Math.round((t - a) * fps()) / fps(), a), b);
}
export function groupCentroid(name, positions = S.rest) {
  const idx = S.groupVerts[name], c = new THREE.Vector3();
  if (!idx || !idx.length) return c;
  for (const i of idx) c.x += positions[3 * i], c.y += positions[3 * i + 1], c.z += positions[3 * i + 2];
  return c.divideScalar(idx.length);
}
export function boundsOf(indices, positions = S.rest) {
  const box = new THREE.Box3();
  const v = new THREE.Vector3();
  for (const i of indices) box.expandByPoint(v.set(positions[3 * i], positions[3 * i + 1], positions[3 * i + 2]));
  return box;
}
export function fmt(x, d = 3) { return x === null || x === undefined || Number.isNaN(x) ? '–' : Number(x).toPrecision(d); }

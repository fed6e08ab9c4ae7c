// Posing keyframes with the gizmo: translate (W), rotate (E), velocity (V).  During a drag, as
// in Blender: X, Y, Z constrain to an axis, typed digits set an exact value (Enter applies,
// Backspace edits), Ctrl inverts snapping, Esc (or a right click) cancels.  The pivot of a
// rigid target is the group's centroid, the centre of its bounds, or the 3D cursor.
import * as THREE from 'three';
import { TransformControls } from './vendor/TransformControls.js';
import { $, S, api, hooks, camera, canvas, controls, scene3, body, act, edit, toast, groupColor,
  currentKey, groupCentroid, boundsOf, redraw, setStatus } from './core.js';
import { flushState, setTime, setPlaying } from './playback.js';

const VEL_SCALE = 0.25;        // s: the velocity arrow is v * VEL_SCALE long (metres)
const D2R = Math.PI / 180;
const AXES = { X: new THREE.Vector3(1, 0, 0), Y: new THREE.Vector3(0, 1, 0), Z: new THREE.Vector3(0, 0, 1) };

const ghostGeom = new THREE.BufferGeometry();
const ghost = new THREE.Points(ghostGeom, new THREE.PointsMaterial({ size: 4, sizeAttenuation: false,
  color: 0xffffff, transparent: true, opacity: 0.85, depthTest: false }));
ghost.frustumCulled = false;
ghost.renderOrder = 2;
scene3.add(ghost);
const velArrow = new THREE.ArrowHelper(new THREE.Vector3(1, 0, 0), new THREE.Vector3(), 0.2, 0xffd24d);
velArrow.visible = false;
scene3.add(velArrow);
const cursorMark = new THREE.AxesHelper(1);
cursorMark.visible = false;
cursorMark.renderOrder = 3;
cursorMark.material.depthTest = false;
scene3.add(cursorMark);

export const pivot = new THREE.Object3D();
scene3.add(pivot);
export const gizmo = new TransformControls(camera, canvas);
gizmo.setSize(0.9);
scene3.add(gizmo.getHelper ? gizmo.getHelper() : gizmo);
gizmo.addEventListener('change', redraw);

let internal = false;          // our own calls into the gizmo (axis switches, cancel)
let releaseT = null;           // when the pointer was released (latency)
let lastPointer = null, downPointer = null;
let held = false;               // a mouse button is down (orbiting stays off until it is up)
canvas.addEventListener('pointerdown', (e) => { downPointer = e; lastPointer = e; held = true; }, true);
canvas.addEventListener('pointermove', (e) => { lastPointer = e; }, true);
window.addEventListener('pointerup', () => {
  held = false;
  if (S.dragging) releaseT = performance.now();
  else controls.enabled = S.tool === 'orbit';
}, true);
canvas.addEventListener('contextmenu', (e) => {
  e.preventDefault();
  if (S.dragging) cancelDrag();
  else if (e.shiftKey) placeCursor(e);
});

gizmo.addEventListener('dragging-changed', (e) => {
  if (internal) return;
  controls.enabled = !e.value && !held && S.tool === 'orbit';
  if (e.value) beginDrag();
  else if (S.xform && S.xform.cancelled) endCancel();
  else commitDrag();
});
gizmo.addEventListener('objectChange', () => {
  if (!S.dragging || internal || (S.xform && S.xform.cancelled)) return;
  constrain();
  dragPose();
});

// ------------------------------------------------------------------------------------------
// keyframe targets as rigid transforms

// A keyframe's position as a rigid transform {rotation (deg, extrinsic XYZ), translation, center}.
export function rigidOf(k) {
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
function rotationOf(rg) {
  return new THREE.Matrix4().makeRotationFromEuler(new THREE.Euler(rg.rotation[0] * D2R, rg.rotation[1] * D2R, rg.rotation[2] * D2R, 'ZYX'));
}
export function rigidMatrix(rg) {   // x = R (X - c) + c + t, R = Rz Ry Rx (three.js Euler order 'ZYX')
  const c = new THREE.Vector3(...rg.center), t = new THREE.Vector3(...rg.translation);
  return new THREE.Matrix4().makeTranslation(c.x + t.x, c.y + t.y, c.z + t.z).multiply(rotationOf(rg)).multiply(new THREE.Matrix4().makeTranslation(-c.x, -c.y, -c.z));
}
// The same transform about another centre: t' = t + (R - I)(c' - c).
export function recentered(rg, center) {
  const d = new THREE.Vector3(...center).sub(new THREE.Vector3(...rg.center));
  const t = new THREE.Vector3(...rg.translation).add(d.clone().applyMatrix4(rotationOf(rg))).sub(d);
  return { rotation: [...rg.rotation], translation: t.toArray(), center: [...center] };
}
// The centre (in rest coordinates) of a group's transform `rg` for the pivot choice
// (S.view.pivot): the group's centroid or the centre of its bounds (so the gizmo sits on the
// target's), or the rest point that `rg` carries to the 3D cursor (so the gizmo sits on it).
export function pivotCenter(group, rg) {
  if (S.view.pivot === 'cursor' && S.cursor) return S.cursor.clone().applyMatrix4(rigidMatrix(rg).invert());
  if (S.view.pivot === 'bounds') return boundsOf(S.groupVerts[group] || []).getCenter(new THREE.Vector3());
  return groupCentroid(group);
}

// ------------------------------------------------------------------------------------------
// The velocity arrow's tip while posing a velocity (Frame keeps it in view), else null.
export function velocityTip() {
  return S.posing && S.posing.mode === 'velocity' ? pivot.position.clone() : null;
}

// ghost of the target and velocity arrow

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
  redraw();
  const c = new THREE.Vector3(); for (let j = 0; j < idx.length; j++) c.x += arr[3 * j], c.y += arr[3 * j + 1], c.z += arr[3 * j + 2];
  S.velBase = c.divideScalar(Math.max(idx.length, 1));
  showVelocity(k.velocity);
}
export function ghostPoints() { return ghost.visible ? ghostGeom.getAttribute('position') : null; }
function showVelocity(v) {
  const vel = new THREE.Vector3(...(v || [0, 0, 0])), len = vel.length() * VEL_SCALE;
  velArrow.position.copy(S.velBase);
  velArrow.visible = !!v && len > 1e-6;
  if (velArrow.visible) { velArrow.setDirection(vel.normalize()); velArrow.setLength(len, Math.min(0.04, 0.4 * len), Math.min(0.025, 0.25 * len)); }
  redraw();
}
export function updatePoseHelpers() {
  const k = currentKey();
  redraw();
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
  const k = currentKey();
  if (k && S.posing) {
    const want = pivotCenter(k.group, rg).toArray();
    if (want.some((x, i) => Math.abs(x - rg.center[i]) > 1e-9)) rg = recentered(rg, want);
  }
  const c = new THREE.Vector3(...rg.center), t = new THREE.Vector3(...rg.translation);
  pivot.position.copy(c).add(t);
  pivot.quaternion.setFromEuler(new THREE.Euler(rg.rotation[0] * D2R, rg.rotation[1] * D2R, rg.rotation[2] * D2R, 'ZYX'));
  pivot.updateMatrixWorld();
  S.posing.center = rg.center;
}

// ------------------------------------------------------------------------------------------
// posing

export function startPosing(mode) {
  const k = currentKey();
  if (!k) { toast('select a keyframe first', true); return; }
  if (S.dragging) return;
  setPlaying(false);
  if (mode === 'velocity') {
    S.posing = { id: k.id, mode };
    setTime(k.time);
    setGhost(k, rigidOf(k));
    const v = new THREE.Vector3(...(k.velocity || [0, 0, 0]));
    pivot.position.copy(S.velBase).addScaledVector(v, VEL_SCALE);
    pivot.quaternion.identity();
    pivot.updateMatrixWorld();
    gizmo.setMode('translate');
    gizmo.setSpace('world');
    gizmo.attach(pivot);
    hooks.renderKeyPanel();
    return;
  }
  const rg = rigidOf(k);
  if (!rg) { toast('absolute targets cannot be posed with the gizmo; press Rest to start from the rest pose', true); return; }
  S.posing = { id: k.id, mode, center: rg.center };
  setTime(k.time);
  placePivot(rg);
  gizmo.setMode(mode);
  gizmo.setSpace(mode === 'rotate' ? 'local' : 'world');
  gizmo.attach(pivot);
  hooks.renderKeyPanel();
}
export function stopPosing() {
  if (S.dragging) cancelDrag();
  S.posing = null;
  gizmo.detach();
  redraw();
}
function velocityTarget() {
  const r4 = (x) => Math.round(x * 1e4) / 1e4;
  return pivot.position.clone().sub(S.velBase).divideScalar(VEL_SCALE).toArray().map(r4);
}
function poseOp(k) {
  return S.posing.mode === 'velocity' ? { op: 'update_keyframe', id: k.id, velocity: velocityTarget() }
    : { op: 'update_keyframe', id: k.id, position: poseTarget() };
}
export function poseTarget() {
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
// A new pivot choice: the gizmo of the selected keyframe moves there; the next drag commits the
// target about it (the same pose: only its centre changes).
export function applyPivot() {
  if (!S.dragging) updatePoseHelpers();
}
function placeCursor(e) {
  const r = canvas.getBoundingClientRect();
  const ray = new THREE.Raycaster();
  ray.setFromCamera(new THREE.Vector2((e.clientX - r.left) / r.width * 2 - 1, -((e.clientY - r.top) / r.height) * 2 + 1), camera);
  const hit = ray.intersectObject(body, false)[0];
  if (!hit) return;
  setCursor(hit.point);
}
export function setCursor(p) {
  S.cursor = p ? new THREE.Vector3().copy(p) : null;
  cursorMark.visible = !!p;
  if (p) {
    cursorMark.position.copy(p);
    const size = body.geometry.boundingSphere ? body.geometry.boundingSphere.radius : 1;
    cursorMark.scale.setScalar(0.12 * size);
  }
  $('cursor-readout').textContent = p ? `[${[p.x, p.y, p.z].map((x) => x.toFixed(3)).join(', ')}]` : 'none';
  if (S.view.pivot === 'cursor') applyPivot();
  redraw();
}

// ------------------------------------------------------------------------------------------
// the drag: constraints, typed values, snapping, cancel, commit

function beginDrag() {
  S.dragging = true;
  S.release = null;  // a new drag: stop measuring the previous release
  S.xform = { mode: S.posing && S.posing.mode === 'rotate' ? 'rotate' : 'translate', axis: gizmo.axis, typed: '', cancelled: false,
    velocity: !!S.posing && S.posing.mode === 'velocity',
    startPos: pivot.position.clone(), startQuat: pivot.quaternion.clone(),
    down: downPointer, invert: !!(downPointer && downPointer.ctrlKey) };
  applySnap();
  showHud();
}
function snapping() { return S.view.snap !== !!(S.xform && S.xform.invert); }
function applySnap() {
  gizmo.setRotationSnap(snapping() && S.xform && S.xform.mode === 'rotate' ? S.view.snapTurn * D2R : null);
}
// The drag's pose after typed values and snapping (TransformControls moved the pivot).
function constrain() {
  const x = S.xform;
  if (!x) return;
  const axis = (x.axis || '').replace(/[^XYZ]/g, '');
  const unit = x.velocity ? VEL_SCALE : 1;   // velocity: values in m/s, the arrow v * VEL_SCALE
  if (x.typed !== '' && axis) {
    const v = parseFloat(x.typed);
    const value = Number.isFinite(v) ? v : 0;
    const dir = AXES[axis[0]];
    if (x.mode === 'rotate') {
      pivot.position.copy(x.startPos);
      pivot.quaternion.copy(x.startQuat).multiply(new THREE.Quaternion().setFromAxisAngle(dir, value * D2R));
    } else {
      pivot.quaternion.copy(x.startQuat);
      pivot.position.copy(x.startPos).addScaledVector(dir, value * unit);
    }
  } else if (snapping() && x.mode === 'translate') {
    const step = S.view.snapMove * unit;
    const d = pivot.position.clone().sub(x.startPos);
    for (const a of 'XYZ') {
      const c = a.toLowerCase();
      if (axis.includes(a)) d[c] = Math.round(d[c] / step) * step;
    }
    pivot.position.copy(x.startPos).add(d);
  }
  pivot.updateMatrixWorld();
  showHud();
}
function showHud() {
  const x = S.xform;
  if (!x) { $('hud').textContent = ''; return; }
  const axis = (x.axis || '').replace(/[^XYZ]/g, '') || 'free';
  const unit = x.mode === 'rotate' ? '°' : x.velocity ? ' m/s' : ' m';
  let now = '';
  if (x.mode === 'rotate') {
    const dq = x.startQuat.clone().invert().multiply(pivot.quaternion);
    now = `${(2 * Math.acos(Math.min(1, Math.abs(dq.w))) / D2R).toFixed(2)}°`;
  } else {
    const d = pivot.position.clone().sub(x.startPos).divideScalar(x.velocity ? VEL_SCALE : 1);
    now = `[${d.toArray().map((v) => v.toFixed(4)).join(', ')}]${unit}`;
  }
  $('hud').textContent = `${x.mode === 'rotate' ? 'rotate' : x.velocity ? 'velocity' : 'move'} · axis ${axis}${snapping() ? ' · snapping' : ''}` +
    (x.typed !== '' ? ` · typed ${x.typed}${unit} (Enter applies)` : ` · ${now}`) + '\nX/Y/Z axis · type a value · Ctrl snap · Esc cancel';
  redraw();
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
// A pointer event as TransformControls takes it: normalized device coordinates.
function pointerOf(e) {
  const r = canvas.getBoundingClientRect();
  return { x: (e.clientX - r.left) / r.width * 2 - 1, y: -(e.clientY - r.top) / r.height * 2 + 1, button: e.button };
}
// Constrain the running drag to one axis, from where it started (Blender's X, Y, Z).
function switchAxis(letter) {
  const x = S.xform;
  if (!x || !x.down) return;
  internal = true;
  try {
    gizmo.reset();
    pivot.position.copy(x.startPos); pivot.quaternion.copy(x.startQuat); pivot.updateMatrixWorld();
    gizmo.dragging = false;
    gizmo.axis = letter;
    gizmo.getHelper().updateMatrixWorld(true);
    gizmo.pointerDown({ ...pointerOf(x.down), button: 0 });
    x.axis = letter;
  } finally { internal = false; }
  if (lastPointer) gizmo.pointerMove({ ...pointerOf(lastPointer), button: -1 });  // -> objectChange
  else { constrain(); dragPose(); }
}
function typeKey(key) {
  const x = S.xform;
  if (key === 'Backspace') x.typed = x.typed.slice(0, -1);
  else if (key === '-') x.typed = x.typed.startsWith('-') ? x.typed.slice(1) : '-' + x.typed;
  else x.typed += key;
  if (!(x.axis || '').replace(/[^XYZ]/g, '')) x.axis = 'X';
  constrain();
  dragPose();
}
// Esc, a right click, or the keyframe deleted elsewhere: the drag leaves nothing behind.
export function cancelDrag() {
  const x = S.xform;
  if (!S.dragging || !x) return;
  x.cancelled = true;
  internal = true;
  try {
    gizmo.reset();
    pivot.position.copy(x.startPos); pivot.quaternion.copy(x.startQuat); pivot.updateMatrixWorld();
  } finally { internal = false; }
  gizmo.pointerUp(null);   // ends TransformControls' drag: dragging-changed -> endCancel
}
function endCancel() {
  S.dragging = false;
  S.xform = null;
  S.previewPending = null;
  S.committing = null;
  S.release = null;
  releaseT = null;
  showHud();
  updatePoseHelpers();
  setStatus('drag cancelled', '');
  act(() => api.post('/api/preview/cancel'));
  flushState();
}
function finishDrag() {
  const x = S.xform;
  x.commit = true;
  gizmo.pointerUp(null);   // dragging-changed -> commitDrag
}
async function commitDrag() {
  S.dragging = false;
  S.xform = null;
  showHud();
  const k = currentKey();
  const t0 = releaseT ?? performance.now();
  releaseT = null;
  S.previewPending = null;
  if (!k || !S.posing) { flushState(); return; }
  const base = S.desc.version;
  S.committing = { base, t: t0 };
  S.release = { t: t0, base };
  const rel = S.release;
  const r = await edit(poseOp(k));
  rel.posted = performance.now() - t0;
  if (!r || !r.changed) {       // nothing to commit: the drag's previews must go
    if (S.release === rel) S.release = null;
    S.committing = null;
    if (r) act(() => api.post('/api/preview/cancel'));
    flushState();
  }
}

// Keys during a drag (before every other shortcut); true if used.
export function dragKey(e) {
  if (!S.dragging || !S.xform) return false;
  const key = e.key;
  if (key === 'Escape') { cancelDrag(); return true; }
  if (key === 'Enter') { finishDrag(); return true; }
  if (key === 'Control') {   // held: snapping inverted until it is released (not per repeat)
    if (!e.repeat) { S.xform.invert = !S.xform.invert; applySnap(); constrain(); dragPose(); }
    return true;
  }
  if (/^[xyzXYZ]$/.test(key)) { switchAxis(key.toUpperCase()); return true; }
  if (/^[0-9.]$/.test(key) || key === '-' || key === 'Backspace') { typeKey(key); return true; }
  return true;  // nothing else while dragging
}
export function dragKeyUp(e) {
  if (S.dragging && S.xform && e.key === 'Control') { S.xform.invert = !S.xform.invert; applySnap(); constrain(); dragPose(); }
}
// Screen point of the gizmo and the direction of an axis (tests).
export function gizmoHandle(axis) {
  const r = canvas.getBoundingClientRect();
  const p = pivot.position.clone();
  const dir = AXES[axis] ? AXES[axis].toArray() : [0, 0, 0];
  const len = camera.position.distanceTo(p) * 0.05;
  const q = p.clone().add(new THREE.Vector3(...dir).multiplyScalar(len)).project(camera);
  const o = p.clone().project(camera);
  const ox = r.left + (o.x + 1) / 2 * r.width, oy = r.top + (1 - o.y) / 2 * r.height;
  const dx = r.left + (q.x + 1) / 2 * r.width - ox, dy = r.top + (1 - q.y) / 2 * r.height - oy;
  const n = Math.hypot(dx, dy) || 1;
  return { x: ox, y: oy, dx: dx / n, dy: dy / n, axis: gizmo.axis };
}
// Screen points on the rotate gizmo's ring about an axis (tests).
export function gizmoRing(axis) {
  const r = canvas.getBoundingClientRect();
  const p = pivot.position.clone();
  const factor = p.distanceTo(camera.position) * Math.min(1.9 * Math.tan(Math.PI * camera.fov / 360) / camera.zoom, 7);
  const R = 0.5 * factor * gizmo.size / 4;   // the rings have radius 0.5 in gizmo units
  const [u, v] = { X: ['Y', 'Z'], Y: ['Z', 'X'], Z: ['X', 'Y'] }[axis].map((a) => AXES[a].clone().applyQuaternion(pivot.quaternion));
  const out = [];
  for (let k = 0; k < 24; k++) {
    const th = (k + 0.5) / 24 * 2 * Math.PI;
    const q = p.clone().addScaledVector(u, R * Math.cos(th)).addScaledVector(v, R * Math.sin(th)).project(camera);
    out.push({ x: r.left + (q.x + 1) / 2 * r.width, y: r.top + (1 - q.y) / 2 * r.height });
  }
  return { points: out, axis: gizmo.axis };
}
export function restPose(k) { edit({ op: 'update_keyframe', id: k.id, position: 'rest' }); }

// The driver of a [drive] scene (secondary motion on an existing animation): a ghost of the
// driver's pose at the current time (what the driven groups follow, and where the free parts
// would be without physics), the driven groups in their colour, and the driven frames as
// ticks on the group's row of the dope sheet.  D toggles the ghost.
import * as THREE from 'three';
import { S, geometry, scene3, scene, redraw, setStatus, hooks } from './core.js';

const GHOST = new THREE.Color(0.93, 0.95, 1.0);
const ghostGeom = new THREE.BufferGeometry();
// unlit, see-through, drawn after the body without writing depth: the body shows where it
// and the driver coincide, the ghost where the body lags or overshoots
const ghost = new THREE.Mesh(ghostGeom, new THREE.MeshBasicMaterial({
  color: GHOST, transparent: true, opacity: 0.3, depthWrite: false, side: THREE.FrontSide,
  polygonOffset: true, polygonOffsetFactor: 1, polygonOffsetUnits: 4 }));
ghost.frustumCulled = false;
ghost.renderOrder = 1;
const group = new THREE.Group();
group.add(ghost);
group.visible = false;
scene3.add(group);

let loadedKey = null, loading = null;

// The drive spec this tab shows (null without [drive]); a new one reloads the driver.
function driveKey() {
  const sc = scene();
  if (!sc || !sc.drive) return null;
  return JSON.stringify([S.meshKey, sc.drive, sc.time_range, S.desc.driver_stamp]);
}

// Fetch the driver's keyed frames when the scene's [drive] changed (called on every state).
export async function syncDriver() {
  const key = driveKey();
  if (key === loadedKey) return;
  loadedKey = key;
  S.driver = null;
  group.visible = false;
  if (key === null) { hooks.drawDopesheet(); redraw(); return; }
  const mine = loading = fetch('/api/driver');
  try {
    const res = await mine;
    if (loading !== mine) return;  // a newer [drive] is loading
    if (!res.ok) {
      let msg = `${res.status}`;
      try { msg = (await res.json()).error || msg; } catch { /* not JSON */ }
      setStatus(`driver: ${msg}`, 'err');
      return;
    }
    const meta = JSON.parse(res.headers.get('X-Wiggly-Driver'));
    const data = new Float32Array(await res.arrayBuffer());
    if (loading !== mine || meta.n_vertices !== S.n) return;
    S.driver = { meta, data };
    const pos = new THREE.BufferAttribute(new Float32Array(S.n * 3), 3);
    ghostGeom.setIndex(geometry.getIndex());
    ghostGeom.setAttribute('position', pos);
    updateDriverGhost();
    hooks.drawDopesheet();
  } catch (err) {
    if (loading === mine) setStatus(`driver: ${err.message}`, 'err');
  }
}

// The driver's pose at shot time t: linear between its keyed frames; before the first and
// after the last, the pose the motion holds there (a loop's join of its ends is not drawn).
export function driverPose(t = S.t) {
  const d = S.driver;
  if (!d) return null;
  const times = d.meta.times, F = times.length, n3 = S.n * 3;
  if (t < times[0] - 1e-9 || t > times[F - 1] + 1e-9) {
    const sc = scene();
    if (sc && sc.time.loop) return null;
    return d.data.subarray(t < times[0] ? 0 : (F - 1) * n3, t < times[0] ? n3 : F * n3);
  }
  let i = 0;
  while (i < F - 2 && times[i + 1] <= t) i++;
  const a = d.data.subarray(i * n3, (i + 1) * n3);
  if (F === 1 || t <= times[i]) return a;
  const b = d.data.subarray((i + 1) * n3, (i + 2) * n3);
  const w = Math.min(1, Math.max(0, (t - times[i]) / (times[i + 1] - times[i])));
  const out = new Float32Array(n3);
  for (let j = 0; j < n3; j++) out[j] = a[j] + (b[j] - a[j]) * w;
  return out;
}

// Move the ghost to the current time (called at every time change).
export function updateDriverGhost() {
  const pose = S.view.driver ? driverPose() : null;
  const show = pose !== null && ghostGeom.getAttribute('position') !== undefined;
  if (show) {
    const pos = ghostGeom.getAttribute('position');
    pos.array.set(pose);
    pos.needsUpdate = true;
  }
  if (group.visible !== show || show) redraw();
  group.visible = show;
}

// Test hooks: what the ghost shows (the driven groups as the server names them, as the dope
// sheet draws them).
export function driverInfo() {
  const pos = ghostGeom.getAttribute('position');
  return { loaded: !!S.driver, visible: group.visible, times: S.driver ? S.driver.meta.times : [],
    groups: S.driver ? S.driver.meta.groups : [],
    positions: group.visible && pos ? Array.from(pos.array) : null };
}

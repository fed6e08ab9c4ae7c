// Views as in Blender: numpad 1 front, 3 right side, 7 top (Ctrl or Shift: the opposite side;
// the digit keys work too), F or numpad . frames the selection (selected vertices, else the selected
// groups, else the keyframe's target, else the whole body).  y is up, the front looks along -z.
import * as THREE from 'three';
import { S, camera, controls, geometry, boundsOf, redraw } from './core.js';
import { ghostPoints, velocityTip } from './posing.js';

const DIRS = { front: [0, 0, 1], back: [0, 0, -1], right: [1, 0, 0], left: [-1, 0, 0], top: [0, 1, 0], bottom: [0, -1, 0] };

// Look at the target from one side, at the same distance.
export function viewFrom(side) {
  const d = new THREE.Vector3(...DIRS[side]);
  if (Math.abs(d.y) > 0.5) d.z += 1e-4;   // straight down: keep the orbit's up vector defined
  const dist = camera.position.distanceTo(controls.target);
  camera.position.copy(controls.target).addScaledVector(d.normalize(), dist);
  camera.lookAt(controls.target);
  controls.update();
  S.view.side = side;
  redraw();
}

function selectionBounds() {
  const idx = [];
  for (let i = 0; i < S.n; i++) if (S.selection[i]) idx.push(i);
  const pos = geometry.getAttribute('position').array;
  if (idx.length) return boundsOf(idx, pos);
  const names = new Set(S.groups);
  if (S.selectedGroup) names.add(S.selectedGroup);
  for (const g of names) for (const i of S.groupVerts[g] || []) idx.push(i);
  if (idx.length) return boundsOf(idx, pos);
  const ghost = ghostPoints();
  if (ghost) return new THREE.Box3().setFromBufferAttribute(ghost);
  return geometry.boundingBox ? new THREE.Box3().setFromBufferAttribute(geometry.getAttribute('position')) : null;
}
// Centre the selection and fit it in the view (the direction stays).
export function frameSelected() {
  const box = selectionBounds();
  if (!box || box.isEmpty()) return;
  const tip = velocityTip();
  if (tip) box.expandByPoint(tip);  // the arrow being posed stays in view
  const sphere = box.getBoundingSphere(new THREE.Sphere());
  const r = Math.max(sphere.radius, 1e-3 * (geometry.boundingSphere ? geometry.boundingSphere.radius : 1));
  const dir = camera.position.clone().sub(controls.target).normalize();
  const fov = THREE.MathUtils.degToRad(camera.fov) / 2;
  const dist = r / Math.sin(Math.min(fov, fov * camera.aspect)) * 1.15;
  controls.target.copy(sphere.center);
  camera.position.copy(sphere.center).addScaledVector(dir, dist);
  camera.near = Math.max(dist / 1000, 1e-4);
  camera.updateProjectionMatrix();
  controls.update();
  redraw();
}

// Keys of the view (true if used).
export function viewKey(e) {
  const code = e.code || '';
  const digit = code.startsWith('Numpad') ? code.slice(6) : /^Digit[137]$/.test(code) ? code.slice(5) : null;
  const other = e.ctrlKey || e.shiftKey;
  if (digit === '1') { viewFrom(other ? 'back' : 'front'); return true; }
  if (digit === '3') { viewFrom(other ? 'left' : 'right'); return true; }
  if (digit === '7') { viewFrom(other ? 'bottom' : 'top'); return true; }
  if (code === 'NumpadDecimal' || (!e.ctrlKey && !e.altKey && (e.key === 'f' || e.key === 'F'))) { frameSelected(); return true; }
  return false;
}

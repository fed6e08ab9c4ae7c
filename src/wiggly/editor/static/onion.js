// Onion skins (O): ghosts of the body at earlier frames (warm) and later frames (cool), every
// `onionStep` frames, `onionCount` on each side, fading with distance; they follow playback and
// show where the body is not (the body hides them).  Like Blender's motion paths for bones,
// they ghost only the selected groups (the faces touching their vertices) when groups are
// selected, and the whole body when none is.  Motion paths (P): the path of each
// selected group's centroid over the shot, a dot per frame, a larger dot per keyframe of the
// group, the current frame ringed.
import * as THREE from 'three';
import { S, geometry, scene3, scene, groupColor } from './core.js';
import { frameIndex, framePositions } from './playback.js';

const PAST = new THREE.Color(1.0, 0.45, 0.25), FUTURE = new THREE.Color(0.3, 0.75, 1.0);
const MAX_SKINS = 8;   // per side
const skins = [];      // {mesh, frame, framesId}
const onion = new THREE.Group();
onion.visible = false;
scene3.add(onion);

function skin() {
  const g = new THREE.BufferGeometry();
  // unlit and front faces only: ghosts are read by their outline; pushed back a little so
  // that where a ghost and the body coincide, the body shows
  const m = new THREE.MeshBasicMaterial({ side: THREE.FrontSide, transparent: true, depthWrite: false,
    polygonOffset: true, polygonOffsetFactor: 1, polygonOffsetUnits: 4 });
  const mesh = new THREE.Mesh(g, m);
  mesh.frustumCulled = false;
  mesh.renderOrder = 1;
  onion.add(mesh);
  return mesh;
}

// The selected groups (the active one and the others picked with it), drawn in the paths and
// ghosted by the onion skins.
export function selectedGroups() {
  const names = new Set(S.groups);
  if (S.selectedGroup) names.add(S.selectedGroup);
  return [...names].filter((g) => S.groupVerts[g] && S.groupVerts[g].length);
}

// The faces the skins draw: the body's, or those touching a selected group's vertices.
let ghostIndex = { key: null, index: null };
function ghostFaces() {
  const body = geometry.getIndex();
  const names = selectedGroups().sort();
  if (!names.length || !body) return body;
  const key = JSON.stringify([S.meshKey, names, names.map((g) => S.groupVerts[g].length)]);
  if (ghostIndex.key === key && ghostIndex.index) return ghostIndex.index;
  const mark = new Uint8Array(S.n);
  for (const g of names) for (const i of S.groupVerts[g]) mark[i] = 1;
  const faces = body.array, out = [];
  for (let f = 0; f < faces.length; f += 3) {
    if (mark[faces[f]] || mark[faces[f + 1]] || mark[faces[f + 2]]) out.push(faces[f], faces[f + 1], faces[f + 2]);
  }
  ghostIndex = { key, index: new THREE.BufferAttribute(new Uint32Array(out), 1) };
  return ghostIndex.index;
}

// Rebuild the skins' geometry (a new mesh, the count or the selected groups changed).
function ensureSkins() {
  const want = 2 * Math.min(S.view.onionCount, MAX_SKINS);
  const index = ghostFaces();
  while (skins.length < want) skins.push({ mesh: skin() });
  skins.forEach((s, j) => {
    const g = s.mesh.geometry;
    if (g.getIndex() !== index) g.setIndex(index);
    const pos = g.getAttribute('position');
    if (!pos || pos.count !== S.n) g.setAttribute('position', new THREE.BufferAttribute(new Float32Array(S.n * 3), 3));
    s.mesh.visible = j < want;
  });
}

// Move the skins to the frames around the current time (called at every time change).
export function updateOnion() {
  const on = S.view.onion && S.frames && S.n > 0;
  onion.visible = !!on;
  if (!on) return;
  ensureSkins();
  const i = frameIndex(), n = Math.min(S.view.onionCount, MAX_SKINS), step = Math.max(1, S.view.onionStep);
  const F = S.frames.meta.n_frames;
  for (let j = 0; j < 2 * n; j++) {
    const side = j < n ? -1 : 1, d = (j % n) + 1;
    const f = i + side * d * step;
    const s = skins[j];
    if (f < 0 || f >= F) { s.mesh.visible = false; continue; }
    s.mesh.visible = true;
    const g = s.mesh.geometry;
    const pos = g.getAttribute('position');
    if (s.frame !== f || s.framesId !== S.frames.meta.id) {
      pos.array.set(framePositions(f));
      pos.needsUpdate = true;
      s.frame = f; s.framesId = S.frames.meta.id;
    }
    const m = s.mesh.material;
    m.color.copy(side < 0 ? PAST : FUTURE);
    m.opacity = 0.42 * (1 - (d - 1) / (n + 0.5));
  }
}

// ------------------------------------------------------------------------------------------
// motion paths

const paths = new THREE.Group();
paths.renderOrder = 3;
scene3.add(paths);
const marker = new THREE.Mesh(new THREE.RingGeometry(0.7, 1.0, 24), new THREE.MeshBasicMaterial({ color: 0xffffff, depthTest: false, side: THREE.DoubleSide }));
marker.renderOrder = 4;
let pathData = [];     // {name, points: Float32Array F*3}

function clearPaths() {
  for (const c of [...paths.children]) { paths.remove(c); if (c.geometry) c.geometry.dispose(); }
  pathData = [];
}
// Recompute the paths (new frames, another selection).
export function updatePaths() {
  clearPaths();
  if (!S.view.paths || !S.frames || !scene()) { paths.visible = false; return; }
  paths.visible = true;
  const F = S.frames.meta.n_frames, data = S.frames.data, n3 = S.n * 3;
  const size = geometry.boundingSphere ? geometry.boundingSphere.radius : 1;
  for (const name of selectedGroups()) {
    const idx = S.groupVerts[name], pts = new Float32Array(F * 3);
    for (let f = 0; f < F; f++) {
      let x = 0, y = 0, z = 0;
      const o = f * n3;
      for (const i of idx) { x += data[o + 3 * i]; y += data[o + 3 * i + 1]; z += data[o + 3 * i + 2]; }
      pts[3 * f] = x / idx.length; pts[3 * f + 1] = y / idx.length; pts[3 * f + 2] = z / idx.length;
    }
    const color = new THREE.Color(groupColor(name));
    const g = new THREE.BufferGeometry();
    g.setAttribute('position', new THREE.BufferAttribute(pts, 3));
    const line = new THREE.Line(g, new THREE.LineBasicMaterial({ color, depthTest: false, transparent: true, opacity: 0.9 }));
    const dots = new THREE.Points(g, new THREE.PointsMaterial({ color, size: 3, sizeAttenuation: false, depthTest: false }));
    const keyPts = [];
    for (const k of scene().keyframes) {
      if (k.group !== name) continue;
      const f = Math.min(Math.max(Math.round((k.time - S.frames.meta.start) * S.frames.meta.fps), 0), F - 1);
      keyPts.push(pts[3 * f], pts[3 * f + 1], pts[3 * f + 2]);
    }
    const kg = new THREE.BufferGeometry();
    kg.setAttribute('position', new THREE.BufferAttribute(new Float32Array(keyPts), 3));
    const keys = new THREE.Points(kg, new THREE.PointsMaterial({ color: 0xffffff, size: 8, sizeAttenuation: false, depthTest: false }));
    for (const o of [line, dots, keys]) { o.frustumCulled = false; o.renderOrder = 3; paths.add(o); }
    pathData.push({ name, points: pts });
  }
  marker.scale.setScalar(0.025 * size);
  paths.add(marker);
  updatePathMarker();
}
export function updatePathMarker() {
  if (!paths.visible || !pathData.length) { marker.visible = false; return; }
  const f = frameIndex();
  const p = pathData[0].points;
  marker.visible = f >= 0;
  if (f >= 0) marker.position.set(p[3 * f], p[3 * f + 1], p[3 * f + 2]);
}
export function faceCamera(camera) { marker.quaternion.copy(camera.quaternion); }
// The path of a group (tests): centroids per frame.
export function pathOf(name) { const p = pathData.find((d) => d.name === name); return p ? Array.from(p.points) : null; }
// The onion skins (tests): the frame each shows, its side, opacity, vertex 0 and the vertices
// of the faces it draws.
export function onionInfo() {
  return skins.filter((s) => onion.visible && s.mesh.visible).map((s) => ({ frame: s.frame,
    opacity: s.mesh.material.opacity, past: s.mesh.material.color.equals(PAST),
    vertex0: Array.from(s.mesh.geometry.getAttribute('position').array.slice(0, 3)),
    vertices: [...new Set(s.mesh.geometry.getIndex().array)].sort((a, b) => a - b) }));
}

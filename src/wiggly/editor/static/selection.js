// Selecting vertices: brush (B), box (X), lasso (L); Shift adds, Alt removes.  Box and lasso
// take only the vertices one can see, as in Blender, unless X-ray is on (Alt+Z): a depth pass
// of the body (view-space depth per pixel) tells which vertices are hidden behind the surface.
import * as THREE from 'three';
import { $, S, body, camera, canvas, controls, geometry, renderer, redraw } from './core.js';
import { updateColors } from './playback.js';

// ------------------------------------------------------------------------------------------
// visibility: a depth pass of the body (1 / view-space depth per pixel, in a float target)

const depthMaterial = new THREE.ShaderMaterial({
  side: THREE.DoubleSide,
  vertexShader: `varying float vDepth;
    void main() { vec4 p = modelViewMatrix * vec4(position, 1.0); vDepth = -p.z; gl_Position = projectionMatrix * p; }`,
  fragmentShader: `varying float vDepth;
    void main() { gl_FragColor = vec4(1.0 / vDepth, 0.0, 0.0, 1.0); }`,
});
const depthScene = new THREE.Scene();
const depthBody = new THREE.Mesh(geometry, depthMaterial);
depthBody.frustumCulled = false;
depthScene.add(depthBody);
let depthTarget = null;

// Whether each vertex in `indices` is visible (not behind the surface), from a depth pass over
// the page rectangle [x0, x1] x [y0, y1] (CSS pixels of the canvas).
function visibleAmong(indices, sp, x0, y0, x1, y1) {
  const ratio = renderer.getPixelRatio();
  const W = renderer.domElement.width, H = renderer.domElement.height;
  if (!depthTarget || depthTarget.width !== W || depthTarget.height !== H) {
    if (depthTarget) depthTarget.dispose();
    depthTarget = new THREE.WebGLRenderTarget(W, H, { type: THREE.FloatType, format: THREE.RGBAFormat,
      minFilter: THREE.NearestFilter, magFilter: THREE.NearestFilter, depthBuffer: true });
  }
  const px0 = Math.max(0, Math.floor(x0 * ratio) - 2), px1 = Math.min(W - 1, Math.ceil(x1 * ratio) + 2);
  const py0 = Math.max(0, Math.floor(y0 * ratio) - 2), py1 = Math.min(H - 1, Math.ceil(y1 * ratio) + 2);
  const w = px1 - px0 + 1, h = py1 - py0 + 1;
  const out = new Uint8Array(indices.length).fill(1);
  if (w <= 0 || h <= 0) return out;
  const clear = new THREE.Color(), alpha = renderer.getClearAlpha();
  renderer.getClearColor(clear);
  renderer.setRenderTarget(depthTarget);
  renderer.setClearColor(0x000000, 0);   // stored: 1 / depth, so the background is at infinity
  renderer.clear();
  renderer.render(depthScene, camera);
  const buf = new Float32Array(w * h * 4);
  renderer.readRenderTargetPixels(depthTarget, px0, H - 1 - py1, w, h, buf);  // rows bottom-up
  renderer.setRenderTarget(null);
  renderer.setClearColor(clear, alpha);
  const at = (px, py) => {   // depth at a device pixel (top-down), clamped into the read region
    const cx = Math.min(Math.max(px, px0), px1), cy = Math.min(Math.max(py, py0), py1);
    const inv = buf[4 * ((py1 - cy) * w + (cx - px0))];
    return inv > 0 ? 1 / inv : Infinity;
  };
  const size = geometry.boundingSphere ? geometry.boundingSphere.radius : 1;
  const tol = 0.01 * size;
  const v = new THREE.Vector3();
  const pos = geometry.getAttribute('position').array;
  camera.updateMatrixWorld();
  indices.forEach((i, j) => {
    const depth = -v.set(pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]).applyMatrix4(camera.matrixWorldInverse).z;
    // the surface drawn at the vertex's pixel is the vertex's own (visible), or nearer
    // (hidden).  On a silhouette the pixel may show the background: then the nearest surface
    // around it decides.  A surface seen at a grazing angle changes depth fast across the
    // pixel: allow that change.
    const px = Math.floor(sp[3 * i] * ratio), py = Math.floor(sp[3 * i + 1] * ratio);
    let here = at(px, py);
    if (!Number.isFinite(here)) {
      for (let dy = -1; dy <= 1; dy++) for (let dx = -1; dx <= 1; dx++) here = Math.min(here, at(px + dx, py + dy));
    }
    let slope = 0;
    for (const [dx, dy] of [[1, 0], [-1, 0], [0, 1], [0, -1]]) {
      const d = at(px + dx, py + dy);
      if (Number.isFinite(d) && Number.isFinite(here)) slope = Math.max(slope, Math.abs(d - here));
    }
    out[j] = depth <= here + tol + slope ? 1 : 0;
  });
  return out;
}

// ------------------------------------------------------------------------------------------
// tools

export function setTool(tool) {
  S.tool = tool;
  for (const b of document.querySelectorAll('.tool')) b.classList.toggle('active', b.dataset.tool === tool);
  controls.enabled = tool === 'orbit' && !S.dragging;
  canvas.style.cursor = tool === 'orbit' ? '' : 'crosshair';
}
export function setXray(on) {
  S.view.xray = on;
  $('btn-xray').classList.toggle('active', on);
}
export function updateSelCount() {
  let n = 0; for (let i = 0; i < S.n; i++) n += S.selection[i];
  $('sel-count').textContent = `${n} vertices`;
  updateColors();
  return n;
}
export function selectedIndices() { const out = []; for (let i = 0; i < S.n; i++) if (S.selection[i]) out.push(i); return out; }
export function screenPositions() {
  const pos = geometry.getAttribute('position').array;
  const r = canvas.getBoundingClientRect();
  const v = new THREE.Vector3(), out = new Float32Array(S.n * 3);
  for (let i = 0; i < S.n; i++) {
    v.set(pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]).project(camera);
    out[3 * i] = (v.x + 1) / 2 * r.width; out[3 * i + 1] = (1 - v.y) / 2 * r.height; out[3 * i + 2] = v.z;
  }
  return out;
}
export function screenBox(indices) {  // page-space bounding box of some vertices (tests)
  const sp = screenPositions(), r = canvas.getBoundingClientRect();
  let x0 = 1e9, y0 = 1e9, x1 = -1e9, y1 = -1e9;
  for (const i of indices) { x0 = Math.min(x0, sp[3 * i]); x1 = Math.max(x1, sp[3 * i]); y0 = Math.min(y0, sp[3 * i + 1]); y1 = Math.max(y1, sp[3 * i + 1]); }
  return { x0: x0 + r.left, y0: y0 + r.top, x1: x1 + r.left, y1: y1 + r.top };
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
  let inside = [], bx0, by0, bx1, by1;
  if (S.tool === 'box' && d.x1 !== undefined) {
    [bx0, bx1] = [Math.min(d.x0, d.x1), Math.max(d.x0, d.x1)]; [by0, by1] = [Math.min(d.y0, d.y1), Math.max(d.y0, d.y1)];
    for (let i = 0; i < S.n; i++) {
      const x = sp[3 * i], y = sp[3 * i + 1];
      if (x >= bx0 && x <= bx1 && y >= by0 && y <= by1 && sp[3 * i + 2] < 1) inside.push(i);
    }
  } else if (S.tool === 'lasso' && d.pts.length > 2) {
    const xs = d.pts.map((p) => p[0]), ys = d.pts.map((p) => p[1]);
    [bx0, bx1, by0, by1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
    for (let i = 0; i < S.n; i++) if (sp[3 * i + 2] < 1 && pointInPolygon(sp[3 * i], sp[3 * i + 1], d.pts)) inside.push(i);
  }
  if (inside.length && !S.view.xray) {
    const vis = visibleAmong(inside, sp, bx0, by0, bx1, by1);
    inside = inside.filter((_, j) => vis[j]);
  }
  for (const i of inside) S.selection[i] = d.value;
  updateSelCount();
  redraw();
});

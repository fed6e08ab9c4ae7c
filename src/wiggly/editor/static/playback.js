// Loading the mesh, the state and the frames the server solves; time, playback (preview
// range, speed) and the body's colours.
import * as THREE from 'three';
import { $, S, api, hooks, geometry, scene, range, groupColor, setStatus, redraw, toast } from './core.js';

const BASE = new THREE.Color(0.70, 0.74, 0.80);
const SELECTED = new THREE.Color(1.0, 0.86, 0.25);
const FOLD = new THREE.Color(0.8, 0.0, 0.55);  // where the warped motion folds, as in previews
const KEY_WINDOW = 0.25;       // s: a keyframed group is highlighted this close to its key time
const STAGE_RANK = { linear: 0, warped: 1 };

// ------------------------------------------------------------------------------------------
// mesh and state

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
  colorsKey = null;
  S.frames = null;
  S.shown = { seq: -1, rank: -1, id: -1 };
  hooks.meshLoaded();
}

// A new server process (restarted): its sequence numbers start again, its mesh is reloaded.
function meetInstance(instance) {
  if (!instance || instance === S.instance) return false;
  S.instance = instance;
  S.shown = { seq: -1, rank: -1, id: -1 };
  framesWanted = null;
  S.committing = null;
  S.release = null;
  S.meshKey = null;
  return true;
}

let stateBusy = false, stateAgain = false;
export async function refreshState() {
  if (stateBusy) { stateAgain = true; return; }
  stateBusy = true;
  try {
    do {
      stateAgain = false;
      const d = await api.get('/api/state');
      meetInstance(d.instance);
      if (!d.open) { S.desc = d; setStatus('no scene open: Open… a scene or a mesh', ''); hooks.openDialog(); continue; }
      if (d.mesh_key !== S.meshKey) {
        S.meshKey = d.mesh_key;
        S.desc = d;
        await loadMesh();
        const late = S.lateFrames;
        S.lateFrames = null;
        if (late) offerFrames(late);
      }
      S.desc = d;
      S.groupVerts = {};
      for (const [name, idx] of Object.entries(d.groups)) S.groupVerts[name] = Int32Array.from(idx);
      if (S.selectedGroup && !(S.selectedGroup in d.scene.groups)) S.selectedGroup = null;
      for (const g of [...S.groups]) if (!(g in d.scene.groups)) S.groups.delete(g);
      const ids = new Set(d.scene.keyframes.map((k) => k.id));
      for (const id of [...S.keys]) if (!ids.has(id)) S.keys.delete(id);
      if (S.selectedKey !== null && !ids.has(S.selectedKey)) {
        // deleted elsewhere (another tab) while this one posed it: the move is dropped, said
        if (S.dragging) {
          const gone = 'the keyframe being posed was deleted in another tab: the move was not applied';
          toast(gone, true);
          setStatus(gone, 'err');
        }
        hooks.selectKey(null);
      }
      hooks.renderPanels();
      hooks.syncDriver();
      hooks.showNotices(d);
      if (d.group_error) setStatus(d.group_error, 'err');
    } while (stateAgain);
  } catch (err) { setStatus(`cannot reach the editor server: ${err.message}`, 'err'); }
  finally { stateBusy = false; }
  window.wiggly.ready = true;
}
export function flushState() {
  S.committing = null;
  if (S.stateDeferred) { S.stateDeferred = false; refreshState(); }
}

// ------------------------------------------------------------------------------------------
// frames: the newest request wins (higher seq; within one seq, warped over linear, final over
// partial)

let framesWanted = null, framesBusy = false;
export function offerFrames(meta) {
  if (meetInstance(meta.instance)) { S.lateFrames = meta; refreshState(); return; }
  // right after a gizmo release, frames of the drag previews are stale: skip them
  if (S.committing && meta.version <= S.committing.base) return;
  if (S.release && meta.version > S.release.base && S.release.event === undefined) S.release.event = performance.now() - S.release.t;
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
      const stale = () => meta.instance !== S.instance ||
        meta.seq < S.shown.seq || (meta.seq === S.shown.seq && meta.rank <= S.shown.rank) ||
        (S.committing && meta.version <= S.committing.base);
      if (stale()) continue;
      let buf;
      const requested = performance.now();
      try { ({ buf } = await api.bin(`/api/frames/${meta.id}`)); } catch { continue; }
      const fetched = performance.now();
      if (stale()) continue;
      if (meta.n_vertices !== S.n) { S.lateFrames = meta; continue; }  // mesh not loaded yet
      S.frames = { meta, data: new Float32Array(buf) };
      S.shown = { seq: meta.seq, rank: meta.rank, id: meta.id };
      window.wiggly.framesApplied += 1;
      showFrame();
      hooks.framesChanged();
      if (S.committing && meta.version > S.committing.base) flushState();  // panels may update now
      measureRelease(meta, requested, fetched);
    }
  } finally { framesBusy = false; }
}

// Latency of a gizmo release: from the pointer's release to the first frames of the committed
// edit on screen (and every later update of it: warped frames), whether or not the edit's
// answer came back before its frames.
function measureRelease(meta, requested, fetched) {
  const rel = S.release;
  if (!rel || meta.version <= rel.base) return;
  const stage = meta.stage + (meta.final ? ' (final)' : '');
  const applied = performance.now();
  const first = !rel.done;
  rel.done = true;
  requestAnimationFrame(() => {   // the frame is drawn in this callback (tick renders)
    window.wiggly.latencies.push({ ms: performance.now() - rel.t, stage, version: meta.version, first,
      posted: rel.posted ?? null, event: rel.event ?? null, requested: requested - rel.t,
      fetched: fetched - rel.t, applied: applied - rel.t, server_seconds: meta.seconds });
  });
  if (meta.final) S.release = null;
}

// ------------------------------------------------------------------------------------------
// time and playback

export function playRange() {
  const [a, b] = range();
  const r = S.view.range;
  if (!r) return [a, b];
  const lo = Math.max(a, Math.min(r[0], r[1])), hi = Math.min(b, Math.max(r[0], r[1]));
  return hi > lo ? [lo, hi] : [a, b];
}
export function setTime(t) {
  const [a, b] = range();
  S.t = Math.min(Math.max(t, a), b);
  showFrame();
}
export function frameIndex(t = S.t) {
  const f = S.frames;
  if (!f) return -1;
  const i = Math.round((t - f.meta.start) * f.meta.fps);
  return Math.min(Math.max(i, 0), f.meta.n_frames - 1);
}
export function framePositions(i) {
  return S.frames.data.subarray(i * S.n * 3, (i + 1) * S.n * 3);
}
export function showFrame() {
  const pos = geometry.getAttribute('position');
  if (!pos) return;
  const i = frameIndex();
  if (i >= 0) pos.array.set(framePositions(i));
  else pos.array.set(S.rest);
  pos.needsUpdate = true;
  geometry.computeVertexNormals();
  updateColors(false);
  redraw();
  $('time-readout').textContent = `${S.t.toFixed(3)} s  ·  frame ${Math.max(i, 0)}${S.frames ? ' / ' + (S.frames.meta.n_frames - 1) : ''}  ·  ${S.frames ? S.frames.meta.stage : 'rest'}`;
  hooks.timeChanged();
}
// The body's colours: grey, groups tinted (more when selected or near one of their keys),
// selected vertices yellow.  Playback recolours only when a group's tint changed.
let colorsKey = null;
export function updateColors(force = true) {
  const col = geometry.getAttribute('color');
  if (!col || !scene()) return;
  const c = col.array;
  const tint = new THREE.Color();
  const weights = {};
  for (const name of Object.keys(scene().groups)) weights[name] = name === S.selectedGroup || S.groups.has(name) ? 0.45 : 0.18;
  // driven groups ([drive]) are keyed at every driver frame: always in their colour
  const drive = scene().drive;
  for (const name of drive ? [].concat(drive.group) : []) if (name in weights) weights[name] = Math.max(weights[name], 0.6);
  for (const k of scene().keyframes) {
    const w = Math.max(0, 1 - Math.abs(S.t - k.time) / KEY_WINDOW);
    weights[k.group] = Math.max(weights[k.group] || 0, 0.18 + 0.82 * w);
  }
  // the surface over tets the warped frames turn inside out, over the spans where they do
  const spans = (S.frames && S.frames.meta.fold_spans) || [];
  const folds = spans.map(sp => Math.max(0, 1 - Math.max(sp.from - S.t, S.t - sp.until, 0) / KEY_WINDOW));
  const key = JSON.stringify([weights, S.frames ? S.frames.meta.id : null, folds]);
  if (!force && key === colorsKey) return;
  colorsKey = key;
  const blend = (idx, color, w) => {  // the vertices idx, from grey towards color by w
    for (const i of idx) {
      c[3 * i] = BASE.r + (color.r - BASE.r) * w;
      c[3 * i + 1] = BASE.g + (color.g - BASE.g) * w;
      c[3 * i + 2] = BASE.b + (color.b - BASE.b) * w;
    }
  };
  for (let i = 0; i < S.n; i++) { c[3 * i] = BASE.r; c[3 * i + 1] = BASE.g; c[3 * i + 2] = BASE.b; }
  for (const [name, w] of Object.entries(weights)) {
    const idx = S.groupVerts[name];
    if (idx) blend(idx, tint.set(groupColor(name)), w);
  }
  spans.forEach((sp, k) => { if (folds[k] > 0) blend(sp.vertices, FOLD, 0.9 * folds[k]); });
  for (let i = 0; i < S.n; i++) {
    if (S.selection[i]) { c[3 * i] = SELECTED.r; c[3 * i + 1] = SELECTED.g; c[3 * i + 2] = SELECTED.b; }
  }
  col.needsUpdate = true;
  redraw();
}
export function setPlaying(on) {
  S.playing = on;
  const [a, b] = playRange();
  if (on && (S.t >= b - 1e-9 || S.t < a)) S.t = a;
  S.lastTick = performance.now();
  $('btn-play').textContent = S.playing ? '❚❚' : '▶';
}
export function togglePlay() { setPlaying(!S.playing); }
// Advance playback by dt seconds of wall time (at most 0.1 s: a stalled tab does not jump),
// times the playback speed, looping in the preview range.
export function step(dt) {
  if (!S.playing) return;
  const [a, b] = playRange();
  const advance = Math.min(dt, 0.1) * S.view.speed;
  let t = Math.max(S.t + advance, a);
  if (t > b) {
    if ($('loop').checked) t = a + ((t - a) % Math.max(b - a, 1e-6));
    else { t = b; setPlaying(false); }
  }
  window.wiggly.lastStep = { wall: dt, advance, t };
  setTime(t);
}

// wiggly edit: the browser side. The server holds the scene (source of truth); this page
// draws it, turns user gestures into edits ({op: ...} JSON, see wiggly/editor/state.py), and
// plays the frames the server solves (float32 buffers, newest request wins).
//   core.js       server access, the tab's state S, the three.js scene
//   playback.js   mesh, state and frames; time, preview range and speed
//   panels.js     side panels, dialogs, notices
//   dopesheet.js  one row per group: select, move, copy, paste, duplicate keys
//   posing.js     the gizmo: axis keys, typed values, snapping, pivots, cancel
//   selection.js  brush, box, lasso; visible vertices only unless X-ray
//   onion.js      onion skins and motion paths
//   driver.js     the [drive] driver: its ghost, the driven groups' colour and dope-sheet ticks
//   views.js      front / side / top views, frame selected
import * as THREE from 'three';
import { $, S, api, hooks, act, edit, toast, setStatus, fmt, scene, range, fps, currentKey,
  camera, controls, renderer, scene3, geometry, canvas, redraw, SOFTWARE_GL, PAGE, TAB } from './core.js';
import { refreshState, offerFrames, setTime, togglePlay, step } from './playback.js';
import { renderPanels, renderKeyPanel, selectGroup, selectKey, deleteGroup, openDialog, promptDialog,
  newGroupFromSelection, setGroupFromSelection, showNotices } from './panels.js';
import { draw as drawDopesheet, drawTimeCursor, drivenTicks, pagePoint, setPreviewRange, deleteSelectedKeys, copyKeys, pasteKeys,
  duplicateKeys, keySelectedGroups, toggleKey } from './dopesheet.js';
import { startPosing, stopPosing, cancelDrag, updatePoseHelpers, dragKey, dragKeyUp, gizmoHandle,
  gizmoRing, poseTarget, applyPivot, setCursor, restPose } from './posing.js';
import { setTool, setXray, updateSelCount, screenBox } from './selection.js';
import { updateOnion, updatePaths, updatePathMarker, faceCamera, pathOf, onionInfo } from './onion.js';
import { syncDriver, updateDriverGhost, driverInfo } from './driver.js';
import { viewFrom, frameSelected, viewKey } from './views.js';

// ------------------------------------------------------------------------------------------
// wiring the modules together

let ground = null;
function makeGround() {
  if (ground) scene3.remove(ground);
  const bb = geometry.boundingBox;
  const size = bb.getSize(new THREE.Vector3()).length();
  const y = bb.min.y;
  ground = new THREE.Group();
  const plane = new THREE.Mesh(new THREE.PlaneGeometry(size * 8, size * 8),
    new THREE.MeshBasicMaterial({ color: 0x30353d }));   // unlit: it fills the view
  plane.rotation.x = -Math.PI / 2;
  plane.position.y = y - 1e-4 * size;
  const grid = new THREE.GridHelper(size * 8, 32, 0x59616e, 0x474e59);
  grid.position.y = y;
  ground.add(plane, grid);
  ground.name = 'ground';
  ground.userData.restY = y;
  scene3.add(ground);
  redraw();
}
// The floor stays under the whole motion: a body that sags or hangs below its rest pose
// (a tail fixed up high, a soft body under gravity) would be hidden by an opaque floor.
function lowerGround() {
  if (!ground || !S.frames) return;
  const d = S.frames.data;
  let low = Infinity;
  for (let i = 1; i < d.length; i += 3) if (d[i] < low) low = d[i];
  const size = geometry.boundingBox.getSize(new THREE.Vector3()).length();
  const y = Math.min(ground.userData.restY, low) - ground.userData.restY;
  if (Math.abs(ground.position.y - y) > 1e-6 * size) { ground.position.y = y; redraw(); }
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
  $('snap-move').value = +(niceRound(size / 100)).toPrecision(2);
  S.view.snapMove = parseFloat($('snap-move').value);
}
function niceRound(x) { const p = 10 ** Math.floor(Math.log10(x)); const m = x / p; return (m < 1.5 ? 1 : m < 3.5 ? 2 : m < 7.5 ? 5 : 10) * p; }

Object.assign(hooks, {
  meshLoaded() { frameCamera(); makeGround(); setCursor(null); },
  renderPanels, renderKeyPanel, selectKey, selectGroup, openDialog, showNotices, refreshState,
  updatePoseHelpers, startPosing, stopPosing, cancelDrag,
  drawDopesheet, toggleKey,
  updatePaths() { updatePaths(); updateOnion(); },   // the selected groups changed, too
  timeChanged() { drawTimeCursor(); updateOnion(); updatePathMarker(); updateDriverGhost(); },
  syncDriver,
  framesChanged() { updatePaths(); updateOnion(); lowerGround(); },
});

window.wiggly = {                 // test and benchmark hooks (read-only use)
  S, latencies: [], framesApplied: 0,
  groundY: () => (ground ? ground.userData.restY + ground.position.y : null),
  gizmoHandle, gizmoRing, screenBox, redraw, onionInfo, driverInfo,
  projectGroup: (name) => screenBox(S.groupVerts[name] || []),
  rigidOfPose: () => poseTarget(),
  timePoint: (t, group) => pagePoint(t, group),
  shownPositions: () => Array.from(geometry.getAttribute('position').array),
  shownColors: () => Array.from(geometry.getAttribute('color').array),
  setTime: (t) => setTime(t),
  drivenTicks: () => drivenTicks(),
  pathOf,
  camera: () => ({ position: camera.position.toArray(), target: controls.target.toArray(), fov: camera.fov, aspect: camera.aspect }),
  ready: false,
  softwareGL: SOFTWARE_GL,
  renderScale: 1,
};

// ------------------------------------------------------------------------------------------
// events from the server

function connect(wait = 500) {
  const es = new EventSource(`/api/events?page=${PAGE}&tab=${TAB}`);
  es.onmessage = (m) => {
    const e = JSON.parse(m.data);
    if (e.type === 'state') {
      if (S.committing) { S.stateDeferred = true; setTimeout(() => { if (S.stateDeferred) { S.committing = null; S.stateDeferred = false; refreshState(); } }, 1000); }  // frames first
      else refreshState();
    } else if (e.type === 'frames') offerFrames(e);
    else if (e.type === 'solve') onSolve(e);
    else if (e.type === 'physics') onPhysics(e);
    else if (e.type === 'export') { setStatus(e.message, e.stage === 'error' ? 'err' : e.stage === 'done' ? 'ok' : 'busy'); if (e.stage !== 'running') toast(e.message, e.stage === 'error'); }
    else if (e.type === 'notice' && e.from_tab !== TAB) toast(e.message, e.level === 'error');  // not of this tab's own open or save as
  };
  es.onerror = () => {
    setStatus('connection to the editor server lost; retrying…', 'err');
    // the browser retries a dropped stream itself, but gives up on an answer that is not a
    // stream (503: too many open; a proxy's error): then the page retries, less and less often
    if (es.readyState === EventSource.CLOSED) setTimeout(() => connect(Math.min(2 * wait, 10000)), wait);
  };
  es.onopen = () => { wait = 500; refreshState(); };
}

function onSolve(e) {
  if (e.seq < S.shown.seq && e.stage !== 'error') return;
  const res = e.residual_max != null ? `, max keyframe residual ${fmt(e.residual_max * 1000)} mm` : '';
  if (e.stage === 'error') setStatus(e.message, 'err');
  else if (e.stage === 'linear') setStatus('solving… (linear)', 'busy');
  else if (e.stage === 'refining') setStatus(`linear frames shown in ${fmt(e.seconds)} s; refining warped…`, 'busy');
  else if (e.stage === 'warped') setStatus(`solving… warped: ${e.iterations} Newton iterations${e.objective != null ? `, objective ${fmt(e.objective, 4)}` : ''}`, 'busy');
  else if (e.stage === 'done') setStatus(`${e.converged === undefined ? 'linear solve' : 'warped: ' + e.message} in ${fmt(e.seconds)} s${res}`, e.converged === false ? '' : 'ok');
}
function onPhysics(e) {
  const bar = $('phys-progress');
  const busy = e.stage !== 'ready' && e.stage !== 'error';
  bar.hidden = !busy;
  bar.firstElementChild.style.width = `${Math.round(100 * e.fraction)}%`;
  bar.classList.toggle('indeterminate', busy && e.stage === 'mesh');
  $('phys-state').textContent = busy ? `${e.message}… ${e.elapsed.toFixed(1)} s` : e.message;
  if (busy) setStatus(`recomputing: ${e.message}… ${e.elapsed.toFixed(1)} s`, 'busy');
  else if (e.stage === 'error') setStatus(e.message, 'err');
}

// ------------------------------------------------------------------------------------------
// buttons and fields

// Save (to ``path``, or the scene's own file): a file changed on disk since it was opened, or
// another existing file, is overwritten only when the user confirms what the server said.
async function saveTo(body) {
  try { return await api.post('/api/save', body); } catch (err) {
    if (err.status === 409) {
      if (confirm(`${err.message}\n\nOverwrite it?`)) return act(() => api.post('/api/save', { ...body, overwrite: true }));
      setStatus('not saved', 'err');
      return null;
    }
    toast(err.message, true); setStatus(err.message.split('\n')[0], 'err');
    return null;
  }
}
async function save() {
  const r = await saveTo({});
  if (r) { toast(`saved ${r.path}`); setStatus(`saved ${r.path}`, 'ok'); }
}
async function undoRedo(which) {
  try {
    const r = await api.post(`/api/${which}`);
    // each tab undoes its own edits: say so rather than do nothing visible
    if (r && r.changed === false) setStatus(`nothing to ${which} in this tab (each tab ${which}s its own edits)`);
  } catch (err) { toast(err.message, true); setStatus(err.message.split('\n')[0], 'err'); refreshState(); }
}
$('btn-open').onclick = openDialog;
$('btn-save').onclick = save;
$('btn-saveas').onclick = () => promptDialog('Save scene as (.toml)', S.desc.path || 'scene.toml', async (p) => {
  const r = await saveTo({ path: p });
  if (r) { toast(`saved ${r.path}`); setStatus(`saved ${r.path}`, 'ok'); }
  return !!r;
});
const lastExport = {};  // scene name -> the paths last exported (the dialog offers them again)
$('btn-export').onclick = () => {
  const n = scene().name;
  promptDialog('Export (comma-separated: .glb .gltf .usd .usda .usdc .npz .obj .mp4 .gif .png)', lastExport[n] || `out/${n}.glb, out/${n}.mp4`, async (v) => {
    const paths = v.split(',').map((s) => s.trim()).filter(Boolean);
    lastExport[n] = paths.join(', ');
    let r = null;
    try { r = await api.post('/api/export', { paths, overwrite: false }); } catch (err) {
      if (err.status !== 409) { toast(err.message, true); setStatus(err.message.split('\n')[0], 'err'); return false; }
      if (!confirm(`${err.message}\n\nOverwrite?`)) { setStatus('not exported', 'err'); return false; }
      r = await act(() => api.post('/api/export', { paths, overwrite: true }));
    }
    if (r) setStatus(`exporting ${r.paths.join(', ')}…`, 'busy');
    return !!r;
  });
};
$('btn-undo').onclick = () => undoRedo('undo');
$('btn-redo').onclick = () => undoRedo('redo');
for (const b of document.querySelectorAll('.tool')) b.onclick = () => setTool(b.dataset.tool);
$('btn-xray').onclick = () => setXray(!S.view.xray);
$('btn-group-new').onclick = newGroupFromSelection;
$('btn-group-set').onclick = setGroupFromSelection;
$('btn-sel-clear').onclick = () => { S.selection.fill(0); updateSelCount(); };
$('btn-key-add').onclick = keySelectedGroups;
const togglePose = (mode) => { if (S.posing && S.posing.mode === mode) stopPosing(); else startPosing(mode); renderKeyPanel(); };
$('btn-pose-t').onclick = () => togglePose('translate');
$('btn-pose-r').onclick = () => togglePose('rotate');
$('btn-pose-v').onclick = () => togglePose('velocity');
$('btn-pose-rest').onclick = () => { const k = currentKey(); if (k) restPose(k); };
$('btn-key-del').onclick = () => { const k = currentKey(); if (k) edit({ op: 'delete_keyframe', id: k.id }); };
$('btn-play').onclick = togglePlay;
$('btn-notices').onclick = () => { $('notices').hidden = true; };
// fn gives the keyframe's changed fields, or null for a value that is not one (then the
// fields show the scene's values again and nothing is sent)
// a refused value leaves the field (the field being typed in keeps its text otherwise)
const showScene = (el) => { if (document.activeElement === el) el.blur(); renderPanels(); };
const keyField = (id, fn) => { $(id).onchange = () => { const k = currentKey(); if (!k) return; const f = fn($(id)); if (f === null) { showScene($(id)); return; } edit({ op: 'update_keyframe', id: k.id, ...f }).then((r) => { if (!r) showScene($(id)); }); }; };
const numberOf = (el, what) => { const v = parseFloat(el.value); if (Number.isFinite(v)) return v; toast(`keyframe ${what}: ${el.value === '' ? 'empty' : JSON.stringify(el.value)} is not a number`, true); return null; };
keyField('key-time', (el) => { const t = numberOf(el, 'time'); return t === null ? null : { time: t }; });
keyField('key-group', (el) => ({ group: el.value }));
keyField('key-stiffness', (el) => { if (el.value === '') return { stiffness: null }; const v = numberOf(el, 'stiffness'); return v === null ? null : { stiffness: v }; });
keyField('key-name', (el) => ({ name: el.value || null }));
const velocity = () => { if (!$('key-vel-on').checked) return { velocity: null }; const v = ['key-vx', 'key-vy', 'key-vz'].map((id) => numberOf($(id), 'velocity')); return v.includes(null) ? null : { velocity: v }; };
for (const id of ['key-vel-on', 'key-vx', 'key-vy', 'key-vz']) keyField(id, velocity);
for (const el of document.querySelectorAll('[data-set]')) {
  el.onchange = () => {
    const [section, key, index] = el.dataset.set.split('.');
    let v = el.type === 'checkbox' ? el.checked : el.tagName === 'SELECT' ? el.value : parseFloat(el.value);
    if (el.type === 'number' && Number.isNaN(v)) { toast(`${section}.${key}: not a number`, true); showScene(el); return; }  // the scene's value again
    if (key === 'modes' || key === 'resolution' || key === 'free_modes') v = Math.round(v);
    if (index !== undefined) { const vec = [...(scene()[section][key])]; vec[+index] = v; v = vec; }
    edit({ op: 'set', section, values: { [key]: v } }).then((r) => { if (!r) showScene(el); });  // refused: the scene's value again
  };
}
// view options (this tab only)
const setView = (key, value) => { S.view[key] = value; syncView(); };
function syncView() {
  $('onion').checked = S.view.onion; $('paths').checked = S.view.paths; $('snap').checked = S.view.snap;
  $('driver').checked = S.view.driver;
  $('speed').value = String(S.view.speed); $('pivot').value = S.view.pivot;
  updateOnion(); updatePaths(); updateDriverGhost(); redraw();
}
$('onion').onchange = () => setView('onion', $('onion').checked);
$('onion-count').onchange = () => setView('onionCount', Math.max(1, Math.min(8, parseInt($('onion-count').value, 10) || 3)));
$('onion-step').onchange = () => setView('onionStep', Math.max(1, parseInt($('onion-step').value, 10) || 5));
$('paths').onchange = () => setView('paths', $('paths').checked);
$('driver').onchange = () => setView('driver', $('driver').checked);
$('snap').onchange = () => setView('snap', $('snap').checked);
$('snap-move').onchange = () => setView('snapMove', Math.max(1e-6, parseFloat($('snap-move').value) || 0.01));
$('snap-turn').onchange = () => setView('snapTurn', Math.max(0.01, parseFloat($('snap-turn').value) || 15));
$('speed').onchange = () => setView('speed', parseFloat($('speed').value) || 1);
$('pivot').onchange = () => { setView('pivot', $('pivot').value); applyPivot(); };
for (const id of ['range-from', 'range-to']) {
  $(id).onchange = () => {
    const a = parseFloat($('range-from').value), b = parseFloat($('range-to').value);
    const [lo, hi] = range();
    if (Number.isNaN(a) && Number.isNaN(b)) { setPreviewRange(null); return; }
    const from = Math.max(lo, Math.min(hi, Number.isNaN(a) ? lo : a));
    const to = Math.max(lo, Math.min(hi, Number.isNaN(b) ? hi : b));
    setPreviewRange(from <= to ? [from, to] : [to, from]);  // typed the wrong way round
  };
}
$('btn-range-clear').onclick = () => setPreviewRange(null);
for (const [id, side] of [['view-front', 'front'], ['view-side', 'right'], ['view-top', 'top']]) $(id).onclick = () => viewFrom(side);
$('view-frame').onclick = frameSelected;
$('btn-help').onclick = () => toast([
  'Space play/pause · ←/→ step a frame · Home/End · Ctrl+drag on the ruler: preview range, Alt+P clears',
  'Q/Esc orbit · B brush · X box · L lasso (Shift adds, Alt removes; visible vertices only) · Alt+Z X-ray · [ ] brush radius',
  'G new group · K key the selected groups at the current time · Shift/Ctrl+click selects several groups or keys',
  'W move / E rotate the keyframe (gizmo) · V its velocity · while dragging: X Y Z axis, type a value + Enter, Ctrl snap, Esc cancels',
  'Shift+right-click places the 3D cursor (pivot choice) · Shift+Tab snapping on/off',
  'Ctrl+C / Ctrl+V / Shift+D copy, paste, duplicate keys · Delete deletes them',
  '1 / 3 / 7 (numpad) front, side, top (Ctrl or Shift: opposite) · F or numpad . frame selected · O onion skins (of the selected groups; the whole body when none is) · P motion paths · D the driver ghost ([drive] scenes)',
  'Ctrl+Z undo · Ctrl+Shift+Z / Ctrl+Y redo (this tab\'s edits) · Ctrl+S save'].join('\n'));

// ------------------------------------------------------------------------------------------
// keyboard

// Run fn once a key being added (K) is answered and selected: W right after K poses the new
// key even when the state and frames showed it before the edit's answer came back.
function afterKeying(fn) {
  if (S.keying) S.keying.then(fn, fn); else fn();
}

window.addEventListener('keyup', dragKeyUp);
// a field's value when it got the focus, for Escape to put back
document.addEventListener('focusin', (e) => {
  const el = e.target;
  if (['INPUT', 'SELECT', 'TEXTAREA'].includes(el.tagName) && el.type !== 'checkbox') {
    el.dataset.before = el.value;
  }
});
window.addEventListener('keydown', (e) => {
  if (dragKey(e)) { e.preventDefault(); return; }
  const typing = ['INPUT', 'SELECT', 'TEXTAREA'].includes(document.activeElement.tagName) && document.activeElement.type !== 'checkbox';
  const mod = e.ctrlKey || e.metaKey;
  const k = e.key.length === 1 ? e.key.toLowerCase() : e.key;
  if (mod && k === 's') { e.preventDefault(); save(); return; }
  if (!$('modal').hidden) { if (e.key === 'Escape') $('modal-cancel').click(); return; }
  if (typing && (e.key === 'Enter' || e.key === 'Escape') && document.activeElement.id !== 'group-name') {
    const field = document.activeElement;
    // Escape cancels what was typed (its value as it was when focused: no change event);
    // Enter commits it; either gives the keys back to the shortcuts
    if (e.key === 'Escape' && field.dataset.before !== undefined) field.value = field.dataset.before;
    field.blur();
    canvas.focus();
    return;
  }
  if (typing) return;
  if (mod && k === 'z') { e.preventDefault(); undoRedo(e.shiftKey ? 'redo' : 'undo'); return; }
  if (mod && k === 'y') { e.preventDefault(); undoRedo('redo'); return; }
  if (mod && k === 'c') { e.preventDefault(); copyKeys(); return; }
  if (mod && k === 'v') { e.preventDefault(); pasteKeys(); return; }
  if (viewKey(e)) { e.preventDefault(); return; }
  if (mod) return;
  if (e.altKey) {
    if (k === 'z') { e.preventDefault(); setXray(!S.view.xray); }
    else if (k === 'p') { e.preventDefault(); setPreviewRange(null); }
    return;
  }
  if (e.shiftKey && k === 'd') { e.preventDefault(); duplicateKeys(); return; }
  if (e.shiftKey && e.key === 'Tab') { e.preventDefault(); setView('snap', !S.view.snap); return; }
  switch (e.key) {
    case ' ': e.preventDefault(); togglePlay(); break;
    case 'ArrowRight': setTime(S.t + 1 / fps()); break;
    case 'ArrowLeft': setTime(S.t - 1 / fps()); break;
    case 'Home': setTime(range()[0]); break;
    case 'End': setTime(range()[1]); break;
    case 'Delete': case 'Backspace': if (!deleteSelectedKeys() && S.selectedGroup) deleteGroup(S.selectedGroup); break;
    case 'Escape': stopPosing(); setTool('orbit'); renderKeyPanel(); break;
    default:
      switch (k) {
        case 'q': setTool('orbit'); break;
        case 'b': setTool('brush'); break;
        case 'x': setTool('box'); break;
        case 'l': setTool('lasso'); break;
        case 'g': newGroupFromSelection(); break;
        case 'k': keySelectedGroups(); break;
        case 'w': afterKeying(() => startPosing('translate')); break;
        case 'e': afterKeying(() => startPosing('rotate')); break;
        case 'v': afterKeying(() => startPosing('velocity')); break;
        case 'o': setView('onion', !S.view.onion); break;
        case 'p': setView('paths', !S.view.paths); break;
        case 'd': setView('driver', !S.view.driver); break;
        case '[': $('brush-radius').stepDown(5); break;
        case ']': $('brush-radius').stepUp(5); break;
        default: return;
      }
  }
});

// ------------------------------------------------------------------------------------------
// rendering on demand: only when something changed (software GL in a headless browser draws a
// few frames per second, and an idle editor should leave the main thread to the network)

function resize() {
  const r = $('view').getBoundingClientRect();
  renderer.setSize(Math.max(1, r.width), Math.max(1, r.height), false);
  camera.aspect = r.width / Math.max(1, r.height);
  camera.updateProjectionMatrix();
  redraw();
}

// While playing, the view is drawn at a lower resolution when frames take longer than a 30th
// of a second (software GL spends its time per pixel: onion skins on a 20k-tet body), down to
// half; paused, at full resolution again.
const FULL_RATIO = renderer.getPixelRatio(), MIN_SCALE = 0.5;
const quality = { scale: 1, intervals: [] };
function setScale(scale) {
  quality.scale = scale;
  renderer.setPixelRatio(FULL_RATIO * scale);
  resize();
  window.wiggly.renderScale = scale;
}
function adaptScale(dt) {
  if (!S.playing) {
    quality.intervals = [];
    if (quality.scale !== 1) setScale(1);
    return;
  }
  quality.intervals.push(dt);
  if (quality.intervals.length < 6) return;
  const mean = quality.intervals.reduce((a, b) => a + b, 0) / quality.intervals.length;
  quality.intervals = [];
  if (mean > 1 / 33 && quality.scale > MIN_SCALE) setScale(Math.max(MIN_SCALE, quality.scale * 0.8));
  else if (mean < 1 / 50 && quality.scale < 1) setScale(Math.min(1, quality.scale / 0.8));
}
window.addEventListener('resize', () => { resize(); drawDopesheet(); });
// reloaded or closed mid-drag: the drag is abandoned (the server also notices the event
// stream's end, for a crashed page)
// a value typed in a field without Enter is committed, as leaving the field does
window.addEventListener('pagehide', () => {
  if (S.dragging) api.beacon('/api/preview/cancel');
  const field = document.activeElement;
  if (field && ['INPUT', 'TEXTAREA'].includes(field.tagName) && field.value !== field.dataset.before) {
    S.leaving = true;  // its change handler's request is sent with keepalive
    field.blur();      // fires its change event
    S.leaving = false;
  }
});
new ResizeObserver(() => { resize(); drawDopesheet(); }).observe($('view'));

function tick(now) {
  const dt = (now - S.lastTick) / 1000;
  S.lastTick = now;
  step(dt);
  adaptScale(dt);
  if (S.needsRender || S.playing) {
    S.needsRender = false;
    if (S.view.paths) faceCamera(camera);
    renderer.render(scene3, camera);
    const w = window.wiggly;
    w.renders = (w.renders || 0) + 1;
    w.renderedT = S.t;   // the time the canvas shows (tests wait for it)
    w.renderMs = performance.now() - now;
  }
  requestAnimationFrame(tick);
}
resize();
connect();
requestAnimationFrame((now) => { S.lastTick = now; tick(now); });

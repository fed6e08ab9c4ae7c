// The dope sheet: one row per group with its keyframes as diamonds, a time ruler on top.
//   ruler: click or drag to scrub (on the frame grid); Ctrl+drag sets the preview range (Alt+P
//          clears it)
//   keys: click selects (Shift adds or removes), drag moves the selected keys in time (on the
//         frame grid), drag on empty space box-selects, a click there sets the time
//   labels: click selects a group (Shift adds: K keys every selected group at once)
//   Ctrl+C / Ctrl+V copy and paste the selected keys at the current time (same groups, same
//   spacing), Shift+D duplicates them there, Delete deletes them; each is one undo step.
import { $, S, hooks, edit, toast, scene, range, fps, groupColor, keyById, snapTime } from './core.js';
import { setTime, setPlaying, playRange } from './playback.js';

const RULER = 18, ROW = 18, LABEL_W = 120, PAD = 10, MAX_ROWS = 6;
const KEY_FIELDS = ['time', 'group', 'position', 'velocity', 'stiffness', 'c_A', 'c_B', 'name'];
const ds = $('dopesheet');
let scrollRow = 0;
let drag = null;

function groupsShown() { return scene() ? Object.keys(scene().groups) : []; }
function width() { return ds.clientWidth; }
export function tlX(t) { const [a, b] = range(); return LABEL_W + PAD + (t - a) / Math.max(b - a, 1e-9) * (width() - LABEL_W - 2 * PAD); }
function tlT(x) { const [a, b] = range(); return a + (x - LABEL_W - PAD) / Math.max(width() - LABEL_W - 2 * PAD, 1) * (b - a); }
function rowOf(name) { const i = groupsShown().indexOf(name) - scrollRow; return i >= 0 && i < MAX_ROWS ? i : -1; }
function rowY(i) { return RULER + i * ROW + ROW / 2; }
function groupAtY(y) {
  if (y < RULER) return null;
  const i = Math.floor((y - RULER) / ROW) + scrollRow;
  return groupsShown()[i] ?? null;
}
function keyTime(k) { return drag && drag.move && drag.ids.has(k.id) ? snapTime(k.time + drag.dt) : k.time; }

export function layout() {
  const rows = Math.max(1, Math.min(MAX_ROWS, groupsShown().length));
  const h = RULER + rows * ROW + 4;
  if (ds.style.height !== `${h}px`) ds.style.height = `${h}px`;
  scrollRow = Math.max(0, Math.min(scrollRow, groupsShown().length - MAX_ROWS));
}

// Everything but the time cursor is drawn into `sheet` (when the scene, the selection or a
// drag changes); playback only copies it and draws the cursor.
const sheet = document.createElement('canvas');
let ticks = {};  // group -> driven-frame ticks drawn (tests)
let hinted = false;  // the rows hold the "no groups yet" hint: the cursor stays in the ruler
export function drivenTicks() { return { ...ticks }; }
export function draw() {
  layout();
  const w = ds.clientWidth, h = ds.clientHeight;
  const dpr = devicePixelRatio;
  if (sheet.width !== Math.round(w * dpr) || sheet.height !== Math.round(h * dpr)) { sheet.width = Math.round(w * dpr); sheet.height = Math.round(h * dpr); }
  const g = sheet.getContext('2d');
  g.setTransform(dpr, 0, 0, dpr, 0, 0);
  g.clearRect(0, 0, w, h);
  g.fillStyle = '#1a1d22'; g.fillRect(LABEL_W, 0, w - LABEL_W, h);
  if (!scene()) return;
  const [a, b] = range();
  const names = groupsShown();
  // rows and labels
  g.font = '11px system-ui'; g.textBaseline = 'middle';
  names.forEach((name, j) => {
    const i = j - scrollRow;
    if (i < 0 || i >= MAX_ROWS) return;
    const y = RULER + i * ROW;
    const sel = S.groups.has(name) || name === S.selectedGroup;
    g.fillStyle = sel ? '#2c4a6b' : (i % 2 ? '#20242a' : '#1d2126');
    g.fillRect(0, y, w, ROW);
    g.fillStyle = groupColor(name); g.fillRect(6, y + 5, 8, 8);
    g.fillStyle = sel ? '#fff' : '#dfe3ea';
    g.fillText(name.length > 15 ? name.slice(0, 14) + '…' : name, 20, y + ROW / 2);
  });
  hinted = !names.length;
  if (hinted) { g.fillStyle = '#8d95a3'; g.fillText('no groups yet: select vertices, press G', 8, RULER + ROW / 2); }
  if (names.length > MAX_ROWS) { g.fillStyle = '#8d95a3'; g.fillText(`${scrollRow + 1}-${Math.min(names.length, scrollRow + MAX_ROWS)} of ${names.length} (wheel)`, 8, RULER / 2); }
  // ruler
  g.fillStyle = '#262a31'; g.fillRect(LABEL_W, 0, w - LABEL_W, RULER);
  g.fillStyle = '#8d95a3'; g.font = '10px system-ui'; g.strokeStyle = '#3a3f48'; g.lineWidth = 1;
  const stepT = niceStep((b - a) / 10);
  for (let t = Math.ceil(a / stepT) * stepT; t <= b + 1e-9; t += stepT) {
    const x = tlX(t);
    g.beginPath(); g.moveTo(x, RULER - 5); g.lineTo(x, h); g.stroke();
    g.fillText(`${+t.toFixed(3)}`, x + 2, RULER / 2);
  }
  // preview range: dim what lies outside
  const r = drag && drag.range ? [Math.min(drag.t0, drag.t1), Math.max(drag.t0, drag.t1)] : S.view.range ? playRange() : null;
  if (r) {
    g.fillStyle = 'rgba(0,0,0,0.45)';
    g.fillRect(LABEL_W, 0, tlX(r[0]) - LABEL_W, h);
    g.fillRect(tlX(r[1]), 0, w - tlX(r[1]), h);
    g.fillStyle = '#f0b43c';
    g.fillRect(tlX(r[0]) - 1, 0, 2, RULER); g.fillRect(tlX(r[1]) - 1, 0, 2, RULER);
  }
  // driven frames ([drive]): a tick per driver frame on the driven groups' rows
  ticks = {};
  if (S.driver) {
    for (const name of S.driver.meta.groups) {
      const i = rowOf(name);
      if (i < 0) continue;
      const y = rowY(i);
      g.strokeStyle = groupColor(name); g.globalAlpha = 0.7; g.lineWidth = 1;
      g.beginPath();
      for (const t of S.driver.meta.times) { const x = Math.round(tlX(t)) + 0.5; g.moveTo(x, y - 4); g.lineTo(x, y + 4); }
      ticks[name] = S.driver.meta.times.length;
      g.stroke();
      g.globalAlpha = 1;
    }
  }
  // keys
  for (const k of scene().keyframes) {
    const i = rowOf(k.group);
    if (i < 0) continue;
    const x = tlX(keyTime(k)), y = rowY(i);
    g.save(); g.translate(x, y); g.rotate(Math.PI / 4);
    g.fillStyle = groupColor(k.group);
    g.fillRect(-5, -5, 10, 10);
    if (S.keys.has(k.id) || k.id === S.selectedKey) { g.strokeStyle = k.id === S.selectedKey ? '#fff' : '#ffd24d'; g.lineWidth = 2; g.strokeRect(-6, -6, 12, 12); }
    g.restore();
  }
  // box selection
  if (drag && drag.box && drag.x1 !== undefined) {
    g.strokeStyle = '#4da3ff'; g.setLineDash([4, 3]);
    g.strokeRect(Math.min(drag.x0, drag.x1), Math.min(drag.y0, drag.y1), Math.abs(drag.x1 - drag.x0), Math.abs(drag.y1 - drag.y0));
    g.setLineDash([]);
  }
  drawTimeCursor();
}
export function drawTimeCursor() {
  const dpr = devicePixelRatio;
  if (ds.width !== sheet.width || ds.height !== sheet.height) { ds.width = sheet.width; ds.height = sheet.height; }
  const g = ds.getContext('2d');
  g.setTransform(1, 0, 0, 1, 0, 0);
  g.drawImage(sheet, 0, 0);
  if (!scene()) return;
  g.setTransform(dpr, 0, 0, dpr, 0, 0);
  const x = tlX(S.t);
  g.strokeStyle = '#4da3ff'; g.lineWidth = 2;
  g.beginPath(); g.moveTo(x, 0); g.lineTo(x, hinted ? RULER : ds.clientHeight); g.stroke();
  g.lineWidth = 1;
}
function niceStep(x) { const p = 10 ** Math.floor(Math.log10(x)); const m = x / p; return (m < 1.5 ? 1 : m < 3.5 ? 2 : m < 7.5 ? 5 : 10) * p; }

function keyAt(x, y) {
  const name = groupAtY(y);
  if (name === null) return null;
  let best = null, dist = 7;
  for (const k of scene().keyframes) {
    if (k.group !== name) continue;
    const d = Math.abs(tlX(k.time) - x);
    if (d < dist) { dist = d; best = k; }
  }
  return best;
}
// Page coordinates of a time, a group's row and a key (tests, benchmarks).
export function pagePoint(t, group) {
  const r = ds.getBoundingClientRect();
  const i = group === undefined ? null : rowOf(group);
  return { x: r.left + tlX(t), y: r.top + (i === null ? RULER / 2 : i < 0 ? -1 : rowY(i)) };
}

// ------------------------------------------------------------------------------------------
// mouse

ds.addEventListener('pointerdown', (e) => {
  if (!scene() || e.button !== 0) return;
  ds.setPointerCapture(e.pointerId);
  const x = e.offsetX, y = e.offsetY, add = e.shiftKey;
  if (x < LABEL_W) {
    const name = groupAtY(y);
    if (name !== null) hooks.selectGroup(name, { add: add || e.ctrlKey, vertices: !(add || e.ctrlKey) });
    return;
  }
  if (y < RULER) {
    if (e.ctrlKey) { drag = { range: true, t0: snapTime(tlT(x)), t1: snapTime(tlT(x)) }; draw(); return; }
    drag = { scrub: true }; setPlaying(false); setTime(snapTime(tlT(x))); return;
  }
  const k = keyAt(x, y);
  if (k) {
    if (add) {
      toggleKey(k.id);
      drag = null; draw(); return;
    }
    if (!S.keys.has(k.id)) hooks.selectKey(k.id, false);
    else hooks.selectKey(k.id, false, { keep: true });
    drag = { move: true, id: k.id, ids: new Set(S.keys), x0: x, dt: 0, moved: false };
    draw();
    return;
  }
  drag = { box: true, x0: x, y0: y, add };
});
ds.addEventListener('pointermove', (e) => {
  if (!drag) return;
  const x = e.offsetX, y = e.offsetY;
  if (drag.scrub) { setTime(snapTime(tlT(x))); return; }
  if (drag.range) { drag.t1 = snapTime(tlT(x)); draw(); return; }
  if (drag.move) {
    if (Math.abs(x - drag.x0) > 3) drag.moved = true;
    if (drag.moved) { drag.dt = tlT(x) - tlT(drag.x0); draw(); }
    return;
  }
  if (drag.box) { drag.x1 = x; drag.y1 = y; draw(); }
});
ds.addEventListener('pointerup', async (e) => {
  const d = drag; drag = null;
  if (!d || d.scrub) { draw(); return; }
  if (d.range) {
    const [lo, hi] = [Math.min(d.t0, d.t1), Math.max(d.t0, d.t1)];
    setPreviewRange(hi - lo > 1e-9 ? [lo, hi] : null);
    return;
  }
  if (d.move) {
    if (!d.moved) { setTime(keyById(d.id).time); draw(); return; }
    const ops = [];
    for (const id of d.ids) {
      const k = keyById(id);
      if (!k) continue;
      const t = snapTime(k.time + d.dt);
      if (t !== k.time) ops.push({ op: 'update_keyframe', id, time: t });
    }
    draw();
    if (ops.length) {
      await edit(ops.length === 1 ? ops[0] : { op: 'batch', ops, label: `move ${ops.length} keyframes` });  // one: the server names it
      const k = keyById(d.id);
      if (k) setTime(k.time);
    }
    return;
  }
  if (d.box) {
    if (d.x1 === undefined || (Math.abs(d.x1 - d.x0) < 3 && Math.abs(d.y1 - d.y0) < 3)) {
      if (!d.add) { S.keys.clear(); hooks.selectKey(null); }
      setPlaying(false); setTime(snapTime(tlT(e.offsetX)));
      return;
    }
    const [x0, x1] = [Math.min(d.x0, d.x1), Math.max(d.x0, d.x1)], [y0, y1] = [Math.min(d.y0, d.y1), Math.max(d.y0, d.y1)];
    if (!d.add) S.keys.clear();
    let last = null;
    for (const k of scene().keyframes) {
      const i = rowOf(k.group);
      if (i < 0) continue;
      const x = tlX(k.time), y = rowY(i);
      if (x >= x0 && x <= x1 && y >= y0 - ROW / 2 && y <= y1 + ROW / 2) { S.keys.add(k.id); last = k.id; }
    }
    hooks.selectKey(last ?? (S.keys.size ? [...S.keys].pop() : null), false, { keep: true });
  }
});
ds.addEventListener('wheel', (e) => {
  if (groupsShown().length <= MAX_ROWS) return;
  e.preventDefault();
  scrollRow += Math.sign(e.deltaY);
  draw();
}, { passive: false });

// ------------------------------------------------------------------------------------------
// the preview range

export function setPreviewRange(r) {
  S.view.range = r;
  $('range-from').value = r ? +r[0].toFixed(4) : '';
  $('range-to').value = r ? +r[1].toFixed(4) : '';
  if (r && (S.t < r[0] || S.t > r[1])) setTime(r[0]);
  draw();
}

// ------------------------------------------------------------------------------------------
// keyframe operations on the selection

// Shift+click on a key: add it to the selection (it becomes the active one), or take it out.
export function toggleKey(id) {
  if (!S.keys.has(id)) { S.keys.add(id); hooks.selectKey(id, false, { keep: true }); return; }
  S.keys.delete(id);
  const active = S.selectedKey === id ? ([...S.keys].pop() ?? null) : S.selectedKey;
  if (active === null) hooks.selectKey(null);
  else hooks.selectKey(active, false, { keep: true });
}

function selectedKeys() { return scene().keyframes.filter((k) => S.keys.has(k.id) || k.id === S.selectedKey); }
export function deleteSelectedKeys() {
  const keys = selectedKeys();
  if (!keys.length) return false;
  const ops = keys.map((k) => ({ op: 'delete_keyframe', id: k.id }));
  edit(ops.length === 1 ? ops[0] : { op: 'batch', ops, label: `delete ${keys.length} keyframes` });
  return true;
}
export function copyKeys() {
  const keys = selectedKeys();
  if (!keys.length) { toast('select keyframes in the dope sheet first', true); return; }
  const t0 = Math.min(...keys.map((k) => k.time));
  S.clipboard = { t0, keys: keys.map((k) => Object.fromEntries(KEY_FIELDS.filter((f) => k[f] !== undefined).map((f) => [f, k[f]]))) };
  toast(`copied ${keys.length} keyframe${keys.length > 1 ? 's' : ''}`);
}
async function pasteAt(t, clip, label) {
  const [a, b] = range();
  const times = clip.keys.map((k) => t + (k.time - clip.t0));
  const out = times.filter((x) => x < a - 1e-9 || x > b + 1e-9).length;
  if (out) { toast(`${out} of the keyframes would fall outside the shot (${a}–${b} s); move the time first`, true); return; }
  const ops = clip.keys.map((k, i) => ({ op: 'add_keyframe', ...k, time: snapTime(times[i]) }));
  const r = await edit({ op: 'batch', ops, label: `${label} ${ops.length} keyframe${ops.length > 1 ? 's' : ''}` });
  if (r && r.ids) {
    S.keys = new Set(r.ids);
    await hooks.refreshState();
    hooks.selectKey(r.ids[r.ids.length - 1], false, { keep: true });
  }
}
export function pasteKeys() {
  if (!S.clipboard) { toast('nothing copied (Ctrl+C on selected keyframes)', true); return; }
  pasteAt(snapTime(S.t), S.clipboard, 'paste');
}
export function duplicateKeys() {
  const keys = selectedKeys();
  if (!keys.length) { toast('select keyframes to duplicate', true); return; }
  const t0 = Math.min(...keys.map((k) => k.time));
  const clip = { t0, keys: keys.map((k) => Object.fromEntries(KEY_FIELDS.filter((f) => k[f] !== undefined).map((f) => [f, k[f]]))) };
  let t = snapTime(S.t);
  if (Math.abs(t - t0) < 0.5 / fps()) t = snapTime(t0 + 1 / fps());  // not on top of the originals
  pasteAt(t, clip, 'duplicate');
}
// K: a keyframe of every selected group at the current time, at its current pose (one step).
export async function keySelectedGroups() {
  const names = [...new Set([...S.groups, ...(S.selectedGroup ? [S.selectedGroup] : [])])].filter((g) => g in scene().groups);
  if (!names.length) { toast('select a group first (click it in the list or the dope sheet)', true); return; }
  const t = snapTime(S.t);
  const ops = names.map((group) => ({ op: 'add_keyframe', time: t, group, position: 'current' }));
  // the new key is selected when the edit is answered, which may come after its state and
  // frames: posing (W, E, V) meanwhile waits for it (S.keying), not poses the last key
  const keying = (async () => {
    const r = await edit(ops.length === 1 ? ops[0] : { op: 'batch', ops, label: `key ${names.length} groups` });
    if (r && r.ids) {
      S.keys = new Set(r.ids);
      await hooks.refreshState();
      hooks.selectKey(r.ids[r.ids.length - 1], false, { keep: true });
    }
  })();
  S.keying = keying;
  try { await keying; } finally { if (S.keying === keying) S.keying = null; }
}

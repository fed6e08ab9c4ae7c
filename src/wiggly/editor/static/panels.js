// The side panels (selection, groups, keyframes, physics), the dialogs and the notices bar.
import { $, S, api, hooks, act, edit, toast, scene, groupColor, currentKey } from './core.js';
import { setTime, setPlaying, updateColors } from './playback.js';
import { selectedIndices, updateSelCount } from './selection.js';

// ------------------------------------------------------------------------------------------
// dialogs

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
export async function openDialog() {
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
  const uploadLabel = document.createElement('label');
  uploadLabel.className = 'upload';
  uploadLabel.append('or upload a mesh: ', upload);
  wrap.append(input, uploadLabel);
  const label = (f) => (files.unsaved.includes(f) ? `${f}  (unsaved: recover from autosave)` : f);
  const sections = [['Scenes', [...files.unsaved, ...files.scenes]], ['Meshes', files.meshes],
                    ['Bundled models', files.builtin]];
  for (const [title, list] of sections) {
    if (!list.length) continue;
    const h = document.createElement('div');
    h.className = 'file-heading'; h.textContent = title;
    wrap.append(h);
    for (const f of list) {
      const d = document.createElement('div');
      d.className = 'file'; d.textContent = label(f);
      d.onclick = () => { input.value = f; };
      d.ondblclick = () => $('modal-ok').click();
      wrap.append(d);
    }
  }
  modal('Open a scene or a mesh', wrap, async () => {
    const r = await act(() => api.post('/api/open', { path: input.value.trim() }));
    if (!r) return false;
    selectKey(null); S.selectedGroup = null; S.groups.clear();
    return true;
  });
}
export function promptDialog(title, value, onOk) {
  const input = document.createElement('input');
  input.type = 'text'; input.value = value;
  input.onkeydown = (e) => { if (e.key === 'Enter') $('modal-ok').click(); };
  modal(title, input, () => onOk(input.value.trim()));
}

// What the server said when it opened the scene (recovered edits, an ignored journal): shown
// in a bar over the view until dismissed, once per opened scene and text, and gone when the
// server drops them (a save of recovered edits).
let noticesShown = null;
export function showNotices(d) {
  const key = JSON.stringify([d.instance, d.opened, d.notices]);
  if (noticesShown === key) return;
  noticesShown = key;
  const bar = $('notices');
  const notes = d.notices || [];
  bar.hidden = !notes.length;
  if (!notes.length) return;
  $('notices-text').textContent = notes.join('\n');
}

// ------------------------------------------------------------------------------------------
// panels

// A number short enough for a narrow field: 1e+8, not 100000000 (cut off at 72 px).
function shortNumber(x) { return Math.abs(x) >= 1e5 || (x !== 0 && Math.abs(x) < 1e-3) ? x.toExponential() : String(x); }
function keyKind(k) {
  const p = k.position;
  if (p === undefined) return 'velocity only';
  if (p === 'rest') return 'rest';
  if (p.offset) return `offset [${p.offset.map((x) => x.toFixed(3)).join(', ')}]`;
  if (p.absolute) return `absolute (${p.absolute.length} points)`;
  return `rigid: rot [${p.rotation.map((x) => x.toFixed(1)).join(', ')}]°, move [${(p.translation || [0, 0, 0]).map((x) => x.toFixed(3)).join(', ')}]`;
}
function getPath(obj, path) {
  return path.split('.').reduce((o, k) => (o == null ? undefined : o[k]), obj);
}

export function renderPanels() {
  if (!S.desc || !S.desc.open) return;
  const d = S.desc, sc = d.scene;
  $('file-name').textContent = d.path || sc.name;
  $('file-name').title = `scene file: ${d.path || sc.name}`;  // the whole name, when it is cut
  $('dirty').textContent = d.dirty ? '●' : '';
  $('btn-undo').disabled = !d.can_undo;
  $('btn-redo').disabled = !d.can_redo;
  $('btn-undo').title = d.can_undo ? `Undo ${d.undo_label} (Ctrl+Z; this tab's edits)` : 'nothing to undo in this tab';
  $('btn-redo').title = d.can_redo ? `Redo ${d.redo_label} (Ctrl+Shift+Z)` : 'nothing to redo in this tab';
  document.title = `${d.dirty ? '● ' : ''}${sc.name} — wiggly edit`;
  // groups
  const ul = $('groups');
  ul.replaceChildren();
  for (const [name, g] of Object.entries(sc.groups)) {
    const li = document.createElement('li');
    li.dataset.group = name;
    if (name === S.selectedGroup || S.groups.has(name)) li.classList.add('sel');
    const color = document.createElement('input');
    color.type = 'color'; color.value = groupColor(name); color.title = 'color';
    color.onchange = () => edit({ op: 'recolor_group', name, color: color.value });
    const label = document.createElement('span');
    label.className = 'name';
    label.textContent = `${name} (${(S.groupVerts[name] || []).length})`;
    label.title = 'click: select; Shift/Ctrl+click: select several (K keys them all); double-click: rename';
    // a refused name keeps the prompt open with what was typed (as a refused Save as does)
    label.ondblclick = () => promptDialog(`Rename group ${name}`, name, async (v) => (await edit({ op: 'rename_group', name, new_name: v })) !== null);
    const fixed = document.createElement('label');
    fixed.className = 'small'; fixed.title = 'hold these vertices at rest';
    const cb = document.createElement('input');
    cb.type = 'checkbox'; cb.checked = sc.simulation.fixed.includes(name);
    cb.onchange = () => edit({ op: 'set_fixed', name, fixed: cb.checked });
    fixed.append(cb, ' fixed');
    const young = document.createElement('input');  // a softer (or stiffer) group
    young.type = 'number'; young.step = 'any'; young.min = '0'; young.className = 'young';
    young.placeholder = 'E'; young.value = g.young === undefined ? '' : shortNumber(g.young);
    young.title = "this group's Young's modulus (Pa); empty: the material's";
    young.onchange = () => {
      const v = young.value === '' ? null : Number(young.value);
      if (v !== null && !(v > 0)) { toast(`${name}: Young's modulus must be a number > 0 Pa`, true); renderPanels(); return; }
      edit({ op: 'set_group_young', name, young: v });
    };
    const del = document.createElement('button');
    del.className = 'x'; del.textContent = '✕'; del.title = 'delete group (and its keyframes)';
    del.onclick = (e) => { e.stopPropagation(); deleteGroup(name); };
    li.onclick = (e) => {
      if (e.target !== li && e.target !== label) return;
      const add = e.shiftKey || e.ctrlKey || e.metaKey;
      selectGroup(name, { add, vertices: !add });
    };
    li.append(color, label, young, fixed, del);
    ul.append(li);
  }
  // keyframes
  const kl = $('keys');
  kl.replaceChildren();
  const keys = [...sc.keyframes].sort((a, b) => a.time - b.time);
  for (const k of keys) {
    const li = document.createElement('li');
    li.dataset.key = k.id;
    if (k.id === S.selectedKey || S.keys.has(k.id)) li.classList.add('sel');
    const sw = document.createElement('span');
    sw.className = 'swatch'; sw.style.background = groupColor(k.group);
    const label = document.createElement('span');
    label.className = 'name';
    label.textContent = `${k.time.toFixed(3)} s  ${k.name || k.group}  · ${keyKind(k).split(':')[0]}${k.velocity ? ' · v' : ''}`;
    li.onclick = (e) => {
      if (e.shiftKey || e.ctrlKey) hooks.toggleKey(k.id);
      else selectKey(k.id, true);
    };
    li.append(sw, label);
    kl.append(li);
  }
  // physics and time
  for (const el of document.querySelectorAll('[data-set]')) {
    // a field being typed in keeps its text; a box shows the scene's state even when focused
    // (a refused or undone toggle, another tab's)
    if (document.activeElement === el && el.type !== 'checkbox') continue;
    const v = getPath(sc, el.dataset.set);
    if (el.type === 'checkbox') el.checked = !!v;
    else el.value = v === undefined || v === null ? '' : v;
  }
  if (sc.time.end === undefined) document.querySelector('[data-set="time.end"]').value = sc.time_range[1];
  $('driver-toggle').hidden = !sc.drive;  // the driver ghost: [drive] scenes only
  for (const el of document.querySelectorAll('.drive-only')) el.hidden = !sc.drive;
  if (sc.drive && sc.drive.intensity === undefined) document.querySelector('[data-set="drive.intensity"]').value = 1;
  for (const el of document.querySelectorAll('.keys-only')) el.hidden = !!(sc.drive && sc.drive.physics !== 'keys');
  if (sc.mesh.scale === undefined) document.querySelector('[data-set="mesh.scale"]').value = 1;
  if (sc.mesh.resolution === undefined && sc.mesh.edge_length === undefined) document.querySelector('[data-set="mesh.resolution"]').value = d.default_resolution || '';
  if (sc.mesh.up_axis === undefined) document.querySelector('[data-set="mesh.up_axis"]').value = 'y';
  const lim = d.limits || {};
  if (lim.MAX_MODES) document.querySelector('[data-set="simulation.modes"]').max = lim.MAX_MODES;
  if (lim.MAX_NAME_LENGTH) { $('group-name').maxLength = lim.MAX_NAME_LENGTH; $('key-name').maxLength = lim.MAX_NAME_LENGTH; }
  renderKeyPanel();
  hooks.updatePoseHelpers();
  hooks.drawDopesheet();
  hooks.updatePaths();
  updateColors();
}

export function renderKeyPanel() {
  const k = currentKey();
  $('key-panel').hidden = !k;
  const many = S.keys.size > 1;
  $('keys-many').hidden = !many;
  if (many) $('keys-many').textContent = `${S.keys.size} keyframes selected: drag them in the dope sheet, Ctrl+C / Ctrl+V, Shift+D, Delete`;
  if (!k) return;
  const sel = $('key-group');
  sel.replaceChildren(...Object.keys(scene().groups).map((g) => new Option(g, g, false, g === k.group)));
  if (document.activeElement !== $('key-time')) $('key-time').value = +k.time.toFixed(6);  // a dragged key's float
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

// Select a group: alone (and its vertices, for editing it), or added to the selected groups.
export function selectGroup(name, { add = false, vertices = true } = {}) {
  if (add) {
    if (S.groups.has(name) && name !== S.selectedGroup) S.groups.delete(name);
    else { S.groups.add(name); S.selectedGroup = name; }
  } else {
    S.groups = new Set([name]);
    S.selectedGroup = name;
  }
  if (vertices && S.groupVerts[name]) {
    S.selection.fill(0);
    for (const i of S.groupVerts[name]) S.selection[i] = 1;
    $('group-name').value = name;
    updateSelCount();
  }
  renderPanels();
}
// The active keyframe (its panel, the gizmo); `keep`: keep the other selected keys.
export function selectKey(id, seek, { keep = false } = {}) {
  if (S.dragging && id !== S.selectedKey) hooks.cancelDrag();
  S.selectedKey = id;
  if (!keep) S.keys = new Set(id === null ? [] : [id]);
  else if (id !== null) S.keys.add(id);
  const k = currentKey();
  if (!k) hooks.stopPosing();
  else {
    S.selectedGroup = k.group;
    if (!keep) S.groups = new Set([k.group]);
    if (seek) { setPlaying(false); setTime(k.time); }
    if (S.posing && S.posing.id !== id) hooks.startPosing(S.posing.mode);
  }
  if (S.desc) renderPanels();
}
export async function deleteGroup(name) {
  const n = scene().keyframes.filter((k) => k.group === name).length;
  if (n && !confirm(`Delete group ${name} and its ${n} keyframe(s)?`)) return;
  await edit({ op: 'delete_group', name });
}
export async function newGroupFromSelection() {
  const idx = selectedIndices();
  if (!idx.length) { toast('select some vertices first (Brush B, Box X, Lasso L)', true); return; }
  let name = $('group-name').value.trim();
  if (!name) { let k = Object.keys(scene().groups).length + 1; while (`group${k}` in scene().groups) k++; name = `group${k}`; }
  if (name in scene().groups && !confirm(`Replace the vertices of group ${name}?`)) return;
  const r = await edit({ op: 'set_group', name, indices: idx });
  if (r) { S.selectedGroup = name; S.groups = new Set([name]); $('group-name').value = ''; S.selection.fill(0); updateSelCount(); }
}
export async function setGroupFromSelection() {
  if (!S.selectedGroup) { toast('select a group in the list first', true); return; }
  const idx = selectedIndices();
  if (!idx.length) { toast('the selection is empty', true); return; }
  await edit({ op: 'set_group', name: S.selectedGroup, indices: idx });
}

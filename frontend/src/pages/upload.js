/**
 * The upload form: motions and target characters (dropped, picked, already uploaded, or built-in bodies), what
 * the service parsed in each (joints, frames, mapping report, warnings) before anything is submitted, options,
 * then one job (1 x 1) or a batch (many x many). Uploads show their progress (XHR progress events).
 */
import { api, listAll, uploadFile } from '../api.js';
import { esc, formatBytes, formatNumber } from '../format.js';
import { rememberAsset } from '../names.js';
import { batchHash, reviewHash } from '../router.js';


export function mountUpload(root) {
  const state = { motions: [], targets: [], uploads: new Set(), alive: true, info: null };
  root.innerHTML = `<section class="upload">
    <h1>New retarget</h1>
    <form class="upload-form" novalidate>
      <div class="upload-cols">
        ${pickerHtml('motion', 'Motion', 'BVH, GLB/glTF or FBX clips. Several motions make a batch.', '.bvh,.glb,.gltf,.fbx')}
        ${pickerHtml('target', 'Target character', 'A rigged, skinned GLB/glTF/FBX, or a built-in body. Several targets make a batch.', '.glb,.gltf,.fbx')}
      </div>
      <fieldset class="options"><legend>Options</legend>
        <div class="opt-grid">
          <label>First frame <input type="number" name="frame_start" min="0" step="1" value="0"></label>
          <label title="Exclusive; empty: to the end of the clip">End frame (exclusive) <input type="number" name="frame_end" min="1" step="1" placeholder="end of the clip"></label>
          <label title="Resample to this rate; empty: the source's">Frame rate <input type="number" name="fps" min="1" max="240" step="any" placeholder="the source's"></label>
          <label>ESO iterations <input type="number" name="eso_iterations" min="0" max="1000" step="1" value="30"></label>
          <label>Source body <select name="source_character_id"><option value="">automatic (the motion's own mesh, or a body fitted to it)</option></select></label>
          <label>Device <select name="queue"><option value="">server default</option><option value="cpu">CPU</option><option value="gpu">GPU</option></select></label>
          <label class="check"><input type="checkbox" name="in_place"> In place (remove horizontal root motion)</label>
          <label class="batch-name" hidden>Batch name <input type="text" name="batch_name" maxlength="300" placeholder="optional"></label>
        </div>
        <div class="stage-switches">Stages: <span class="stage-list">loading…</span></div>
      </fieldset>
      <div class="submit-row">
        <button type="submit" class="btn primary" data-act="submit" disabled>Submit</button>
        <span class="submit-note"></span>
      </div>
    </form>
  </section>`;
  const form = root.querySelector('form');
  const submit = root.querySelector('[data-act=submit]');
  const note = root.querySelector('.submit-note');

  const refresh = () => {
    const ready = (l) => l.filter((c) => c.asset);
    const nm = ready(state.motions).length;
    const nt = ready(state.targets).length;
    const busy = state.uploads.size > 0;
    const n = nm * nt;
    submit.disabled = !n || busy;
    submit.textContent = n > 1 ? `Submit batch of ${n} jobs` : 'Submit job';
    root.querySelector('.batch-name').hidden = n <= 1;
    note.textContent = busy ? 'waiting for uploads to finish…' : !nm ? 'choose a motion' : !nt ? 'choose a target character' : '';
    for (const kind of ['motion', 'target']) renderCards(root, kind, state, refresh);
  };

  for (const kind of ['motion', 'target']) wirePicker(root, kind, state, refresh);
  loadExisting(root, state, refresh);
  loadStages(root, state);

  form.addEventListener('submit', async (e) => {
    e.preventDefault();
    if (submit.disabled) return;
    const fd = new FormData(form);
    const num = (k) => (fd.get(k) === '' || fd.get(k) == null ? null : Number(fd.get(k)));
    const options = {
      frame_start: num('frame_start') ?? 0,
      frame_end: num('frame_end'),
      fps: num('fps'),
      in_place: fd.get('in_place') === 'on',
      eso_iterations: num('eso_iterations') ?? 30,
      stages: Object.fromEntries((state.info?.stages || []).map((st) => [st.name, fd.get(`stage_${st.name}`) === 'on'])),
    };
    if (options.frame_end !== null && options.frame_end <= options.frame_start) {
      note.textContent = 'The end frame must be after the first frame.';
      return;
    }
    const motions = state.motions.filter((c) => c.asset).map((c) => c.asset.id);
    const targets = state.targets.filter((c) => c.asset).map((c) => c.asset.id);
    const common = { options, source_character_id: fd.get('source_character_id') || null, queue: fd.get('queue') || null };
    submit.disabled = true;
    note.textContent = 'submitting…';
    try {
      if (motions.length * targets.length === 1) {
        const job = await api('/v1/jobs', { method: 'POST', body: { motion_id: motions[0], target_character_id: targets[0], ...common } });
        window.location.hash = reviewHash(job.id);
      } else {
        const batch = await api('/v1/batches', { method: 'POST', body: { name: fd.get('batch_name') || null, motion_ids: motions, target_character_ids: targets, ...common } });
        window.location.hash = batchHash(batch.id);
      }
    } catch (err) {
      note.innerHTML = `<span class="error">Not submitted: ${esc(err.message)}</span>`;
      submit.disabled = false;
    }
  });
  refresh();
  return () => {
    state.alive = false;
    for (const u of state.uploads) u.abort();
  };
}

function pickerHtml(kind, title, help, accept) {
  const builtin = kind === 'target'
    ? `<label>Built-in body <select data-pick="builtin"><option value="">add a built-in body…</option></select></label>`
    : '';
  return `<fieldset class="picker" data-kind="${kind}"><legend>${title}</legend>
    <p class="help">${esc(help)}</p>
    <label class="drop" tabindex="0" data-drop="${kind}">
      <input type="file" id="${kind}-file" accept="${accept}" multiple hidden>
      <span><b>Drop files here</b> or click to choose</span>
    </label>
    <div class="pick-row">${builtin}
      <label>Uploaded before <select data-pick="existing"><option value="">add an uploaded ${kind === 'motion' ? 'motion' : 'character'}…</option></select></label>
    </div>
    <div class="cards" data-cards="${kind}"></div>
  </fieldset>`;
}

function wirePicker(root, kind, state, refresh) {
  const drop = root.querySelector(`[data-drop="${kind}"]`);
  const input = drop.querySelector('input');
  const list = kind === 'motion' ? state.motions : state.targets;
  const add = (files) => { for (const f of files) startUpload(kind, f, list, state, refresh); };
  input.addEventListener('change', () => { add([...input.files]); input.value = ''; });
  drop.addEventListener('keydown', (e) => { if (e.key === 'Enter' || e.key === ' ') { e.preventDefault(); input.click(); } });
  drop.addEventListener('dragover', (e) => { e.preventDefault(); drop.classList.add('over'); });
  drop.addEventListener('dragleave', () => drop.classList.remove('over'));
  drop.addEventListener('drop', (e) => { e.preventDefault(); drop.classList.remove('over'); add([...e.dataTransfer.files]); });
  for (const sel of root.querySelectorAll(`[data-kind="${kind}"] select[data-pick]`)) {
    sel.addEventListener('change', () => {
      const asset = sel._assets?.get(sel.value);
      if (asset && !list.some((c) => c.asset?.id === asset.id)) list.push({ key: asset.id, asset, picked: true });
      sel.value = '';
      refresh();
    });
  }
}

function startUpload(kind, file, list, state, refresh) {
  const card = { key: `${file.name}-${Math.random()}`, file, progress: 0, phase: 'uploading', asset: null, error: null };
  list.push(card);
  const path = kind === 'motion' ? '/v1/motions' : '/v1/characters';
  const up = uploadFile(path, file, {
    onProgress: (loaded, total) => { card.progress = total ? loaded / total : 0; updateCard(card); },
    onSent: () => { card.phase = 'parsing'; card.progress = 1; updateCard(card); },
  });
  card.abort = () => { card.removed = true; up.abort(); };
  state.uploads.add(up);
  refresh();
  up.promise.then((asset) => {
    card.asset = asset;
    card.phase = 'ready';
    rememberAsset(asset);
  }).catch((err) => {
    if (card.removed) return;
    card.phase = 'error';
    card.error = err.status ? `${err.message} (HTTP ${err.status})` : err.message;
  }).finally(() => {
    state.uploads.delete(up);
    if (state.alive) refresh();
  });
}

/** Update a card's progress in place (no full re-render while bytes flow). */
function updateCard(card) {
  const el = document.querySelector(`.card[data-key="${CSS.escape(card.key)}"]`);
  if (!el) return;
  el.dataset.phase = card.phase;
  const bar = el.querySelector('.progress-fill');
  if (bar) bar.style.width = `${Math.round(card.progress * 100)}%`;
  const label = el.querySelector('.progress span');
  if (label) label.textContent = card.phase === 'parsing' ? 'uploaded · the service is parsing it…' : `uploading ${Math.round(card.progress * 100)}%`;
}

function renderCards(root, kind, state, refresh) {
  const list = kind === 'motion' ? state.motions : state.targets;
  const box = root.querySelector(`[data-cards="${kind}"]`);
  // Keyed update: a card is rebuilt only when its phase changes, so open <details> elsewhere stay open.
  const existing = new Map([...box.children].map((el) => [el.dataset.key, el]));
  const keep = new Set();
  let prev = null;
  for (const c of list) {
    const phase = c.error ? 'error' : c.asset ? 'ready' : c.phase;
    let el = existing.get(c.key);
    if (!el || el.dataset.phase !== phase) {
      const tpl = document.createElement('template');
      tpl.innerHTML = cardHtml(c).trim();
      const fresh = tpl.content.firstElementChild;
      if (el) el.replaceWith(fresh);
      el = fresh;
      el.querySelector('[data-remove]').onclick = () => {
        const i = list.findIndex((x) => x.key === c.key);
        if (i >= 0) { list[i].abort?.(); list.splice(i, 1); }
        refresh();
      };
    }
    if (prev ? prev.nextElementSibling !== el : box.firstElementChild !== el) {
      if (prev) prev.after(el); else box.prepend(el);
    }
    keep.add(c.key);
    prev = el;
  }
  for (const [key, el] of existing) if (!keep.has(key)) el.remove();
}

function cardHtml(c) {
  const title = c.asset ? c.asset.name : c.file?.name;
  const size = c.file ? formatBytes(c.file.size) : c.asset?.size_bytes ? formatBytes(c.asset.size_bytes) : '';
  let inner = '';
  if (c.phase === 'uploading' || c.phase === 'parsing') {
    const pct = Math.round(c.progress * 100);
    inner = `<div class="progress running"><div class="progress-fill" style="width:${pct}%"></div><span>${c.phase === 'parsing' ? 'uploaded · the service is parsing it…' : `uploading ${pct}%`}</span></div>`;
  } else if (c.error) {
    inner = `<div class="error-box">Rejected: ${esc(c.error)}</div>`;
  } else if (c.asset) {
    inner = assetInfoHtml(c.asset);
  }
  const phase = c.error ? 'error' : c.asset ? 'ready' : c.phase;
  return `<div class="card" data-key="${esc(c.key)}" data-phase="${phase}" data-asset="${esc(c.asset?.id || '')}">
    <div class="card-head"><b>${esc(title)}</b> <small>${esc(size)} ${c.asset?.builtin ? 'built-in body' : c.picked ? 'uploaded before' : ''}</small>
      <button type="button" class="icon" data-remove="${esc(c.key)}" title="Remove" aria-label="Remove">✕</button></div>
    ${inner}</div>`;
}

/** What the parser found in an asset: counts, mapping report, warnings. */
export function assetInfoHtml(asset) {
  const i = asset.info || {};
  if (asset.builtin) {
    return `<p class="facts">Built-in MakeHuman body <code>${esc(asset.id)}</code> (22-joint skin), generated by a worker on first use.</p>`;
  }
  const facts = [];
  if (i.format) facts.push(['format', String(i.format).toUpperCase()]);
  if (i.joint_count != null || Array.isArray(i.joints)) facts.push(['joints', i.joint_count ?? i.joints.length]);
  if (i.frames != null) facts.push(['frames', i.frames]);
  if (i.fps != null) facts.push(['fps', formatNumber(i.fps)]);
  if (i.duration_s != null) facts.push(['duration', `${formatNumber(i.duration_s)} s`]);
  if (i.vertices != null) facts.push(['vertices', i.vertices]);
  if (i.triangles != null) facts.push(['triangles', i.triangles]);
  if (i.height_m != null) facts.push(['height', `${formatNumber(i.height_m)} m`]);
  if (i.has_mesh != null) facts.push(['mesh', i.has_mesh ? 'yes' : 'no']);
  if (Array.isArray(i.clips) && i.clips.length > 1) facts.push(['clips', i.clips.length]);
  const m = i.mapping || {};
  const joints = m.joints || {};
  const rows = Object.entries(joints).map(([canon, v]) => {
    const conf = typeof v?.confidence === 'number' ? v.confidence : null;
    const cls = conf === null ? '' : conf >= 0.9 ? 'good' : conf >= 0.7 ? 'fair' : 'poor';
    return `<tr class="${cls}"><td>${esc(canon)}</td><td><code>${esc(v?.joint ?? v)}</code></td><td>${conf === null ? '' : Math.round(conf * 100) + '%'}</td><td>${esc(v?.method ?? '')}</td></tr>`;
  }).join('');
  const missing = [...(m.missing_required || []).map((j) => `<b>${esc(j)}</b> (required)`), ...(m.missing_optional || []).map(esc)];
  const warnings = [...new Set([...(i.warnings || []), ...(m.warnings || [])])];
  const overall = typeof m.overall_confidence === 'number' ? `${Math.round(m.overall_confidence * 100)}%` : '';
  return `<dl class="facts">${facts.map(([k, v]) => `<div><dt>${esc(k)}</dt><dd>${esc(v)}</dd></div>`).join('')}</dl>
    ${rows ? `<details class="mapping"><summary>Joint mapping: ${Object.keys(joints).length} of 22 canonical joints${overall ? `, confidence ${overall}` : ''}${missing.length ? ` · missing ${missing.length}` : ''}</summary>
      <table><thead><tr><th>canonical</th><th>joint in file</th><th>conf.</th><th>by</th></tr></thead><tbody>${rows}</tbody></table>
      ${missing.length ? `<p>Missing: ${missing.join(', ')}</p>` : ''}</details>` : ''}
    ${extrasHtml(m.extras)}
    ${Array.isArray(i.joints) && i.joints.length ? `<details class="joints"><summary>All ${i.joints.length} joints</summary><p>${i.joints.map((j) => `<code>${esc(j)}</code>`).join(' ')}</p></details>` : ''}
    ${warnings.length ? `<ul class="warnings">${warnings.map((w) => `<li>${esc(w)}</li>`).join('')}</ul>` : '<p class="ok">No warnings.</p>'}`;
}

/** The extra joints of a mapping report (fingers, toes, twist bones): joint, confidence, how found, twist share. */
export function extrasHtml(extras) {
  const entries = Object.entries(extras || {});
  if (!entries.length) return '<p class="extras-none">No fingers, toes or twist bones found: hands and feet are carried as single joints.</p>';
  const count = (kind) => entries.filter(([, v]) => v?.kind === kind).length;
  const rows = entries.map(([name, v]) => {
    const conf = typeof v?.confidence === 'number' ? v.confidence : null;
    const cls = conf === null ? '' : conf >= 0.9 ? 'good' : conf >= 0.7 ? 'fair' : 'poor';
    const share = typeof v?.share === 'number' ? ` · share ${formatNumber(v.share)}` : '';
    return `<tr class="${cls}" data-extra="${esc(name)}"><td>${esc(name)}</td><td><code>${esc(v?.joint ?? '')}</code></td><td>${conf === null ? '' : Math.round(conf * 100) + '%'}</td><td>${esc(v?.method ?? '')}${share}</td></tr>`;
  }).join('');
  return `<details class="mapping extras"><summary>Fingers, toes, twist bones: ${count('finger')} finger, ${count('toe')} toe, ${count('twist')} twist joints</summary>
      <table><thead><tr><th>extra joint</th><th>joint in file</th><th>conf.</th><th>by</th></tr></thead><tbody>${rows}</tbody></table></details>`;
}

/** The stage switches, in pipeline order, from /v1/info (the service's one list of stages). */
async function loadStages(root, state) {
  const list = root.querySelector('.stage-list');
  try {
    state.info = await api('/v1/info');
  } catch {
    list.textContent = 'unavailable (the service did not answer)';
    return;
  }
  if (!state.alive) return;
  list.innerHTML = state.info.stages.map((st) => {
    const title = st.available ? st.description : `${st.description} (not available in this version)`;
    const on = st.default && st.available ? ' checked' : '';
    const off = st.available ? '' : ' disabled';
    return `<label class="check" title="${esc(title)}"><input type="checkbox" name="stage_${esc(st.name)}"${on}${off}> ${esc(st.label)}</label>`;
  }).join('');
}

async function loadExisting(root, state, refresh) {
  let motions = [];
  let characters = [];
  try {
    [motions, characters] = await Promise.all([listAll('/v1/motions', 500), listAll('/v1/characters', 500)]);
  } catch {
    return; // the key prompt or the error banner says why
  }
  if (!state.alive) return;
  for (const a of [...motions, ...characters]) rememberAsset(a);
  const fill = (sel, assets) => {
    sel._assets = new Map(assets.map((a) => [a.id, a]));
    sel.insertAdjacentHTML('beforeend', assets.map((a) => `<option value="${esc(a.id)}">${esc(a.name)}${a.format ? ` (${esc(a.format)})` : ''}</option>`).join(''));
  };
  fill(root.querySelector('[data-kind=motion] [data-pick=existing]'), motions);
  fill(root.querySelector('[data-kind=target] [data-pick=existing]'), characters.filter((c) => !c.builtin));
  fill(root.querySelector('[data-kind=target] [data-pick=builtin]'), characters.filter((c) => c.builtin));
  const src = root.querySelector('select[name=source_character_id]');
  src.insertAdjacentHTML('beforeend', characters.map((a) => `<option value="${esc(a.id)}">${esc(a.name)}${a.builtin ? ' (built-in)' : ''}</option>`).join(''));
  refresh();
}

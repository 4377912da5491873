/**
 * The single-file viewer: drop any GLB (or glTF with embedded data), see the Khronos validator's report and the
 * model with its animations on a timeline. Works without an API key: nothing is uploaded.
 */
import { esc, formatBytes } from '../format.js';
import { validateGltf, SEVERITY } from '../validator.js';
import { bindKeys, mountControls } from '../viewer/controls.js';
import { parseGltf } from '../viewer/loadglb.js';
import { ModelView } from '../viewer/modelview.js';
import { Timeline } from '../viewer/timeline.js';

export function mountFileView(root) {
  const state = { cleanup: null };
  root.innerHTML = `<section class="fileview">
    <div class="fileview-side">
      <h1>GLB viewer</h1>
      <p class="help">Drop a .glb or .gltf (embedded data) to check it with the Khronos glTF validator and play its
        animations. The file stays in your browser.</p>
      <label class="drop" tabindex="0" data-drop="file"><input type="file" id="glb-file" accept=".glb,.gltf" hidden>
        <span><b>Drop a GLB here</b> or click to choose</span></label>
      <div class="validation"></div>
      <div class="file-info"></div>
    </div>
    <div class="fileview-main"><div class="view single" data-view="file"><div class="view-box"><div class="view-status">no file yet</div></div></div>
      <div class="controls-bar"></div></div>
  </section>`;
  const drop = root.querySelector('[data-drop]');
  const input = drop.querySelector('input');
  const open = (file) => { if (file) showFile(root, file, state); };
  input.addEventListener('change', () => { open(input.files[0]); input.value = ''; });
  drop.addEventListener('keydown', (e) => { if (e.key === 'Enter' || e.key === ' ') { e.preventDefault(); input.click(); } });
  // Dropping anywhere on the page works too.
  const over = (e) => { e.preventDefault(); drop.classList.add('over'); };
  const leave = () => drop.classList.remove('over');
  const dropped = (e) => { e.preventDefault(); leave(); open(e.dataTransfer.files[0]); };
  root.addEventListener('dragover', over);
  root.addEventListener('dragleave', leave);
  root.addEventListener('drop', dropped);
  return () => { state.cleanup?.(); };
}

async function showFile(root, file, state) {
  state.cleanup?.();
  state.cleanup = null;
  const val = root.querySelector('.validation');
  const info = root.querySelector('.file-info');
  const fig = root.querySelector('.view[data-view=file]');
  const box = fig.querySelector('.view-box');
  box.innerHTML = '<div class="view-status">reading…</div>';
  const bar = root.querySelector('.controls-bar');
  bar.innerHTML = '';
  bar.className = 'controls-bar';
  fig.dataset.loaded = 'false';
  val.innerHTML = `<p>Validating <b>${esc(file.name)}</b> (${formatBytes(file.size)})…</p>`;
  info.innerHTML = '';
  const buffer = await file.arrayBuffer();
  const validation = validateGltf(buffer, file.name).then((r) => renderValidation(val, file.name, r))
    .catch((e) => { val.innerHTML = `<div class="error-box">The validator could not read ${esc(file.name)}: ${esc(e.message || e)}</div>`; val.dataset.done = 'error'; });
  let gltf;
  try {
    gltf = await parseGltf(buffer);
  } catch (e) {
    box.innerHTML = `<div class="view-status error">three.js could not load it: ${esc(e.message)}</div>`;
    await validation;
    return;
  }
  box.innerHTML = '';
  const view = new ModelView(box, { name: 'file' });
  const timing = view.setModel(gltf, 0);
  const timeline = new Timeline(timing?.frames ?? 1, timing?.fps ?? 30);
  view.frameBox(view.motionBounds().world);
  const clips = gltf.animations;
  info.innerHTML = `<dl class="facts"><div><dt>clips</dt><dd>${clips.length}</dd></div>
      <div><dt>skinned meshes</dt><dd>${view.skinned.length}</dd></div>
      <div><dt>vertices</dt><dd>${view.skinned.concat([]).reduce((n, m) => n + m.geometry.attributes.position.count, 0)}</dd></div>
      <div><dt>bones</dt><dd>${view.skinned[0]?.skeleton.bones.length ?? 0}</dd></div></dl>
    ${clips.length > 1 ? `<label>Clip <select data-act="clip">${clips.map((c, i) => `<option value="${i}">${esc(c.name || `clip ${i}`)}</option>`).join('')}</select></label>` : ''}`;
  const clipSel = info.querySelector('[data-act=clip]');
  if (clipSel) clipSel.onchange = () => {
    view.setClip(clips, Number(clipSel.value));
    timeline.pause();
    timeline.setLength(view.frames, view.fps);
    timeline.seek(0);
    view.setFrame(0);
    update();
  };
  fig.dataset.loaded = 'true';
  const update = mountControls(root.querySelector('.controls-bar'), timeline, [
    { id: 'skeleton', label: 'Skeleton', checked: false, onChange: (on) => view.setSkeleton(on) },
  ]);
  timeline.on((f) => { view.setFrame(f); update(); });
  const unbind = bindKeys(timeline);
  let raf = requestAnimationFrame(function loop(now) {
    timeline.tick(now);
    view.render();
    raf = requestAnimationFrame(loop);
  });
  window.__fileviewer = { timeline, view };
  state.cleanup = () => { cancelAnimationFrame(raf); unbind(); view.dispose(); delete window.__fileviewer; };
  await validation;
}

function renderValidation(el, name, r) {
  const ok = r.numErrors === 0;
  const rows = r.messages.map((m) => `<tr class="sev-${SEVERITY[m.severity] || m.severity}"><td>${esc(SEVERITY[m.severity] || m.severity)}</td>
    <td><code>${esc(m.code)}</code></td><td>${esc(m.message)}</td><td><code>${esc(m.pointer ?? (m.offset != null ? `@${m.offset}` : ''))}</code></td></tr>`).join('');
  el.innerHTML = `<div class="validation-summary ${ok ? 'ok' : 'bad'}" data-errors="${r.numErrors}" data-warnings="${r.numWarnings}">
      <b>${ok ? '✓ valid glTF' : '✗ invalid glTF'}</b>: ${r.numErrors} errors, ${r.numWarnings} warnings, ${r.numInfos} infos, ${r.numHints} hints
      <small>(Khronos glTF validator ${esc(r.validatorVersion)}${r.truncated ? ', first issues only' : ''})</small></div>
    ${r.info ? `<p class="help">${esc(r.info.generator || 'unknown generator')} · glTF ${esc(r.info.version || '?')} · ${r.info.animationCount ?? 0} animations · ${r.info.totalVertexCount ?? '?'} vertices</p>` : ''}
    ${rows ? `<div class="issues-wrap"><table class="issues"><thead><tr><th>severity</th><th>code</th><th>message</th><th>where</th></tr></thead><tbody>${rows}</tbody></table></div>` : ''}`;
  el.dataset.done = ok ? 'valid' : 'invalid';
}

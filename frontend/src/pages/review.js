/**
 * The review viewer of one job: source | before | after side by side on one frame-locked timeline, linked
 * cameras, skeleton overlay, contact markers, penetration highlights, per-frame charts with a playhead, summary
 * numbers before | after, downloads. While the job runs, its live progress; the viewer opens when it succeeds.
 *
 * Test hook: window.__viewer (frame, frames, views' frames, seek/play/pause) and data attributes on the views
 * (data-frame, data-loaded, data-renders) and charts (data-has-data, data-points, data-playhead).
 */
import { Vector3 } from 'three';
import { api, download, fetchBytes, ApiError } from '../api.js';
import { esc, formatNumber } from '../format.js';
import { activePairs, readMetrics } from '../metrics.js';
import { reviewLinkUrl, shareUrl } from '../router.js';
import { Chart, COLORS } from '../viewer/charts.js';
import { bindKeys, mountControls } from '../viewer/controls.js';
import { cloneGltf, parseGltf, sameBytes } from '../viewer/loadglb.js';
import { ModelView } from '../viewer/modelview.js';
import { Timeline } from '../viewer/timeline.js';
import { jobProgressHtml, jobTitle } from './jobs_common.js';
import { loadNames } from '../names.js';

const VIEWS = [
  { name: 'source', title: 'Source', sub: 'the motion on its source body', file: 'source.glb', link: 'source_glb' },
  { name: 'before', title: 'Before', sub: 'plain copy (baseline)', file: 'before.glb', link: 'before_glb' },
  { name: 'after', title: 'After', sub: 'our result', file: 'result.glb', link: 'result_glb' },
];
const DOWNLOADS = [
  ['result_glb', 'result.glb'], ['before_glb', 'before.glb'], ['source_glb', 'source.glb'], ['metrics_json', 'metrics.json'],
];
const CONTACT_COLOR = 0xff4f7a;
const FOOT_COLOR = 0x3ddc84;

/**
 * Mount the page; returns its cleanup. With ``token`` (a read-only review link, #/review/<token>) the job is
 * read from /v1/review/<token> without an API key, and only downloads are offered.
 */
export function mountReview(root, jobId, { token = null } = {}) {
  const state = { alive: true, cleanups: [], timer: null };
  const shared = token !== null;
  const source = shared ? `/v1/review/${encodeURIComponent(token)}` : `/v1/jobs/${encodeURIComponent(jobId)}`;
  root.innerHTML = `<section class="review" data-job="${esc(jobId || '')}" data-shared="${shared}">
    <header class="review-head"><div class="review-title"><h1>${shared ? 'Review' : `Job <code>${esc(jobId)}</code>`}</h1><span class="review-sub"></span></div>
      <div class="review-actions"></div></header>
    <div class="review-body"><div class="loading">Loading job…</div></div>
  </section>`;
  const body = root.querySelector('.review-body');
  const sub = root.querySelector('.review-sub');
  const actions = root.querySelector('.review-actions');

  const poll = async () => {
    if (!state.alive) return;
    let job;
    try {
      job = await api(source);
      if (shared) job = { ...job, id: job.job_id };
    } catch (e) {
      body.innerHTML = `<div class="error-box">Cannot load the job: ${esc(e.message)}</div>`;
      if (!(e instanceof ApiError) || e.status === 0 || e.status >= 500) state.timer = setTimeout(poll, 3000);
      return;
    }
    if (!state.alive) return;
    if (shared) {
      sub.textContent = `job ${job.id} · read-only link, valid until ${new Date(job.expires_at).toLocaleString()}`;
      root.querySelector('.review').dataset.job = job.id;
    } else {
      const names = await loadNames([job.motion_id], [job.target_character_id]);
      sub.textContent = jobTitle(job, names);
    }
    if (job.status === 'succeeded') {
      await openViewer(job);
      return;
    }
    body.innerHTML = `<div class="job-live">${jobProgressHtml(job)}</div>`;
    if (job.status === 'queued' || job.status === 'running') state.timer = setTimeout(poll, 1000);
  };

  const openViewer = async (job) => {
    renderActions(actions, job, shared);
    body.innerHTML = `<div class="review-grid">
      <div class="review-main">
        <div class="views">${VIEWS.map((v) => `<figure class="view" data-view="${v.name}">
          <figcaption><b>${v.title}</b> <span>${v.sub}</span><span class="view-frame"></span></figcaption>
          <div class="view-box"><div class="view-status">loading…</div></div></figure>`).join('')}</div>
        <div class="controls-bar"></div>
      </div>
      <aside class="review-side">
        <div class="charts"><div class="charts-legend"><span style="color:${COLORS.before}">━ before</span> <span style="color:${COLORS.after}">━ after</span> <span class="hint">click a chart to jump to a frame</span></div></div>
        <div class="side-col"><div class="summary"></div><div class="stage-reports"></div><div class="notes"></div></div>
      </aside></div>`;
    const results = job.results || {};
    const metricsP = results.metrics_json
      ? fetchBytes(results.metrics_json).then((b) => JSON.parse(new TextDecoder().decode(b))).catch(() => null)
      : Promise.resolve(null);
    const bytes = await Promise.all(VIEWS.map((v) => (results[v.link]
      ? fetchBytes(results[v.link]).catch((e) => ({ error: e.message }))
      : Promise.resolve(null))));
    const report = await metricsP;
    if (!state.alive) return;
    const metrics = readMetrics(report);
    const cleanup = await buildViewer(body, job, VIEWS.map((v, i) => ({ ...v, bytes: bytes[i] })), metrics);
    if (state.alive) state.cleanups.push(cleanup);
    else cleanup();
  };

  poll();
  return () => {
    state.alive = false;
    clearTimeout(state.timer);
    for (const c of state.cleanups) c?.();
  };
}

function renderActions(el, job, shared = false) {
  const r = job.results || {};
  el.innerHTML = `${DOWNLOADS.filter(([k]) => r[k]).map(([k, f]) => `<button type="button" class="btn small" data-dl="${k}" data-file="${f}">⤓ ${f}</button>`).join('')}
    ${shared ? '' : `<button type="button" class="btn small ghost" data-act="share" title="Copy a link to this review (it does not contain your API key; the reader needs their own)">Copy review link</button>
    <button type="button" class="btn small ghost" data-act="readonly" title="Make a link anyone can open without a key: this review and its downloads only, read-only, expiring (revocable with the API)">Share read-only link</button>`}
    <span class="share-note"></span>`;
  for (const b of el.querySelectorAll('[data-dl]')) {
    b.onclick = async () => {
      b.disabled = true;
      try { await download(r[b.dataset.dl], `${job.id}-${b.dataset.file}`); } catch (e) { alert(`Download failed: ${e.message}`); }
      b.disabled = false;
    };
  }
  if (shared) return;
  el.querySelector('[data-act=readonly]').onclick = async (ev) => {
    const note = el.querySelector('.share-note');
    ev.target.disabled = true;
    try {
      const link = await api(`/v1/jobs/${encodeURIComponent(job.id)}/review-links`, { method: 'POST', body: {} });
      const url = reviewLinkUrl(window.location, link.token);
      note.dataset.url = url;
      note.dataset.readonly = 'true';
      try { await navigator.clipboard.writeText(url); note.textContent = `read-only link copied (valid until ${new Date(link.expires_at).toLocaleString()})`; } catch { note.textContent = url; }
    } catch (e) {
      note.textContent = `Could not make a link: ${e.message}`;
    }
    ev.target.disabled = false;
  };
  el.querySelector('[data-act=share]').onclick = async () => {
    const url = shareUrl(window.location, job.id);
    const note = el.querySelector('.share-note');
    try { await navigator.clipboard.writeText(url); note.textContent = 'link copied'; } catch { note.textContent = url; }
    note.dataset.url = url;
  };
}

/** Build the three views, timeline, charts and summary; returns a cleanup. */
async function buildViewer(body, job, views, metrics) {
  const timeline = new Timeline(metrics.frames || 1, metrics.fps || 30);
  const mv = {};
  const loaded = [];
  const parsed = [];
  for (const v of views) {
    const fig = body.querySelector(`.view[data-view="${v.name}"]`);
    const box = fig.querySelector('.view-box');
    const status = box.querySelector('.view-status');
    if (!v.bytes || v.bytes.error) {
      status.textContent = v.bytes?.error
        ? `could not load ${v.file}: ${v.bytes.error}`
        : v.name === 'source' ? 'no source view for this job (the service did not write source.glb)' : `no ${v.file} for this job`;
      fig.dataset.loaded = 'false';
      fig.classList.add('missing');
      continue;
    }
    const twin = parsed.find((p) => sameBytes(p.bytes, v.bytes));
    let gltf;
    try {
      gltf = twin ? cloneGltf(twin.gltf) : await parseGltf(v.bytes);
    } catch (e) {
      status.textContent = `${v.file} could not be read: ${e.message}`;
      fig.dataset.loaded = 'false';
      continue;
    }
    if (!twin) parsed.push({ bytes: v.bytes, gltf });
    status.remove();
    const view = new ModelView(box, { name: v.name });
    fig.dataset.view = v.name;
    const timing = view.setModel(gltf);
    mv[v.name] = { view, fig, timing };
    loaded.push(view);
  }
  // The timeline: the metrics' frame count when known, else the longest clip.
  const timings = Object.values(mv).map((m) => m.timing).filter(Boolean);
  if (timings.length) {
    const frames = metrics.frames || Math.max(...timings.map((t) => t.frames));
    const fps = metrics.fps || (mv.after?.timing ?? timings[0]).fps;
    timeline.setLength(frames, fps);
  }
  // One camera framing for all: the union of the motion's bounds in every view; following the root, the union
  // of the root-relative bounds (a tighter view that stays on the character).
  const opts = { skeleton: false, contacts: true, penetration: true, linked: true, follow: true, focus: '' };
  const bounds = loaded.map((v) => v.motionBounds());
  const frameAll = () => {
    if (!loaded.length) return;
    const box = bounds[0][opts.follow ? 'local' : 'world'].clone();
    for (const b of bounds.slice(1)) box.union(b[opts.follow ? 'local' : 'world']);
    for (const v of loaded) {
      v.followOffset = null;
      v.frameBox(box);
      if (opts.follow) {
        // frameBox aimed at the root-relative box around the origin: move each view onto its own character.
        const root = v.rootPosition(new Vector3());
        root.y = 0;
        v.controls.target.add(root);
        v.camera.position.add(root);
        v.follow(true);
      }
    }
  };
  frameAll();
  // Linked cameras: any view's orbit moves the others.
  let syncing = false;
  for (const v of loaded) {
    v.controls.addEventListener('change', () => {
      v.dirty = true;
      if (!opts.linked || syncing) return;
      syncing = true;
      for (const o of loaded) if (o !== v) o.copyCamera(v, opts.follow);
      syncing = false;
    });
    v.controls.addEventListener('end', () => { if (opts.follow) for (const o of loaded) { o.followOffset = null; o.follow(true); } });
  }
  // Charts.
  const chartsEl = body.querySelector('.charts');
  const charts = metrics.charts.map((c) => {
    const box = document.createElement('div');
    chartsEl.appendChild(box);
    return new Chart(box, c, timeline);
  });
  if (!metrics.hasSeries) {
    const p = document.createElement('p');
    p.className = 'no-data';
    p.dataset.noSeries = 'true';
    p.textContent = metrics.schema
      ? `No per-frame data for this job (metrics schema ${metrics.schema} has no series).`
      : 'No metrics for this job.';
    chartsEl.appendChild(p);
  }
  renderSummary(body.querySelector('.summary'), metrics);
  renderStages(body.querySelector('.stage-reports'), metrics);
  renderSourceQuality(body.querySelector('.view[data-view="source"] .view-box'), metrics.source);
  renderNotes(body.querySelector('.notes'), job, metrics);

  const hasPen = Boolean(metrics.penetration.before || metrics.penetration.after);
  const hasContacts = Boolean(metrics.contacts.pairs.length || metrics.contacts.vertexPairs
    || Object.keys(metrics.contacts.feet.before).length || Object.keys(metrics.contacts.feet.after).length);
  const focusBone = (name, view) => (opts.focus ? boneFor(view, metrics.mapping[name === 'source' ? 'source' : 'target'], opts.focus) : null);
  const applyFrame = (f) => {
    for (const [name, m] of Object.entries(mv)) {
      m.view.setFrame(f);
      const bone = focusBone(name, m.view);
      if (bone) m.view.focusOn(bone, FOCUS_DISTANCE);
      else m.view.follow(opts.follow);
      m.fig.querySelector('.view-frame').textContent = `frame ${m.view.frame}`;
    }
    updateOverlays(mv, metrics, f, opts);
    for (const c of charts) c.draw(f);
  };
  const updateControls = mountControls(body.querySelector('.controls-bar'), timeline, [
    { id: 'skeleton', label: 'Skeleton', checked: opts.skeleton, title: 'Draw the bones over the meshes', onChange: (on) => { opts.skeleton = on; for (const v of loaded) v.setSkeleton(on); } },
    { id: 'contacts', label: 'Contacts', checked: opts.contacts && hasContacts, disabled: !hasContacts, title: hasContacts ? 'Markers on detected hand and foot contacts' : 'no contact data for this job', onChange: (on) => { opts.contacts = on; applyFrame(timeline.frame); } },
    { id: 'penetration', label: 'Penetration', checked: opts.penetration && hasPen, disabled: !hasPen, title: hasPen ? 'Penetrating vertices in red' : 'no penetration data for this job', onChange: (on) => { opts.penetration = on; applyFrame(timeline.frame); } },
    { id: 'follow', label: 'Follow', checked: opts.follow, title: 'Cameras follow each character (off: one fixed camera over the whole motion)', onChange: (on) => { opts.follow = on; timeline.pause(); frameAll(); applyFrame(timeline.frame); } },
    { id: 'linked', label: 'Link cameras', checked: opts.linked, title: 'Orbit all views together', onChange: (on) => { opts.linked = on; if (on && loaded.length) for (const o of loaded.slice(1)) o.copyCamera(loaded[0], opts.follow); } },
  ]);
  mountFocus(body.querySelector('.controls-bar'), (joint) => {
    opts.focus = joint;
    if (!joint) frameAll();
    applyFrame(timeline.frame);
  });
  timeline.on((f) => { applyFrame(f); updateControls(); });
  applyFrame(0);
  const unbindKeys = bindKeys(timeline);

  let raf = 0;
  const loop = (now) => {
    timeline.tick(now);
    for (const v of loaded) v.render();
    raf = requestAnimationFrame(loop);
  };
  raf = requestAnimationFrame(loop);

  window.__viewer = {
    jobId: job.id,
    timeline,
    get frame() { return timeline.frame; },
    get frames() { return timeline.frames; },
    get fps() { return timeline.fps; },
    get playing() { return timeline.playing; },
    views() {
      const out = {};
      for (const v of VIEWS) {
        const m = mv[v.name];
        if (!m) { out[v.name] = { loaded: false }; continue; }
        const cam = m.view.camera.position.distanceTo(m.view.controls.target);
        const bone = focusBone(v.name, m.view);
        const offset = bone ? bone.getWorldPosition(new Vector3()).distanceTo(m.view.controls.target) : null;
        out[v.name] = { loaded: true, frame: m.view.frame, renders: m.view.renders, camera: { distance: cam, focus: opts.focus, offset } };
      }
      return out;
    },
    charts() {
      return charts.map((c) => ({ id: c.data.id, hasData: c.hasData, points: Number(c.container.dataset.points), playhead: c.frame, mode: c.mode, parts: Boolean(c.data.parts) }));
    },
    seek(f) { timeline.pause(); timeline.seek(f); },
    play() { timeline.play(); },
    pause() { timeline.pause(); },
    ready: true,
  };
  body.querySelector('.review-grid').dataset.ready = 'true';

  return () => {
    cancelAnimationFrame(raf);
    unbindKeys();
    timeline.pause();
    for (const c of charts) c.dispose();
    for (const v of loaded) v.dispose();
    if (window.__viewer?.timeline === timeline) delete window.__viewer;
  };
}

// The focus menu: a close camera on one joint in every view (fingers are judged on the hands).
const FOCUS_DISTANCE = 0.35;
const FOCUS = [['', 'Whole body'], ['LeftHand', 'Left hand'], ['RightHand', 'Right hand'], ['Head', 'Head'],
  ['LeftFoot', 'Left foot'], ['RightFoot', 'Right foot']];

/** The bone of canonical joint `canon` in a view: by its own name, else by the mapping report's joint name. */
function boneFor(view, mapping, canon) {
  return view.bone(canon) || view.bone(mapping?.[canon]);
}

/** Adds the focus menu to the controls bar; `onChange(joint)` with '' for the whole body. */
function mountFocus(bar, onChange) {
  const label = document.createElement('label');
  label.className = 'focus';
  label.title = 'Close camera on one joint in every view (the hands: to judge the fingers)';
  label.innerHTML = `focus <select data-act="focus">${FOCUS.map(([v, t]) => `<option value="${v}">${t}</option>`).join('')}</select>`;
  label.querySelector('select').addEventListener('change', (e) => onChange(e.target.value));
  bar.appendChild(label);
}

/** Contact markers and penetration highlights of frame `f` in every view. */
function updateOverlays(mv, metrics, f, opts) {
  const { contacts, mapping, penetration } = metrics;
  for (const [name, m] of Object.entries(mv)) {
    const view = m.view;
    const points = [];
    const lines = [];
    const side = name === 'source' ? 'source' : 'target';
    const boneOf = (canon) => view.bone(canon) || view.bone(mapping[side]?.[canon]);
    if (opts.contacts) {
      const vp = contacts.vertexPairs;
      const rows = vp?.byFrame.get(f);
      if (rows) {
        const [ki, kj] = name === 'source' ? ['source_i', 'source_j'] : ['target_i', 'target_j'];
        for (const r of rows) {
          const a = view.vertexPosition(vp[ki][r]);
          const b = view.vertexPosition(vp[kj][r]);
          if (a && b) {
            points.push({ position: a, color: CONTACT_COLOR, size: 0.6 }, { position: b, color: CONTACT_COLOR, size: 0.6 });
            lines.push({ a, b, color: CONTACT_COLOR });
          }
        }
      } else {
        for (const p of activePairs(contacts.pairs, f)) {
          const a = boneOf(p.hand);
          const b = boneOf(p.other);
          if (!a) continue;
          const pa = a.getWorldPosition(new Vector3());
          points.push({ position: pa, color: CONTACT_COLOR });
          if (b) {
            const pb = b.getWorldPosition(new Vector3());
            points.push({ position: pb, color: CONTACT_COLOR, size: 0.7 });
            lines.push({ a: pa, b: pb, color: CONTACT_COLOR });
          }
        }
      }
      const feet = name === 'source' ? null : contacts.feet[name];
      for (const [canon, labels] of Object.entries(feet || {})) {
        if (!labels[f]) continue;
        const bone = boneOf(canon);
        if (bone) points.push({ position: bone.getWorldPosition(new Vector3()), color: FOOT_COLOR, size: 1.2 });
      }
    }
    view.setMarkers(points, lines);
    m.fig.dataset.markers = String(points.length);
    if (name !== 'source') {
      const pen = opts.penetration ? penetration[name]?.get(f) : null;
      view.highlight(pen ? pen.vertex : null);
      m.fig.dataset.penetrating = String(pen ? pen.vertex.length : 0);
    }
  }
}

function renderSummary(el, metrics) {
  if (!metrics.summary.length) {
    el.innerHTML = `<h2>Summary</h2><p class="no-data" data-no-summary="true">No summary numbers for this job${metrics.schema ? ` (metrics schema ${esc(metrics.schema)})` : ''}.</p>`;
    return;
  }
  const rows = metrics.summary.map((r) => `<tr data-key="${esc(r.key)}" class="${r.verdict || ''}">
      <th scope="row">${esc(r.label)}<small>${esc(r.unit)}</small></th>
      <td>${formatNumber(r.before)}</td><td>${formatNumber(r.after)}</td>
      <td class="delta">${r.delta === null ? '' : (r.delta > 0 ? '+' : '') + formatNumber(r.delta)}</td></tr>`).join('');
  el.innerHTML = `<h2>Summary</h2><table class="summary-table">
    <thead><tr><th></th><th style="color:${COLORS.before}">before</th><th style="color:${COLORS.after}">after</th><th>change</th></tr></thead>
    <tbody>${rows}</tbody></table>`;
}

/** What each refinement stage changed (context.stage_reports): frames changed, seconds, its own figures. */
function renderStages(el, metrics) {
  if (!metrics.stages.length) {
    el.innerHTML = '<p class="no-data" data-no-stages="true">No refinement stage ran: after is the copy baseline.</p>';
    return;
  }
  const items = metrics.stages.map((st) => `<li data-stage="${esc(st.name)}"><b>${esc(st.name)}</b>
      ${st.framesChanged === null ? '' : `<span data-frames-changed="${st.framesChanged}">${formatNumber(st.framesChanged)} frames changed</span>`}
      ${st.seconds === null ? '' : `<small>${formatNumber(st.seconds)} s</small>`}
      ${st.figures.length ? `<details><summary>figures</summary><table>${st.figures.map(([k, v]) => `<tr><th scope="row">${esc(k.replaceAll('_', ' '))}</th><td>${typeof v === 'boolean' ? (v ? 'yes' : 'no') : formatNumber(v)}</td></tr>`).join('')}</table></details>` : ''}</li>`).join('');
  el.innerHTML = `<h2>Stages</h2><ul class="stage-report-list">${items}</ul>`;
}

/**
 * The source pane's list of what came in broken (metrics' `source`: the source measured on its own body): the
 * flags in words, and the figures on demand. Drawn over the bottom of the source view, so the layout stays.
 */
function renderSourceQuality(box, source) {
  if (!box || !source) return;
  const el = document.createElement('div');
  el.className = `source-quality ${source.flags.length ? 'flagged' : 'clean'}`;
  el.dataset.flags = String(source.flags.length);
  const figures = source.figures.map((f) => `<li data-key="${esc(f.key)}">${esc(f.label)}: <b>${formatNumber(f.value)}</b> ${esc(f.unit)}</li>`).join('');
  const head = source.flags.length
    ? `⚠ ${source.flags.length} problem${source.flags.length > 1 ? 's' : ''} in the source itself (not caused by retargeting)`
    : '✓ no problem found in the source';
  el.innerHTML = `<details${source.flags.length ? ' open' : ''}><summary>${head}</summary>
    <ul class="source-flags">${source.flags.map((f) => `<li data-flag="${esc(f.name)}" title="${esc(f.message)}">${esc(f.label)}${f.value === null ? '' : `: <b>${formatNumber(f.value)}</b> ${esc(f.unit)}`}${f.threshold === null ? '' : ` (over ${formatNumber(f.threshold)})`}</li>`).join('')}</ul>
    <details class="source-figures"><summary>figures on ${esc(source.body ?? 'the source body')} (at 1.80 m)</summary><ul>${figures}</ul></details>
  </details>`;
  box.appendChild(el);
}

function renderNotes(el, job, metrics) {
  const notes = [...new Set([...(job.warnings || []), ...metrics.notes])];
  if (!notes.length) { el.innerHTML = ''; return; }
  el.innerHTML = `<details><summary>${notes.length} note${notes.length > 1 ? 's' : ''} from the pipeline</summary><ul>${notes.map((n) => `<li>${esc(n)}</li>`).join('')}</ul></details>`;
}

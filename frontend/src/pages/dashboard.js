/**
 * The job dashboard (live status and progress by stage, errors in words, result links, cancel and retry) and
 * the batch page (a motions x characters grid of one batch). Both poll while something is unfinished.
 */
import { api, download } from '../api.js';
import { esc, formatAgo, formatSeconds, shortId } from '../format.js';
import { loadNames, nameOf } from '../names.js';
import { batchHash, reviewHash } from '../router.js';
import { errorHtml, progressBar, stagesHtml, statusChip } from './jobs_common.js';

const STATUSES = ['', 'queued', 'running', 'succeeded', 'failed', 'canceled'];
const PAGE = 50;

export function mountDashboard(root, route) {
  const state = { alive: true, timer: null, status: route.query.get('status') || '', offset: Number(route.query.get('offset')) || 0 };
  root.innerHTML = `<section class="dashboard">
    <div class="dash-head"><h1>Jobs</h1>
      <label>Status <select data-act="status">${STATUSES.map((s) => `<option value="${s}" ${s === state.status ? 'selected' : ''}>${s || 'all'}</option>`).join('')}</select></label>
      <span class="dash-live" title="The list refreshes while jobs are unfinished"></span>
      <a class="btn small" href="#/upload">New retarget</a></div>
    <div class="jobs-table-wrap"><table class="jobs-table"><thead><tr>
      <th>Job</th><th>Status</th><th>Progress</th><th>Submitted</th><th>Run time</th><th>Results</th><th></th></tr></thead>
      <tbody><tr><td colspan="7">Loading…</td></tr></tbody></table></div>
    <div class="pager"></div>
    <h2>Batches</h2><div class="batches">Loading…</div>
  </section>`;
  root.querySelector('[data-act=status]').onchange = (e) => {
    window.location.hash = `#/jobs${e.target.value ? `?status=${e.target.value}` : ''}`;
  };
  const tbody = root.querySelector('tbody');
  const live = root.querySelector('.dash-live');

  const load = async () => {
    if (!state.alive) return;
    let page;
    let batches;
    try {
      const q = `limit=${PAGE}&offset=${state.offset}${state.status ? `&status=${state.status}` : ''}`;
      [page, batches] = await Promise.all([api(`/v1/jobs?${q}`), api('/v1/batches?limit=20')]);
      await loadNames(page.items.map((j) => j.motion_id), page.items.map((j) => j.target_character_id));
    } catch (e) {
      tbody.innerHTML = `<tr><td colspan="7" class="error">Cannot list jobs: ${esc(e.message)}</td></tr>`;
      state.timer = setTimeout(load, 5000);
      return;
    }
    if (!state.alive) return;
    tbody.innerHTML = page.items.length
      ? page.items.map(jobRow).join('')
      : `<tr><td colspan="7" class="empty">No jobs${state.status ? ` with status ${esc(state.status)}` : ''} yet. <a href="#/upload">Submit one</a>.</td></tr>`;
    wireRowActions(tbody, load);
    root.querySelector('.pager').innerHTML = pagerHtml(page, state.status);
    root.querySelector('.batches').innerHTML = batches.items.length
      ? `<table class="batches-table"><thead><tr><th>Batch</th><th>Status</th><th>Jobs</th><th>Progress</th><th>Submitted</th></tr></thead><tbody>${batches.items.map(batchRow).join('')}</tbody></table>`
      : '<p class="empty">No batches yet (submit several motions or targets at once).</p>';
    const unfinished = page.items.some((j) => j.status === 'queued' || j.status === 'running')
      || batches.items.some((b) => b.status === 'queued' || b.status === 'running');
    live.textContent = unfinished ? '● live' : '';
    state.timer = setTimeout(load, unfinished ? 1000 : 5000);
  };
  load();
  return () => { state.alive = false; clearTimeout(state.timer); };
}

function jobRow(j) {
  const results = j.results
    ? Object.entries({ result_glb: 'result.glb', before_glb: 'before.glb', source_glb: 'source.glb', metrics_json: 'metrics.json' })
      .filter(([k]) => j.results[k])
      .map(([k, f]) => `<button type="button" class="link" data-dl="${esc(j.results[k])}" data-file="${esc(`${j.id}-${f}`)}">${f}</button>`).join(' ')
    : '';
  const actions = [
    j.status === 'succeeded' || j.status === 'running' || j.status === 'queued' ? `<a class="btn small" href="${reviewHash(j.id)}">${j.status === 'succeeded' ? 'Review' : 'Watch'}</a>` : '',
    j.links?.cancel ? `<button type="button" class="btn small ghost" data-cancel="${esc(j.id)}">Cancel</button>` : '',
    j.links?.retry ? `<button type="button" class="btn small ghost" data-retry="${esc(j.id)}">Retry</button>` : '',
  ].join(' ');
  return `<tr data-job="${esc(j.id)}" data-status="${esc(j.status)}">
    <td><a href="${reviewHash(j.id)}" title="${esc(j.id)}">${esc(nameOf(j.motion_id))} → ${esc(nameOf(j.target_character_id))}</a>
      <br><small><code>${esc(shortId(j.id, 16))}</code>${j.batch_id ? ` · <a href="${batchHash(j.batch_id)}">batch</a>` : ''}</small></td>
    <td>${statusChip(j.status)}${j.cancel_requested && j.status === 'running' ? '<br><small>cancel requested</small>' : ''}</td>
    <td class="progress-cell">${progressBar(j)}${stagesHtml(j)}${errorHtml(j)}</td>
    <td title="${esc(j.created_at)}">${esc(formatAgo(j.created_at))}</td>
    <td>${esc(formatSeconds(j.timings?.run_seconds))}</td>
    <td class="results">${results}</td>
    <td class="actions">${actions}</td></tr>`;
}

function wireRowActions(el, reload) {
  for (const b of el.querySelectorAll('[data-dl]')) {
    b.onclick = async () => {
      try { await download(b.dataset.dl, b.dataset.file); } catch (e) { alert(`Download failed: ${e.message}`); }
    };
  }
  for (const [attr, verb] of [['cancel', 'cancel'], ['retry', 'retry']]) {
    for (const b of el.querySelectorAll(`[data-${attr}]`)) {
      b.onclick = async () => {
        b.disabled = true;
        try { await api(`/v1/jobs/${encodeURIComponent(b.dataset[attr])}/${verb}`, { method: 'POST' }); } catch (e) { alert(`Could not ${verb}: ${e.message}`); }
        reload();
      };
    }
  }
}

function pagerHtml(page, status) {
  if (page.total <= page.limit) return page.total ? `<small>${page.total} job${page.total > 1 ? 's' : ''}</small>` : '';
  const q = (o) => `#/jobs?${status ? `status=${status}&` : ''}offset=${o}`;
  const prev = page.offset > 0 ? `<a href="${q(Math.max(0, page.offset - page.limit))}">← newer</a>` : '';
  const next = page.next_offset != null ? `<a href="${q(page.next_offset)}">older →</a>` : '';
  return `${prev} <small>${page.offset + 1}–${page.offset + page.items.length} of ${page.total}</small> ${next}`;
}

function batchRow(b) {
  const counts = Object.entries(b.counts).filter(([, n]) => n).map(([s, n]) => `${n} ${s}`).join(', ');
  const pct = Math.round(b.progress * 100);
  return `<tr data-batch="${esc(b.id)}"><td><a href="${batchHash(b.id)}">${esc(b.name || shortId(b.id, 16))}</a></td>
    <td>${statusChip(b.status)}</td><td>${b.total}: ${esc(counts)}</td>
    <td><div class="progress ${esc(b.status)}"><div class="progress-fill" style="width:${pct}%"></div><span>${pct}%</span></div></td>
    <td>${esc(formatAgo(b.created_at))}</td></tr>`;
}

/** One batch: counts, progress and a motions x characters grid linking to each job's review. */
export function mountBatch(root, batchId) {
  const state = { alive: true, timer: null };
  root.innerHTML = `<section class="batch"><h1>Batch <code>${esc(batchId)}</code></h1><div class="batch-body">Loading…</div></section>`;
  const body = root.querySelector('.batch-body');
  const load = async () => {
    if (!state.alive) return;
    let b;
    try {
      b = await api(`/v1/batches/${encodeURIComponent(batchId)}`);
      await loadNames(b.jobs.map((j) => j.motion_id), b.jobs.map((j) => j.target_character_id));
    } catch (e) {
      body.innerHTML = `<div class="error-box">Cannot load the batch: ${esc(e.message)}</div>`;
      return;
    }
    if (!state.alive) return;
    const motions = [...new Set(b.jobs.map((j) => j.motion_id))];
    const targets = [...new Set(b.jobs.map((j) => j.target_character_id))];
    const cell = (m, t) => {
      const j = b.jobs.find((x) => x.motion_id === m && x.target_character_id === t);
      if (!j) return '<td></td>';
      return `<td data-job="${esc(j.id)}" data-status="${esc(j.status)}"><a href="${reviewHash(j.id)}">${statusChip(j.status)} ${j.status === 'succeeded' ? 'review →' : j.status === 'queued' || j.status === 'running' ? 'watch →' : 'details →'}</a>${progressBar(j)}${errorHtml(j)}</td>`;
    };
    const pct = Math.round(b.progress * 100);
    body.innerHTML = `<p>${b.name ? `<b>${esc(b.name)}</b> · ` : ''}${statusChip(b.status)} ${b.total} jobs:
        ${Object.entries(b.counts).filter(([, n]) => n).map(([s, n]) => `${n} ${esc(s)}`).join(', ')}
        ${b.status === 'queued' || b.status === 'running' ? '<button type="button" class="btn small ghost" data-act="cancel">Cancel unfinished</button>' : ''}</p>
      <div class="progress ${esc(b.status)}"><div class="progress-fill" style="width:${pct}%"></div><span>${pct}%</span></div>
      <div class="grid-wrap"><table class="batch-grid"><thead><tr><th>motion \\ character</th>${targets.map((t) => `<th>${esc(nameOf(t))}</th>`).join('')}</tr></thead>
      <tbody>${motions.map((m) => `<tr><th>${esc(nameOf(m))}</th>${targets.map((t) => cell(m, t)).join('')}</tr>`).join('')}</tbody></table></div>`;
    const cancel = body.querySelector('[data-act=cancel]');
    if (cancel) cancel.onclick = async () => { cancel.disabled = true; await api(`/v1/batches/${encodeURIComponent(batchId)}/cancel`, { method: 'POST' }).catch((e) => alert(e.message)); load(); };
    if (b.status === 'queued' || b.status === 'running') state.timer = setTimeout(load, 1000);
  };
  load();
  return () => { state.alive = false; clearTimeout(state.timer); };
}

/** Pieces shared by the dashboard, the batch page and the review page: status chips, progress, errors in words. */
import { esc, formatSeconds } from '../format.js';
import { nameOf } from '../names.js';

export const ERROR_KINDS = {
  input: 'The input files or options are the problem: fix them and submit again.',
  internal: 'An internal error: retrying may help; if it does not, report the job id.',
  timeout: 'The job took longer than the time limit: try a shorter frame range.',
  worker_lost: 'The worker running it stopped more often than allowed.',
};

/** "007_03 → mh_male_bulky". */
export function jobTitle(job, names = { nameOf }) {
  return `${names.nameOf(job.motion_id)} → ${names.nameOf(job.target_character_id)}`;
}

export function statusChip(status) {
  return `<span class="chip status-${esc(status)}" data-status="${esc(status)}">${esc(status)}</span>`;
}

/** A progress bar with the stage name (running), or the status. */
export function progressBar(job) {
  const pct = Math.round((job.status === 'succeeded' ? 1 : job.progress || 0) * 100);
  const label = job.status === 'running' ? `${esc(job.stage || 'starting')} · ${pct}%`
    : job.status === 'queued' ? 'waiting for a worker' : job.status === 'succeeded' ? 'done' : esc(job.status);
  return `<div class="progress ${esc(job.status)}" role="progressbar" aria-valuenow="${pct}" aria-valuemin="0" aria-valuemax="100">
    <div class="progress-fill" style="width:${pct}%"></div><span>${label}</span></div>`;
}

/** The stages seen so far with their seconds, the running one marked. */
export function stagesHtml(job) {
  const stages = Object.entries(job.timings?.stages || {});
  const cur = job.status === 'running' ? job.stage : null;
  const items = stages.map(([name, s]) => `<li class="done">${esc(name)} <small>${formatSeconds(s)}</small></li>`);
  if (cur && cur !== 'done' && !stages.some(([n]) => n === cur)) items.push(`<li class="current">${esc(cur)}…</li>`);
  return items.length ? `<ol class="stages">${items.join('')}</ol>` : '';
}

/** The error of a failed or canceled job in words. */
export function errorHtml(job) {
  if (job.status !== 'failed' && job.status !== 'canceled') return '';
  const hint = job.error_kind ? ERROR_KINDS[job.error_kind] : '';
  return `<div class="job-error"><b>${job.status === 'failed' ? 'Failed' : 'Canceled'}:</b> ${esc(job.message || 'no message')}${hint ? `<br><small>${esc(hint)}</small>` : ''}</div>`;
}

/** The live panel of an unfinished (or failed) job on its review page. */
export function jobProgressHtml(job) {
  return `<div class="job-card" data-status="${esc(job.status)}">
    <p>${statusChip(job.status)} ${job.attempt > 1 ? `<small>attempt ${job.attempt}</small>` : ''}</p>
    ${progressBar(job)}
    ${stagesHtml(job)}
    ${errorHtml(job)}
    ${job.status === 'queued' || job.status === 'running' ? '<p class="hint">The viewer opens here when the job has succeeded.</p>' : ''}
    ${job.warnings?.length ? `<ul class="warnings">${job.warnings.map((w) => `<li>${esc(w)}</li>`).join('')}</ul>` : ''}
  </div>`;
}

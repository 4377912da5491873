/**
 * Hash routes of the single-page app. Pure functions (no DOM) so they can be unit tested.
 *
 *   #/upload                 upload form (default)
 *   #/jobs                   job dashboard (optional ?status=failed)
 *   #/jobs/<id>              a job: live progress, then its review viewer
 *   #/jobs/<id>/review       the review viewer of a job (the URL to share; it never holds the API key)
 *   #/review/<token>         a read-only review link: the review viewer without an API key (the token is the access)
 *   #/batches/<id>           one batch: its jobs as a motions x characters grid
 *   #/view                   single-file viewer for any GLB (validated in the browser)
 *   #/settings               the API key
 */

/** @typedef {{name: string, params: Record<string, string>, query: URLSearchParams}} Route */

const PATTERNS = [
  ['review', /^\/jobs\/([^/]+)\/review$/, ['id']],
  ['shared', /^\/review\/([^/]+)$/, ['token']],
  ['job', /^\/jobs\/([^/]+)$/, ['id']],
  ['jobs', /^\/jobs$/, []],
  ['batch', /^\/batches\/([^/]+)$/, ['id']],
  ['upload', /^\/upload$/, []],
  ['view', /^\/view$/, []],
  ['settings', /^\/settings$/, []],
];

/**
 * The route of a location hash such as "#/jobs/job_1/review?x=1".
 * @param {string} hash
 * @returns {Route}
 */
export function parseRoute(hash) {
  let h = (hash || '').replace(/^#/, '');
  if (!h.startsWith('/')) h = '/' + h;
  const [path, qs = ''] = h.split('?', 2);
  const clean = path.replace(/\/+$/, '') || '/';
  const query = new URLSearchParams(qs);
  if (clean === '/') return { name: 'upload', params: {}, query };
  for (const [name, re, keys] of PATTERNS) {
    const m = re.exec(clean);
    if (m) {
      const params = {};
      keys.forEach((k, i) => { params[k] = decodeURIComponent(m[i + 1]); });
      return { name, params, query };
    }
  }
  return { name: 'notfound', params: { path: clean }, query };
}

/** The hash of the review viewer of a job. */
export function reviewHash(jobId) {
  return `#/jobs/${encodeURIComponent(jobId)}/review`;
}

/** The hash of a batch page. */
export function batchHash(batchId) {
  return `#/batches/${encodeURIComponent(batchId)}`;
}

/**
 * An absolute URL to share for a job's review: origin + path + review hash. Nothing else of the current
 * location (query, other hash parts) is carried over, so no secret can leak through it.
 * @param {{origin: string, pathname: string}} loc
 * @param {string} jobId
 */
export function shareUrl(loc, jobId) {
  return `${loc.origin}${loc.pathname}${reviewHash(jobId)}`;
}

/**
 * The absolute URL of a read-only review link (a token made by POST /v1/jobs/<id>/review-links): whoever opens
 * it sees that job's review and downloads, without an API key.
 * @param {{origin: string, pathname: string}} loc
 * @param {string} token
 */
export function reviewLinkUrl(loc, token) {
  return `${loc.origin}${loc.pathname}#/review/${encodeURIComponent(token)}`;
}

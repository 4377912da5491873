/**
 * The HTTP client of the retarget service (/v1, key in the X-API-Key header).
 *
 * The key lives in localStorage only; it is never put into a URL, so links and share URLs cannot leak it.
 * Downloads go through fetch (the key must be a header), then a blob URL.
 */

const KEY_STORAGE = 'retarget.apiKey';

/** An HTTP error with the service's message ("detail") in words. */
export class ApiError extends Error {
  constructor(status, message, body) {
    super(message);
    this.status = status;
    this.body = body;
  }
}

export function getKey() {
  try { return localStorage.getItem(KEY_STORAGE) || ''; } catch { return ''; }
}

export function setKey(key) {
  try {
    if (key) localStorage.setItem(KEY_STORAGE, key);
    else localStorage.removeItem(KEY_STORAGE);
  } catch { /* storage disabled: the key lasts for this page only */ }
  window.dispatchEvent(new CustomEvent('apikey-changed'));
}

/** The message a person can act on, from an error body (FastAPI: {detail: string | [{msg, loc}]}). */
export function errorMessage(status, body, fallback) {
  const d = body && typeof body === 'object' ? body.detail : null;
  if (typeof d === 'string') return d;
  if (Array.isArray(d)) {
    return d.map((e) => `${(e.loc || []).filter((x) => x !== 'body').join('.')}: ${e.msg}`).join('; ');
  }
  if (status === 0) return 'the service did not answer (network error)';
  return fallback || `HTTP ${status}`;
}

function headers(extra = {}) {
  const h = { ...extra };
  const key = getKey();
  if (key) h['X-API-Key'] = key;
  return h;
}

async function parseBody(res) {
  const type = res.headers.get('content-type') || '';
  if (type.includes('application/json')) {
    try { return await res.json(); } catch { return null; }
  }
  try { return await res.text(); } catch { return null; }
}

/** fetch JSON from the API; throws ApiError with the service's message. */
export async function api(path, { method = 'GET', body, signal } = {}) {
  const opts = { method, headers: headers(body !== undefined ? { 'Content-Type': 'application/json' } : {}), signal };
  if (body !== undefined) opts.body = JSON.stringify(body);
  let res;
  try {
    res = await fetch(path, opts);
  } catch (e) {
    if (e.name === 'AbortError') throw e;
    throw new ApiError(0, errorMessage(0, null));
  }
  const data = await parseBody(res);
  if (!res.ok) {
    const err = new ApiError(res.status, errorMessage(res.status, data, res.statusText), data);
    if (res.status === 401) window.dispatchEvent(new CustomEvent('apikey-rejected', { detail: err.message }));
    throw err;
  }
  return data;
}

/** The bytes of an API file (GLB, JSON) as an ArrayBuffer. */
export async function fetchBytes(path, { signal } = {}) {
  let res;
  try {
    res = await fetch(path, { headers: headers(), signal });
  } catch (e) {
    if (e.name === 'AbortError') throw e;
    throw new ApiError(0, errorMessage(0, null));
  }
  if (!res.ok) {
    const data = await parseBody(res);
    throw new ApiError(res.status, errorMessage(res.status, data, res.statusText), data);
  }
  return res.arrayBuffer();
}

/**
 * Upload a file as multipart form data with progress (XHR: fetch has no upload progress).
 * @param {string} path e.g. "/v1/motions"
 * @param {File} file
 * @param {{onProgress?: (loaded: number, total: number) => void, onSent?: () => void}} cb
 * @returns {{promise: Promise<any>, abort: () => void}}
 */
export function uploadFile(path, file, { onProgress, onSent } = {}) {
  const xhr = new XMLHttpRequest();
  const promise = new Promise((resolve, reject) => {
    xhr.open('POST', path);
    const key = getKey();
    if (key) xhr.setRequestHeader('X-API-Key', key);
    xhr.responseType = 'json';
    xhr.upload.onprogress = (e) => {
      const total = e.lengthComputable ? e.total : file.size;
      // A record of progress events, read by the end-to-end tests (and handy in the console).
      (window.__uploadLog ||= []).push({ name: file.name, loaded: e.loaded, total });
      if (onProgress) onProgress(e.loaded, total);
    };
    xhr.upload.onload = () => { if (onSent) onSent(); };
    xhr.onload = () => {
      const body = xhr.response;
      if (xhr.status >= 200 && xhr.status < 300) resolve(body);
      else {
        if (xhr.status === 401) window.dispatchEvent(new CustomEvent('apikey-rejected'));
        reject(new ApiError(xhr.status, errorMessage(xhr.status, body, xhr.statusText), body));
      }
    };
    xhr.onerror = () => reject(new ApiError(0, errorMessage(0, null)));
    xhr.onabort = () => reject(new ApiError(0, 'upload canceled'));
    const form = new FormData();
    form.append('file', file, file.name);
    xhr.send(form);
  });
  return { promise, abort: () => xhr.abort() };
}

/** Save an API file to disk (fetch with the key header, then a temporary blob link). */
export async function download(path, filename) {
  const buf = await fetchBytes(path);
  const url = URL.createObjectURL(new Blob([buf]));
  const a = document.createElement('a');
  a.href = url;
  a.download = filename;
  document.body.appendChild(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

/** Every page of a list endpoint (items), up to `max` items. */
export async function listAll(path, max = 2000) {
  const items = [];
  let offset = 0;
  const sep = path.includes('?') ? '&' : '?';
  while (items.length < max) {
    const page = await api(`${path}${sep}limit=500&offset=${offset}`);
    items.push(...page.items);
    if (page.next_offset == null) break;
    offset = page.next_offset;
  }
  return items;
}

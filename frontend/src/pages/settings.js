/** The API key: kept in this browser's localStorage, sent as X-API-Key, never put into a URL. */
import { api, getKey, setKey } from '../api.js';
import { esc } from '../format.js';

export function mountSettings(root, { reason = '', onSaved } = {}) {
  root.innerHTML = `<section class="settings">
    <h1>API key</h1>
    ${reason ? `<p class="notice">${esc(reason)}</p>` : ''}
    <form class="key-form" autocomplete="off">
      <label>API key <input type="password" name="key" id="api-key" value="${esc(getKey())}" placeholder="your X-API-Key" required></label>
      <button type="submit" class="btn primary">Save</button>
      <button type="button" class="btn ghost" data-act="forget">Forget</button>
      <span class="key-status"></span>
    </form>
    <p class="help">The key stays in this browser (localStorage) and goes to the service in the <code>X-API-Key</code> header
      only. Links you share (review links) never contain it: whoever opens them needs a key that owns the job.
      On a development machine, <code>python -m api.serve</code> prints a development key.</p>
  </section>`;
  const form = root.querySelector('form');
  const status = root.querySelector('.key-status');
  form.addEventListener('submit', async (e) => {
    e.preventDefault();
    const key = form.key.value.trim();
    setKey(key);
    status.textContent = 'checking…';
    try {
      const me = await api('/v1/me');
      status.innerHTML = `✓ key <b>${esc(me.name)}</b> (${esc(me.key_prefix)}…)`;
      status.dataset.ok = 'true';
      onSaved?.();
    } catch (err) {
      status.innerHTML = `<span class="error">${esc(err.message)}</span>`;
      status.dataset.ok = 'false';
    }
  });
  root.querySelector('[data-act=forget]').onclick = () => { setKey(''); form.key.value = ''; status.textContent = 'forgotten'; };
  return () => {};
}

/** The app shell: navigation, hash routing, the API key gate. Pages mount into #page and return a cleanup. */
import './style.css';
import { getKey } from './api.js';
import { esc } from './format.js';
import { mountBatch, mountDashboard } from './pages/dashboard.js';
import { mountFileView } from './pages/fileview.js';
import { mountReview } from './pages/review.js';
import { mountSettings } from './pages/settings.js';
import { mountUpload } from './pages/upload.js';
import { parseRoute } from './router.js';

const page = document.getElementById('page');
const banner = document.getElementById('banner');
let cleanup = null;

/** Pages that talk to the API and so need a key. */
const NEEDS_KEY = new Set(['upload', 'jobs', 'job', 'review', 'batch']);

function mount() {
  cleanup?.();
  cleanup = null;
  banner.hidden = true;
  const route = parseRoute(window.location.hash);
  for (const a of document.querySelectorAll('nav a[data-nav]')) {
    const nav = a.dataset.nav;
    a.classList.toggle('active', nav === route.name || (nav === 'jobs' && ['job', 'review', 'batch'].includes(route.name)));
  }
  document.body.dataset.route = route.name;
  if (NEEDS_KEY.has(route.name) && !getKey()) {
    cleanup = mountSettings(page, { reason: 'Enter your API key to use the service.', onSaved: () => mount() });
    return;
  }
  switch (route.name) {
    case 'upload': cleanup = mountUpload(page); break;
    case 'jobs': cleanup = mountDashboard(page, route); break;
    case 'job':
    case 'review': cleanup = mountReview(page, route.params.id); break;
    case 'shared': cleanup = mountReview(page, null, { token: route.params.token }); break;
    case 'batch': cleanup = mountBatch(page, route.params.id); break;
    case 'view': cleanup = mountFileView(page); break;
    case 'settings': cleanup = mountSettings(page, { onSaved: () => { window.location.hash = '#/upload'; } }); break;
    default: page.innerHTML = `<section><h1>Not found</h1><p>No page at <code>${esc(route.params.path)}</code>. <a href="#/upload">Start here</a>.</p></section>`;
  }
}

window.addEventListener('hashchange', mount);
window.addEventListener('apikey-rejected', (e) => {
  banner.hidden = false;
  banner.innerHTML = `The service rejected the API key${e.detail ? `: ${esc(e.detail)}` : ''}. <a href="#/settings">Change it</a>.`;
});
window.addEventListener('apikey-changed', () => {
  document.querySelector('[data-nav=settings]').textContent = getKey() ? 'API key ✓' : 'API key';
});
window.dispatchEvent(new CustomEvent('apikey-changed'));
mount();

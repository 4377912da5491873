/**
 * The transport bar of a timeline: first, step back, play/pause, step forward, last, speed, a scrubber and the
 * frame readout, plus optional toggles. Keyboard (space, arrows, Home/End) is bound by `bindKeys`.
 */
import { esc } from '../format.js';

const SPEEDS = [0.1, 0.25, 0.5, 1, 1.5, 2, 4];
const svg = (d) => `<svg viewBox="0 0 16 16" width="14" height="14" aria-hidden="true"><path fill="currentColor" d="${d}"/></svg>`;
const ICONS = {
  first: svg('M2 2h2v12H2zM14 2v12L5 8z'),
  back: svg('M3 2h2v12H3zM13 2v12L6 8z'),
  play: svg('M4 2l10 6-10 6z'),
  pause: svg('M3 2h4v12H3zM9 2h4v12H9z'),
  fwd: svg('M3 2v12l7-6zM11 2h2v12h-2z'),
  last: svg('M2 2v12l9-6zM12 2h2v12h-2z'),
};

/**
 * @param {HTMLElement} el the bar's container
 * @param {import('./timeline.js').Timeline} timeline
 * @param {{id: string, label: string, checked: boolean, disabled?: boolean, title?: string, onChange: (on: boolean) => void}[]} toggles
 */
export function mountControls(el, timeline, toggles = []) {
  el.classList.add('transport');
  el.innerHTML = `
    <div class="transport-buttons">
      <button type="button" data-act="first" title="First frame (Home)" aria-label="First frame">${ICONS.first}</button>
      <button type="button" data-act="back" title="Previous frame (←, Shift+← 10)" aria-label="Previous frame">${ICONS.back}</button>
      <button type="button" data-act="play" class="play" title="Play / pause (Space)" aria-label="Play">${ICONS.play}</button>
      <button type="button" data-act="fwd" title="Next frame (→, Shift+→ 10)" aria-label="Next frame">${ICONS.fwd}</button>
      <button type="button" data-act="last" title="Last frame (End)" aria-label="Last frame">${ICONS.last}</button>
      <label class="speed" title="Playback speed">speed
        <select data-act="speed">${SPEEDS.map((s) => `<option value="${s}" ${s === 1 ? 'selected' : ''}>${s}×</option>`).join('')}</select>
      </label>
    </div>
    <input type="range" class="scrubber" min="0" max="${timeline.frames - 1}" step="1" value="0" aria-label="Frame">
    <span class="frame-readout" aria-live="off"></span>
    <div class="toggles">${toggles.map((t) => `<label class="toggle" title="${esc(t.title || '')}"><input type="checkbox" data-toggle="${esc(t.id)}" ${t.checked ? 'checked' : ''} ${t.disabled ? 'disabled' : ''}> ${esc(t.label)}</label>`).join('')}</div>`;
  const play = el.querySelector('[data-act=play]');
  const scrub = el.querySelector('.scrubber');
  const readout = el.querySelector('.frame-readout');
  el.querySelector('[data-act=first]').onclick = () => { timeline.pause(); timeline.seek(0); };
  el.querySelector('[data-act=last]').onclick = () => { timeline.pause(); timeline.seek(timeline.frames - 1); };
  el.querySelector('[data-act=back]').onclick = () => timeline.step(-1);
  el.querySelector('[data-act=fwd]').onclick = () => timeline.step(1);
  play.onclick = () => timeline.toggle();
  el.querySelector('[data-act=speed]').onchange = (e) => timeline.setSpeed(Number(e.target.value));
  scrub.addEventListener('input', () => { timeline.pause(); timeline.seek(Number(scrub.value)); });
  for (const t of toggles) {
    el.querySelector(`[data-toggle="${t.id}"]`).addEventListener('change', (e) => t.onChange(e.target.checked));
  }
  // Buttons must not keep focus: space would "click" them instead of reaching the keyboard handler.
  for (const b of el.querySelectorAll('button, select, input')) b.addEventListener('keydown', (e) => {
    if (e.key === ' ' && b.tagName !== 'SELECT') e.preventDefault();
  });
  const update = () => {
    scrub.max = String(timeline.frames - 1);
    scrub.value = String(timeline.frame);
    play.innerHTML = timeline.playing ? ICONS.pause : ICONS.play;
    play.setAttribute('aria-label', timeline.playing ? 'Pause' : 'Play');
    const t = timeline.frame / timeline.fps;
    readout.textContent = `frame ${timeline.frame} / ${timeline.frames - 1} · ${t.toFixed(2)} s @ ${Math.round(timeline.fps * 100) / 100} fps`;
    el.dataset.frame = String(timeline.frame);
    el.dataset.playing = String(timeline.playing);
  };
  update();
  return update;
}

/**
 * Space plays/pauses, ←/→ step one frame (Shift: 10), Home/End jump. Ignored while typing in a field.
 * @returns {() => void} unbind
 */
export function bindKeys(timeline) {
  const onKey = (e) => {
    const tag = (e.target && e.target.tagName) || '';
    if (['INPUT', 'TEXTAREA', 'SELECT'].includes(tag) && e.target.type !== 'range' && e.target.type !== 'checkbox') return;
    if (e.ctrlKey || e.metaKey || e.altKey) return;
    const n = e.shiftKey ? 10 : 1;
    if (e.key === ' ' || e.code === 'Space') timeline.toggle();
    else if (e.key === 'ArrowRight') timeline.step(n);
    else if (e.key === 'ArrowLeft') timeline.step(-n);
    else if (e.key === 'Home') { timeline.pause(); timeline.seek(0); }
    else if (e.key === 'End') { timeline.pause(); timeline.seek(timeline.frames - 1); }
    else return;
    e.preventDefault();
  };
  document.addEventListener('keydown', onKey);
  return () => document.removeEventListener('keydown', onKey);
}

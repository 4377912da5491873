/**
 * Per-frame charts on a plain canvas: "before" and "after" lines of one metric, a playhead that follows the
 * timeline, and click-or-drag to scrub. A chart without series says "no data for this job". A chart whose data
 * carries `parts` (the penetration chart: penetrating vertices per body part) has a "by part" switch that draws
 * one line per part instead, in the part's colour (before wide and translucent, after thin).
 */
import { PARTS, seriesRange, valueAt } from '../metrics.js';
import { formatNumber } from '../format.js';

export const COLORS = { before: '#e8a33d', after: '#4aa3ff', playhead: '#f2f2f2', grid: '#39404a', text: '#aab3bf' };

export class Chart {
  /**
   * @param {HTMLElement} container the chart's box (sized by CSS)
   * @param {{id: string, title: string, unit: string, before: any, after: any}} data from metrics.chartData
   * @param {import('./timeline.js').Timeline} timeline
   */
  constructor(container, data, timeline) {
    this.container = container;
    this.data = data;
    this.timeline = timeline;
    this.hasData = Boolean(data.before || data.after);
    container.classList.add('chart');
    container.dataset.chart = data.id;
    container.dataset.hasData = String(this.hasData);
    container.dataset.points = String((data.before?.count ?? 0) + (data.after?.count ?? 0));
    const head = document.createElement('div');
    head.className = 'chart-head';
    head.innerHTML = `<span class="chart-title"></span><span class="chart-readout"></span>`;
    this.title = head.querySelector('.chart-title');
    this.readout = head.querySelector('.chart-readout');
    this.mode = 'value';
    if (data.parts) {
      const toggle = document.createElement('button');
      toggle.type = 'button';
      toggle.className = 'chart-mode';
      toggle.dataset.chartMode = 'parts';
      toggle.title = 'Show the share of penetrating vertices split by body part (the part of each vertex)';
      toggle.onclick = () => this.setMode(this.mode === 'parts' ? 'value' : 'parts');
      head.insertBefore(toggle, this.readout);
      this.toggle = toggle;
    }
    container.appendChild(head);
    this.canvas = document.createElement('canvas');
    this.canvas.className = 'chart-canvas';
    container.appendChild(this.canvas);
    this.frame = -1;
    this.setMode('value', false);
    const scrub = (e) => {
      if (!this.hasData) return;
      const r = this.canvas.getBoundingClientRect();
      const x = (e.clientX - r.left - this.pad.l) / Math.max(1, r.width - this.pad.l - this.pad.r);
      this.timeline.pause();
      this.timeline.seek(x * (this.timeline.frames - 1));
    };
    this.pad = { l: 44, r: 8, t: 6, b: 16 };
    this.canvas.addEventListener('pointerdown', (e) => {
      this.canvas.setPointerCapture(e.pointerId);
      scrub(e);
      const move = (ev) => scrub(ev);
      const up = () => {
        this.canvas.removeEventListener('pointermove', move);
        this.canvas.removeEventListener('pointerup', up);
      };
      this.canvas.addEventListener('pointermove', move);
      this.canvas.addEventListener('pointerup', up);
    });
    this.resizeObserver = new ResizeObserver(() => this.draw(this.timeline.frame, true));
    this.resizeObserver.observe(this.canvas);
  }

  /** 'value': the metric's before/after lines; 'parts': one line per body part (when the data has parts). */
  setMode(mode, redraw = true) {
    this.mode = mode === 'parts' && this.data.parts ? 'parts' : 'value';
    const parts = this.mode === 'parts';
    this.title.textContent = parts
      ? `Penetrating vertices by part (${this.data.parts.unit})`
      : this.data.title + (this.data.unit ? ` (${this.data.unit})` : '');
    if (this.toggle) {
      this.toggle.textContent = parts ? 'depth' : 'by part';
      this.toggle.setAttribute('aria-pressed', String(parts));
    }
    this.container.dataset.mode = this.mode;
    this.range = seriesRange(this.lines().map((l) => l.series));
    if (redraw) this.draw(this.timeline.frame, true);
  }

  /** The lines of the current mode: {series, color, wide, part?}. */
  lines() {
    if (this.mode !== 'parts') {
      return [
        { series: this.data.before, color: COLORS.before, wide: true },
        { series: this.data.after, color: COLORS.after, wide: false },
      ].filter((l) => l.series);
    }
    const out = [];
    for (const [name, wide] of [['before', true], ['after', false]]) {
      for (const p of PARTS) {
        const s = this.data.parts[name]?.[p.id];
        if (s) out.push({ series: s, color: p.color, wide, part: p.id });
      }
    }
    return out;
  }

  /** Redraw with the playhead at `frame`. */
  draw(frame, force = false) {
    if (frame === this.frame && !force) return;
    this.frame = frame;
    const dpr = Math.min(window.devicePixelRatio || 1, 2);
    const w = Math.max(1, this.canvas.clientWidth);
    const h = Math.max(1, this.canvas.clientHeight);
    if (this.canvas.width !== Math.round(w * dpr) || this.canvas.height !== Math.round(h * dpr)) {
      this.canvas.width = Math.round(w * dpr);
      this.canvas.height = Math.round(h * dpr);
    }
    const ctx = this.canvas.getContext('2d');
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    ctx.font = '11px system-ui, sans-serif';
    if (!this.hasData) {
      ctx.fillStyle = COLORS.text;
      ctx.textAlign = 'center';
      ctx.textBaseline = 'middle';
      ctx.fillText('no data for this job', w / 2, h / 2);
      this.readout.textContent = '';
      this.container.dataset.playhead = String(frame);
      return;
    }
    const { l, r, t, b } = this.pad;
    const pw = w - l - r;
    const ph = h - t - b;
    const n = Math.max(2, this.timeline.frames);
    const [lo, hi] = this.range;
    const X = (i) => l + (i / (n - 1)) * pw;
    const Y = (v) => t + ph - ((v - lo) / (hi - lo)) * ph;
    ctx.strokeStyle = COLORS.grid;
    ctx.lineWidth = 1;
    ctx.fillStyle = COLORS.text;
    ctx.textAlign = 'right';
    ctx.textBaseline = 'middle';
    for (const v of [lo, (lo + hi) / 2, hi]) {
      ctx.beginPath();
      ctx.moveTo(l, Math.round(Y(v)) + 0.5);
      ctx.lineTo(l + pw, Math.round(Y(v)) + 0.5);
      ctx.stroke();
      ctx.fillText(formatNumber(v, 2), l - 4, Y(v));
    }
    ctx.textAlign = 'left';
    ctx.textBaseline = 'top';
    ctx.fillText('0', l, t + ph + 3);
    ctx.textAlign = 'right';
    ctx.fillText(String(n - 1), l + pw, t + ph + 3);
    const parts = this.mode === 'parts';
    for (const { series: s, color, wide } of this.lines()) {
      // "before" wide and translucent under a thin "after": both stay visible where they are equal.
      ctx.strokeStyle = color;
      ctx.globalAlpha = wide ? (parts ? 0.45 : 0.75) : 1;
      ctx.lineWidth = wide ? 3.2 : 1.5;
      ctx.beginPath();
      let open = false;
      s.values.forEach((v, i) => {
        if (v === null) { open = false; return; }
        if (!open) { ctx.moveTo(X(i), Y(v)); open = true; } else ctx.lineTo(X(i), Y(v));
      });
      ctx.stroke();
      ctx.globalAlpha = 1;
      // isolated points (a single defined frame between gaps) as dots
      ctx.fillStyle = color;
      s.values.forEach((v, i) => {
        if (v !== null && (s.values[i - 1] ?? null) === null && (s.values[i + 1] ?? null) === null) {
          const r = wide ? 3 : 1.5;
          ctx.fillRect(X(i) - r, Y(v) - r, 2 * r, 2 * r);
        }
      });
    }
    const x = Math.round(X(Math.min(frame, n - 1))) + 0.5;
    ctx.strokeStyle = COLORS.playhead;
    ctx.lineWidth = 1;
    ctx.beginPath();
    ctx.moveTo(x, t);
    ctx.lineTo(x, t + ph);
    ctx.stroke();
    if (parts) {
      // The parts with penetration at this frame, "after" where it exists (else "before"), largest first.
      const side = this.data.parts.after ?? this.data.parts.before;
      const at = PARTS.map((p) => ({ p, v: valueAt(side[p.id], frame) })).filter((x) => x.v);
      at.sort((a, b) => b.v - a.v);
      this.readout.innerHTML = at.length
        ? at.slice(0, 3).map((x) => `<b style="color:${x.p.color}">${x.p.label} ${formatNumber(x.v)}</b>`).join(' ')
        : 'none';
    } else {
      const bv = valueAt(this.data.before, frame);
      const av = valueAt(this.data.after, frame);
      this.readout.innerHTML = `<b style="color:${COLORS.before}">${formatNumber(bv)}</b> → <b style="color:${COLORS.after}">${formatNumber(av)}</b>`;
    }
    this.container.dataset.playhead = String(frame);
  }

  dispose() {
    this.resizeObserver.disconnect();
  }
}

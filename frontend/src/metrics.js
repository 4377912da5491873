/**
 * Reads a job's metrics JSON into what the viewer draws: per-frame chart series, summary rows (before | after),
 * contact markers and penetration highlights. Pure (no DOM), unit tested in test/metrics.test.js.
 *
 * Schemas understood (see docs/metrics.md and retarget_core/metrics/report.py):
 *  - "1.0": { frames, fps, before: {summary, series}, after: {summary, series} | null, source_contacts: {pairs},
 *            improvement, notes, context }. A series is {unit, values: [number|null]} (null: undefined there).
 *  - "0.1": { source: {frames, fps, mapping}, target: {mapping}, summary: {}, warnings } with no series.
 * Optional fields the viewer uses when present (proposed to the metrics owner; see docs/frontend.md):
 *  - source_contacts.vertex_pairs: {frame, source_i, source_j, target_i, target_j} parallel arrays (M,)
 *  - before|after.penetration_vertices: {frame, vertex, depth?} parallel arrays (K,): vertices deeper than
 *    the tolerance at each frame (depth in cm at 1.80 m).
 * Anything missing gives null/empty, never an exception: the viewer then says "no data for this job".
 */

/** The three charts of the review viewer and the series names that can feed each (first found wins). */
export const CHARTS = [
  { id: 'penetration', title: 'Penetration depth', keys: ['penetration_max_depth', 'penetration_depth', 'collision_depth'] },
  { id: 'contact', title: 'Contact distance', keys: ['contact_distance'] },
  { id: 'skate', title: 'Foot skate', keys: ['foot_skate'] },
];

/** Body parts of the per-part penetration split (metrics' penetrating_vertices_percent_<part>), with colours. */
export const PARTS = [
  { id: 'head', label: 'head', color: '#b07cd8' },
  { id: 'torso', label: 'torso', color: '#e67e22' },
  { id: 'left_arm', label: 'left arm', color: '#2e86de' },
  { id: 'right_arm', label: 'right arm', color: '#00b8b8' },
  { id: 'left_leg', label: 'left leg', color: '#27ae60' },
  { id: 'right_leg', label: 'right leg', color: '#c4d936' },
];

/** Human labels of summary fields; fields not listed are still shown, with their key as label. */
export const SUMMARY_LABELS = {
  penetration_max_depth: 'Penetration, deepest',
  penetration_mean_depth: 'Penetration, mean of per-frame max',
  penetration_volume: 'Penetration volume',
  penetrating_vertices_percent: 'Penetrating vertices',
  penetrating_vertices_percent_by_part: 'Penetrating vertices',
  penetrating_frames_percent: 'Frames with penetration',
  deep_frames_percent: 'Frames deeper than 1 cm',
  deep_frames_percent_by_cause: 'Frames deeper than 1 cm',
  contact_pairs: 'Contact vertex pairs',
  contact_frames: 'Frames with contacts',
  contact_distance_mean: 'Contact distance, mean',
  contact_mse: 'Contact error (MSE)',
  contact_satisfied_percent: 'Contacts kept',
  foot_contact_accuracy: 'Foot contact accuracy',
  foot_skate: 'Foot skate',
  foot_contact_frames: 'Frames with a planted foot',
  ground_penetration_mean: 'Ground penetration, mean',
  ground_penetration_max: 'Ground penetration, max',
  global_position_error: 'Global position error',
  global_position_mse: 'Global position MSE',
  mpjpe: 'MPJPE vs. before',
  m_c: 'Collision M_c',
  m_i: 'Collision M_i',
  m_o: 'Collision M_o',
  acceleration: 'Acceleration',
  jerk: 'Jerk',
};

/** Summary fields where larger is better (for colouring the change); all others: smaller is better. */
const HIGHER_IS_BETTER = new Set(['contact_satisfied_percent', 'foot_contact_accuracy']);
/** Summary fields that are context, not quality (no colouring). */
const NEUTRAL = new Set(['frames', 'fps', 'contact_pairs', 'contact_frames', 'foot_contact_frames', 'mpjpe']);
const PERCENT = new Set(['penetrating_vertices_percent', 'penetrating_frames_percent', 'contact_satisfied_percent',
  'penetrating_vertices_percent_by_part', 'deep_frames_percent', 'deep_frames_percent_by_cause']);

/** Why a frame is deeper than 1 cm (metrics/deep_frames.py): the labels of deep_frames_percent_by_cause's rows. */
const DEEP_CAUSE_LABELS = {
  pose: 'a joint rotation could mend',
  placement: 'held by the hands and feet',
  fold: 'skinning fold',
};

const isObj = (v) => v != null && typeof v === 'object' && !Array.isArray(v);
const isNum = (v) => typeof v === 'number' && Number.isFinite(v);

/**
 * A series as {unit, values} from {unit, values} or a bare array; null when absent or without a finite value.
 * @returns {{unit: string, values: (number|null)[], count: number} | null}
 */
export function readSeries(raw) {
  let unit = '';
  let values = null;
  if (Array.isArray(raw)) values = raw;
  else if (isObj(raw) && Array.isArray(raw.values)) { values = raw.values; unit = String(raw.unit ?? ''); }
  if (!values) return null;
  const clean = values.map((v) => (isNum(v) ? v : null));
  const count = clean.reduce((n, v) => n + (v === null ? 0 : 1), 0);
  if (count === 0) return null;
  return { unit, values: clean, count };
}

/** Summary value of one field: a Measure ({value, value_at_180, unit}) or a plain number. */
function readMeasure(key, raw) {
  if (isObj(raw)) {
    const at180 = isNum(raw.value_at_180) ? raw.value_at_180 : null;
    const own = isNum(raw.value) ? raw.value : null;
    const unit = String(raw.unit ?? '');
    return { value: at180 ?? own, unit: at180 !== null && unit ? `${unit} at 1.80 m` : unit, own };
  }
  if (isNum(raw)) return { value: raw, unit: PERCENT.has(key) ? '%' : '', own: raw };
  return { value: null, unit: '', own: null };
}

function methodOf(report, name) {
  const m = report?.[name];
  if (isObj(m)) return m;
  const s = report?.summary?.[name];
  return isObj(s) ? { summary: s } : null;
}

/**
 * Summary rows for the before | after table.
 * @returns {{key: string, label: string, unit: string, before: number|null, after: number|null,
 *            delta: number|null, verdict: 'better'|'worse'|'same'|null}[]}
 */
export function summaryRows(report) {
  const before = methodOf(report, 'before')?.summary;
  const after = methodOf(report, 'after')?.summary;
  if (!isObj(before) && !isObj(after)) return [];
  const keys = [];
  for (const k of [...Object.keys(before ?? {}), ...Object.keys(after ?? {})]) {
    if (!keys.includes(k) && k !== 'frames' && k !== 'fps') keys.push(k);
  }
  const order = Object.keys(SUMMARY_LABELS);
  keys.sort((a, b) => (order.indexOf(a) + 1 || 999) - (order.indexOf(b) + 1 || 999));
  return keys.flatMap((key) => (isSplit(before?.[key]) || isSplit(after?.[key])
    ? splitRows(key, before?.[key], after?.[key])
    : [row(key, before?.[key], after?.[key])]));
}

/** A summary field that is a split by name ({head: 0.1, torso: 0.2, ...}), not a Measure. */
function isSplit(raw) {
  return isObj(raw) && !('value' in raw) && !('value_at_180' in raw) && Object.values(raw).some(isNum);
}

/** One row per entry of a split field (key "<field>.<part>"), in PARTS order first. */
function splitRows(key, before, after) {
  const names = [];
  for (const k of [...Object.keys(before ?? {}), ...Object.keys(after ?? {})]) if (!names.includes(k)) names.push(k);
  const order = PARTS.map((p) => p.id);
  names.sort((a, b) => (order.indexOf(a) + 1 || 999) - (order.indexOf(b) + 1 || 999));
  const base = SUMMARY_LABELS[key] ?? key.replace(/_/g, ' ');
  return names.map((n) => {
    const r = row(key, isObj(before) ? before[n] : undefined, isObj(after) ? after[n] : undefined);
    const part = PARTS.find((p) => p.id === n);
    const name = part ? part.label : (DEEP_CAUSE_LABELS[n] ?? n.replace(/_/g, ' '));
    return { ...r, key: `${key}.${n}`, label: `${base}, ${name}`, part: n };
  });
}

/** One before | after row of summary field `key`. */
function row(key, rawBefore, rawAfter) {
  const b = readMeasure(key, rawBefore);
  const a = readMeasure(key, rawAfter);
  const delta = b.value !== null && a.value !== null ? a.value - b.value : null;
  let verdict = null;
  if (delta !== null && !NEUTRAL.has(key)) {
    const eps = 1e-9 + 1e-6 * Math.max(Math.abs(a.value), Math.abs(b.value));
    if (Math.abs(delta) <= eps) verdict = 'same';
    else verdict = (delta < 0) !== HIGHER_IS_BETTER.has(key) ? 'better' : 'worse';
  }
  const unit = b.unit || a.unit || (PERCENT.has(key) ? '%' : '');
  return { key, label: SUMMARY_LABELS[key] ?? key.replace(/_/g, ' '), unit, before: b.value, after: a.value, delta, verdict };
}

/** The per-frame series of one chart for before and after (either may be null). */
export function chartData(report, chart) {
  const out = { id: chart.id, title: chart.title, key: null, unit: '', before: null, after: null };
  for (const key of chart.keys) {
    const b = readSeries(methodOf(report, 'before')?.series?.[key]);
    const a = readSeries(methodOf(report, 'after')?.series?.[key]);
    if (b || a) {
      out.key = key;
      out.before = b;
      out.after = a;
      out.unit = (a ?? b).unit;
      break;
    }
  }
  return out;
}

/**
 * The per-part split of penetrating vertices for the penetration chart: {unit, before: {part: series},
 * after: {part: series}} from series penetrating_vertices_percent_<part>; null when no part has data.
 */
export function partSeries(report) {
  const out = { unit: '%', before: null, after: null };
  for (const name of ['before', 'after']) {
    const series = methodOf(report, name)?.series;
    const got = {};
    for (const p of PARTS) {
      const s = readSeries(series?.[`penetrating_vertices_percent_${p.id}`]);
      if (s) got[p.id] = s;
    }
    if (Object.keys(got).length) out[name] = got;
  }
  return out.before || out.after ? out : null;
}

/** Short names of the source flags (metrics/source.py) for the source pane's list. */
const SOURCE_FLAG_LABELS = {
  hand_inside_body: 'hand inside the body',
  foot_skate: 'planted feet skate',
  foot_slide: 'feet slide on the floor',
  below_floor: 'below the floor',
  floats: 'feet above the floor',
  jitter: 'jitter',
};

/** Labels and units of the source figures the source pane lists (metrics' `source`, see docs/metrics.md). */
const SOURCE_FIGURES = [
  ['hand_inside_frames_percent', 'hand > 1 cm inside the body', '% of frames'],
  ['hand_depth_max', 'deepest hand', ''],
  ['foot_skate', 'planted-foot skate', ''],
  ['foot_slide_frames_percent', 'feet sliding on the floor', '% of floor frames'],
  ['ground_below_frames_percent', 'below the floor > 1 cm', '% of frames'],
  ['foot_float_mean', 'feet above the floor', ''],
  ['jerk', 'jerk', ''],
  ['penetrating_vertices_percent', 'penetrating vertices', '%'],
];

/**
 * What the metrics say about the source on its own body: {body, flags: [{name, label, value, threshold, unit,
 * message}], figures:
 * [{key, label, value, unit}]} or null (older jobs have no `source`).
 */
export function sourceQuality(report) {
  const src = report?.source;
  if (!isObj(src)) return null;
  const flags = Array.isArray(src.flags)
    ? src.flags.filter((f) => isObj(f) && typeof f.message === 'string').map((f) => ({
      name: String(f.name ?? ''),
      label: SOURCE_FLAG_LABELS[f.name] ?? String(f.name ?? '').replace(/_/g, ' '),
      value: isNum(f.value) ? f.value : null,
      threshold: isNum(f.threshold) ? f.threshold : null,
      unit: String(f.unit ?? ''),
      message: f.message,
    }))
    : [];
  const figures = [];
  for (const [key, label, unit] of SOURCE_FIGURES) {
    const m = readMeasure(key, src[key]);
    if (m.value !== null) figures.push({ key, label, value: m.value, unit: unit || m.unit });
  }
  return { body: typeof src.body === 'string' ? src.body : null, flags, figures };
}

/** Parallel arrays of equal length from an object of arrays, or null. */
function parallel(obj, names) {
  if (!isObj(obj)) return null;
  const arrays = names.map((n) => obj[n]);
  if (!arrays.every(Array.isArray)) return null;
  const n = arrays[0].length;
  if (!arrays.every((a) => a.length === n) || n === 0) return null;
  return Object.fromEntries(names.map((k, i) => [k, arrays[i]]));
}

/** Group parallel arrays by frame: Map(frame -> list of row indices). */
function byFrame(frames) {
  const m = new Map();
  frames.forEach((f, i) => {
    if (!Number.isInteger(f)) return;
    if (!m.has(f)) m.set(f, []);
    m.get(f).push(i);
  });
  return m;
}

/** Foot contact labels (0/1 per frame) of one method: {jointCanonical: values}. */
function footLabels(method) {
  const names = { left_toe: 'LeftToeBase', left_heel: 'LeftFoot', right_toe: 'RightToeBase', right_heel: 'RightFoot' };
  const out = {};
  const series = method?.series;
  if (!isObj(series)) return out;
  for (const [k, v] of Object.entries(series)) {
    const m = /^foot_contact_(.+)$/.exec(k);
    if (!m || !names[m[1]]) continue;
    const s = readSeries(v);
    if (s) out[names[m[1]]] = s.values.map((x) => (x ? 1 : 0));
  }
  return out;
}

/** Penetrating vertices per frame of one method: Map(frame -> {vertex: number[], depth: number[]}) or null. */
function penetration(method) {
  const p = parallel(method?.penetration_vertices, ['frame', 'vertex']);
  if (!p) return null;
  const depth = Array.isArray(method.penetration_vertices.depth) ? method.penetration_vertices.depth : null;
  const out = new Map();
  for (const [f, rows] of byFrame(p.frame)) {
    out.set(f, { vertex: rows.map((i) => p.vertex[i]), depth: rows.map((i) => (depth ? depth[i] : null)) });
  }
  return out;
}

/** The joint name the target (or source) skeleton uses for a canonical joint, from a mapping report. */
export function mappingOf(report, side) {
  const candidates = [report?.[side]?.mapping, report?.context?.[`${side}_mapping`], report?.context?.[side]?.mapping];
  for (const m of candidates) {
    const joints = isObj(m?.joints) ? m.joints : isObj(m) ? m : null;
    if (!joints) continue;
    const out = {};
    for (const [canon, v] of Object.entries(joints)) {
      const name = typeof v === 'string' ? v : v?.joint;
      if (typeof name === 'string') out[canon] = name;
    }
    if (Object.keys(out).length) return out;
  }
  return null;
}

/**
 * What each refinement stage did, in pipeline order: [{name, seconds, framesChanged, figures: [[key, value]]}]
 * from context.stage_reports (numbers and booleans only; nested objects are left out).
 */
export function stageReports(context) {
  const reports = isObj(context) && isObj(context.stage_reports) ? context.stage_reports : {};
  return Object.entries(reports).filter(([, r]) => isObj(r)).map(([name, r]) => ({
    name,
    seconds: isNum(r.seconds) ? r.seconds : null,
    framesChanged: isNum(r.frames_changed) ? r.frames_changed : null,
    figures: Object.entries(r).filter(([k, v]) => !['seconds', 'frames_changed'].includes(k)
      && (isNum(v) || typeof v === 'boolean')),
  }));
}

/**
 * Everything the viewer takes from a metrics JSON.
 * @param {any} report the parsed metrics JSON (or null when the job has none)
 */
export function readMetrics(report) {
  const ok = isObj(report);
  const frames = ok ? (isNum(report.frames) ? report.frames : isNum(report.source?.frames) ? report.source.frames : null) : null;
  const fps = ok ? (isNum(report.fps) ? report.fps : isNum(report.source?.fps) ? report.source.fps : null) : null;
  const charts = CHARTS.map((c) => chartData(ok ? report : null, c));
  const parts = ok ? partSeries(report) : null;
  if (parts) charts.find((c) => c.id === 'penetration').parts = parts;
  const sc = ok && isObj(report.source_contacts) ? report.source_contacts : {};
  const pairs = Array.isArray(sc.pairs)
    ? sc.pairs.filter((p) => isObj(p) && typeof p.hand === 'string' && typeof p.other === 'string'
      && Number.isInteger(p.first) && Number.isInteger(p.last))
    : [];
  const vp = parallel(sc.vertex_pairs, ['frame', 'source_i', 'source_j', 'target_i', 'target_j']);
  const vertexPairs = vp ? { ...vp, byFrame: byFrame(vp.frame) } : null;
  const before = ok ? methodOf(report, 'before') : null;
  const after = ok ? methodOf(report, 'after') : null;
  return {
    schema: ok ? String(report.schema_version ?? 'unknown') : null,
    frames,
    fps,
    charts,
    hasSeries: charts.some((c) => c.before || c.after),
    summary: ok ? summaryRows(report) : [],
    contacts: {
      pairs,
      vertexPairs,
      feet: { before: footLabels(before), after: footLabels(after) },
    },
    penetration: { before: penetration(before), after: penetration(after) },
    mapping: { source: ok ? mappingOf(report, 'source') : null, target: ok ? mappingOf(report, 'target') : null },
    stages: ok ? stageReports(report.context) : [],
    source: ok ? sourceQuality(report) : null,
    notes: ok ? [...(Array.isArray(report.notes) ? report.notes : []), ...(Array.isArray(report.warnings) ? report.warnings : [])].map(String) : [],
  };
}

/** Hand contacts (from `pairs`) active at `frame`: [{hand, other}]. */
export function activePairs(pairs, frame) {
  return pairs.filter((p) => frame >= p.first && frame <= p.last).map((p) => ({ hand: p.hand, other: p.other }));
}

/** The value of a series at a frame (null outside or undefined). */
export function valueAt(series, frame) {
  if (!series || frame < 0 || frame >= series.values.length) return null;
  return series.values[frame];
}

/** [min, max] over the finite values of several series (0-based: min is at most 0). */
export function seriesRange(list) {
  let lo = 0;
  let hi = 0;
  for (const s of list) {
    if (!s) continue;
    for (const v of s.values) {
      if (v === null) continue;
      if (v < lo) lo = v;
      if (v > hi) hi = v;
    }
  }
  if (hi - lo < 1e-12) hi = lo + 1;
  return [lo, hi];
}

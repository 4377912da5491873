// Unit tests of the metrics reader (node --test). The browser test tests/e2e drives the same code with a metrics
// JSON built by the schema's own pydantic models.
import assert from 'node:assert/strict';
import { test } from 'node:test';
import { activePairs, chartData, CHARTS, readMetrics, readSeries, seriesRange, summaryRows, valueAt } from '../src/metrics.js';

const measure = (v, unit = 'cm') => ({ value: v, value_at_180: v === null ? null : v * 2, unit });

function report10() {
  const pen = Array.from({ length: 10 }, (_, i) => i * 0.5);
  const contact = [null, null, 1, 0.8, 0.5, null, null, null, null, null];
  return {
    schema_version: '1.0', frames: 10, fps: 30,
    before: {
      summary: { frames: 10, fps: 30, penetration_max_depth: measure(4), contact_satisfied_percent: 50, foot_skate: measure(null), contact_pairs: 9 },
      series: {
        penetration_max_depth: { unit: 'cm at 1.80 m', values: pen },
        contact_distance: { unit: 'cm at 1.80 m', values: contact },
        foot_contact_left_toe: { unit: '0/1', values: [1, 1, 1, 0, 0, 0, 0, 1, 1, 1] },
        foot_contact_bogus: { unit: '0/1', values: [1] },
      },
      penetration_vertices: { frame: [0, 0, 3], vertex: [5, 6, 7], depth: [0.1, 0.2, 0.3] },
    },
    after: {
      summary: { frames: 10, fps: 30, penetration_max_depth: measure(1), contact_satisfied_percent: 80, foot_skate: measure(0.2), contact_pairs: 9 },
      series: { penetration_max_depth: { unit: 'cm at 1.80 m', values: pen.map((v) => v / 2) } },
    },
    source_contacts: {
      pairs: [{ hand: 'LeftHand', other: 'Head', frames: 3, first: 2, last: 4 }, { hand: 'x' }],
      vertex_pairs: { frame: [2, 2, 3], source_i: [1, 2, 3], source_j: [4, 5, 6], target_i: [7, 8, 9], target_j: [10, 11, 12] },
    },
    notes: ['a note'],
  };
}

test('series: objects, bare arrays, nulls, non-finite values, absent', () => {
  assert.deepEqual(readSeries({ unit: 'cm', values: [1, null, 'x', NaN, 2] }), { unit: 'cm', values: [1, null, null, null, 2], count: 2 });
  assert.equal(readSeries([1, 2]).count, 2);
  assert.equal(readSeries({ unit: 'cm', values: [null, null] }), null);
  assert.equal(readSeries(undefined), null);
  assert.equal(readSeries({ unit: 'cm' }), null);
});

test('schema 1.0: charts from before and after series, first matching key wins', () => {
  const m = readMetrics(report10());
  assert.equal(m.schema, '1.0');
  assert.equal(m.frames, 10);
  assert.equal(m.fps, 30);
  assert.equal(m.hasSeries, true);
  const [pen, contact, skate] = m.charts;
  assert.equal(pen.key, 'penetration_max_depth');
  assert.equal(pen.before.count, 10);
  assert.equal(pen.after.values[4], 1);
  assert.equal(contact.before.count, 3);
  assert.equal(contact.after, null);
  assert.equal(skate.before, null);
  assert.equal(skate.after, null);
  assert.deepEqual(m.charts.map((c) => c.id), CHARTS.map((c) => c.id));
});

test('a fallback series key feeds the penetration chart', () => {
  const r = { before: { series: { collision_depth: [0, 1, 2] } } };
  assert.equal(chartData(r, CHARTS[0]).key, 'collision_depth');
});

test('summary rows: value at 1.80 m, units, change and verdict (lower is better except kept contacts)', () => {
  const rows = summaryRows(report10());
  const pen = rows.find((r) => r.key === 'penetration_max_depth');
  assert.deepEqual([pen.before, pen.after, pen.delta, pen.verdict, pen.unit], [8, 2, -6, 'better', 'cm at 1.80 m']);
  const kept = rows.find((r) => r.key === 'contact_satisfied_percent');
  assert.deepEqual([kept.delta, kept.verdict, kept.unit], [30, 'better', '%']);
  const skate = rows.find((r) => r.key === 'foot_skate');
  assert.deepEqual([skate.before, skate.after, skate.delta, skate.verdict], [null, 0.4, null, null]);
  const pairs = rows.find((r) => r.key === 'contact_pairs');
  assert.equal(pairs.verdict, null, 'counts are context, not quality');
  assert.ok(!rows.some((r) => r.key === 'frames' || r.key === 'fps'));
  assert.equal(rows[0].key, 'penetration_max_depth', 'known fields first, in a fixed order');
});

test('contacts, feet and penetration per frame', () => {
  const m = readMetrics(report10());
  assert.equal(m.contacts.pairs.length, 1, 'malformed pairs are dropped');
  assert.deepEqual(activePairs(m.contacts.pairs, 3), [{ hand: 'LeftHand', other: 'Head' }]);
  assert.deepEqual(activePairs(m.contacts.pairs, 5), []);
  assert.deepEqual(m.contacts.vertexPairs.byFrame.get(2), [0, 1]);
  assert.deepEqual(m.contacts.feet.before, { LeftToeBase: [1, 1, 1, 0, 0, 0, 0, 1, 1, 1] });
  assert.deepEqual(m.penetration.before.get(0).vertex, [5, 6]);
  assert.deepEqual(m.penetration.before.get(3).depth, [0.3]);
  assert.equal(m.penetration.after, null);
  assert.deepEqual(m.notes, ['a note']);
});

test('schema 0.1 (no series, empty summary) and no metrics at all: nothing to draw, no exception', () => {
  const old = { schema_version: '0.1', source: { frames: 60, fps: 60, mapping: { joints: { Hips: { joint: 'CC_Base_Hip' } } } }, target: { mapping: { joints: { Hips: { joint: 'hip' } } } }, summary: {}, warnings: ['w'] };
  const m = readMetrics(old);
  assert.equal(m.schema, '0.1');
  assert.equal(m.frames, 60);
  assert.equal(m.hasSeries, false);
  assert.ok(m.charts.every((c) => !c.before && !c.after));
  assert.deepEqual(m.summary, []);
  assert.deepEqual(m.mapping, { source: { Hips: 'CC_Base_Hip' }, target: { Hips: 'hip' } });
  assert.deepEqual(m.notes, ['w']);
  for (const bad of [null, undefined, 'text', 42, []]) {
    const e = readMetrics(bad);
    assert.equal(e.hasSeries, false);
    assert.equal(e.frames, null);
  }
});

test('series helpers', () => {
  const s = readSeries([1, null, -2, 5]);
  assert.equal(valueAt(s, 2), -2);
  assert.equal(valueAt(s, 1), null);
  assert.equal(valueAt(s, 9), null);
  assert.deepEqual(seriesRange([s, null]), [-2, 5]);
  assert.deepEqual(seriesRange([readSeries([0, 0])]), [0, 1]);
});

test('stage reports come in pipeline order with their own figures', async () => {
  const { stageReports } = await import('../src/metrics.js');
  const st = stageReports({ stage_reports: {
    collisions: { frames_changed: 120, seconds: 1.5, penetration_after: 0.2, nested: { x: 1 }, label: 'x' },
    foot_lock: { frames_changed: 0, seconds: 0.1, plants: 4, pelvis_lowered: true },
  } });
  assert.deepEqual(st.map((s) => s.name), ['collisions', 'foot_lock']);
  assert.equal(st[0].framesChanged, 120);
  assert.deepEqual(st[0].figures, [['penetration_after', 0.2]]);
  assert.deepEqual(st[1].figures, [['plants', 4], ['pelvis_lowered', true]]);
  assert.deepEqual(stageReports(null), []);
  assert.deepEqual(stageReports({ stage_reports: 'nope' }), []);
});

test('the per-part penetration split: summary rows per part and series for the penetration chart', async () => {
  const { PARTS, partSeries } = await import('../src/metrics.js');
  const r = report10();
  r.before.summary.penetrating_vertices_percent_by_part = { head: 1.5, torso: 0, left_arm: 0.25, right_arm: 0, left_leg: 0, right_leg: 0 };
  r.after.summary.penetrating_vertices_percent_by_part = { head: 0.5, torso: 0, left_arm: 0.5, right_arm: 0, left_leg: 0, right_leg: 0 };
  r.before.series.penetrating_vertices_percent_head = { unit: '%', values: [0, 1, 2, 3, 0, 0, 0, 0, 0, 0] };
  r.before.series.penetrating_vertices_percent_left_arm = { unit: '%', values: [0, 0, 0.5, 0, 0, 0, 0, 0, 0, 0] };
  r.after.series.penetrating_vertices_percent_head = { unit: '%', values: [0, 0.5, 1, 1, 0, 0, 0, 0, 0, 0] };
  const rows = summaryRows(r).filter((x) => x.key.startsWith('penetrating_vertices_percent_by_part.'));
  assert.deepEqual(rows.map((x) => x.part), PARTS.map((p) => p.id), 'one row per part, in body order');
  const head = rows[0];
  assert.equal(head.label, 'Penetrating vertices, head');
  assert.equal(head.unit, '%');
  assert.equal(head.before, 1.5);
  assert.equal(head.after, 0.5);
  assert.equal(head.verdict, 'better');
  assert.equal(rows[2].verdict, 'worse');
  const parts = partSeries(r);
  assert.deepEqual(Object.keys(parts.before), ['head', 'left_arm']);
  assert.deepEqual(Object.keys(parts.after), ['head']);
  assert.equal(parts.after.head.values[2], 1);
  const m = readMetrics(r);
  assert.equal(m.charts[0].id, 'penetration');
  assert.equal(m.charts[0].parts.before.head.count, 10);
  assert.equal(m.charts[1].parts, undefined, 'only the penetration chart has parts');
  assert.equal(partSeries(report10()), null, 'no split series: no parts');
  assert.equal(readMetrics(report10()).charts[0].parts, undefined);
});

test('the source measured on its own body: flags in words and figures', async () => {
  const { sourceQuality } = await import('../src/metrics.js');
  const r = report10();
  assert.equal(readMetrics(r).source, null, 'older jobs have no source section');
  r.source = {
    body: 'mh_male_average', frames: 10, fps: 30,
    hand_inside_frames_percent: 40, hand_depth_max: measure(1.5),
    foot_skate: measure(null, 'cm/frame'), foot_slide_frames_percent: null, jerk: measure(0.1, 'cm/frame^3'),
    flags: [{ name: 'hand_inside_body', value: 40, threshold: 10, unit: '% of frames', message: 'a hand is inside' }, { name: 'bad' }],
  };
  const q = sourceQuality(r);
  assert.equal(q.body, 'mh_male_average');
  assert.deepEqual(q.flags, [{ name: 'hand_inside_body', label: 'hand inside the body', value: 40, threshold: 10, unit: '% of frames', message: 'a hand is inside' }]);
  const keys = q.figures.map((f) => f.key);
  assert.deepEqual(keys, ['hand_inside_frames_percent', 'hand_depth_max', 'jerk'], 'figures without a value are left out');
  assert.equal(q.figures[1].value, 3, 'lengths at 1.80 m');
  assert.equal(q.figures[0].unit, '% of frames');
  assert.deepEqual(readMetrics(r).source, q);
});

test('frames deeper than 1 cm: the share and one row per cause, labelled for a reviewer', () => {
  const r = report10();
  r.before.summary.deep_frames_percent = 80;
  r.after.summary.deep_frames_percent = 20;
  r.before.summary.deep_frames_percent_by_cause = { pose: 50, placement: 30, fold: 0 };
  r.after.summary.deep_frames_percent_by_cause = { pose: 5, placement: 15, fold: 0 };
  const rows = summaryRows(r);
  const total = rows.find((x) => x.key === 'deep_frames_percent');
  assert.equal(total.label, 'Frames deeper than 1 cm');
  assert.equal(total.unit, '%');
  assert.equal(total.verdict, 'better');
  const causes = rows.filter((x) => x.key.startsWith('deep_frames_percent_by_cause.'));
  assert.deepEqual(causes.map((x) => x.label), [
    'Frames deeper than 1 cm, a joint rotation could mend',
    'Frames deeper than 1 cm, held by the hands and feet',
    'Frames deeper than 1 cm, skinning fold',
  ]);
  assert.equal(causes[1].before, 30);
  assert.equal(causes[1].after, 15);
  assert.equal(causes[2].verdict, 'same');
});

import assert from 'node:assert/strict';
import { test } from 'node:test';
import { esc, formatBytes, formatNumber, formatSeconds } from '../src/format.js';

test('formatting', () => {
  assert.equal(formatNumber(null), '—');
  assert.equal(formatNumber(Number.NaN), '—');
  assert.equal(formatNumber(0), '0');
  assert.equal(formatNumber(3.14159), '3.14');
  assert.equal(formatNumber(0.000123456), '0.000123');
  assert.equal(formatNumber(123.456), '123.5');
  assert.equal(formatNumber(12345.6), '12346');
  assert.equal(formatBytes(512), '512 B');
  assert.equal(formatBytes(2048), '2.00 KB');
  assert.equal(formatSeconds(1.25), '1.3 s');
  assert.equal(formatSeconds(125), '2 min 5 s');
  assert.equal(esc('<a href="x">&\'</a>'), '&lt;a href=&quot;x&quot;&gt;&amp;&#39;&lt;/a&gt;');
});

import assert from 'node:assert/strict';
import { test } from 'node:test';
import { extrasHtml } from '../src/pages/upload.js';

test('extra joints on an upload card: counts by kind, one row per joint, twist share, escaped names', () => {
  const html = extrasHtml({
    LeftHandIndex1: { joint: 'index_01_l', confidence: 0.9, method: 'name', kind: 'finger' },
    LeftHandThumb1: { joint: 'b<1>', confidence: 0.45, method: 'structure', kind: 'finger' },
    LeftForeArmTwist1: { joint: 'lowerarm_twist_01_l', confidence: 0.9, method: 'name', kind: 'twist', share: 0.5 },
  });
  assert.match(html, /2 finger, 0 toe, 1 twist joints/);
  assert.equal((html.match(/data-extra=/g) || []).length, 3);
  assert.match(html, /share 0\.5/);
  assert.match(html, /b&lt;1&gt;/);
  assert.match(html, /class="poor" data-extra="LeftHandThumb1"/);
});

test('no extra joints: says the hands and feet are single joints', () => {
  assert.match(extrasHtml({}), /No fingers, toes or twist bones/);
  assert.match(extrasHtml(undefined), /No fingers/);
});

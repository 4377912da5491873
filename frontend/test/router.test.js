import assert from 'node:assert/strict';
import { test } from 'node:test';
import { parseRoute, reviewHash, shareUrl } from '../src/router.js';

test('routes', () => {
  assert.equal(parseRoute('').name, 'upload');
  assert.equal(parseRoute('#/').name, 'upload');
  assert.deepEqual(parseRoute('#/jobs/job_1/review').params, { id: 'job_1' });
  assert.equal(parseRoute('#/jobs/job_1/review').name, 'review');
  assert.equal(parseRoute('#/jobs/job_1').name, 'job');
  assert.equal(parseRoute('#/jobs?status=failed').query.get('status'), 'failed');
  assert.equal(parseRoute('#/jobs/').name, 'jobs');
  assert.equal(parseRoute('#/batches/b%201').params.id, 'b 1');
  assert.equal(parseRoute('#/nope').name, 'notfound');
});

test('the share URL is origin + path + review hash, nothing else (no key, no query)', () => {
  const loc = { origin: 'https://r.example', pathname: '/', search: '?key=secret', hash: '#/settings?key=secret' };
  const url = shareUrl(loc, 'job_1');
  assert.equal(url, 'https://r.example/#/jobs/job_1/review');
  assert.ok(!url.includes('secret'));
  assert.equal(reviewHash('a/b'), '#/jobs/a%2Fb/review');
});

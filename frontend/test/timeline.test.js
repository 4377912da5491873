import assert from 'node:assert/strict';
import { test } from 'node:test';
import { Timeline } from '../src/viewer/timeline.js';

test('seek clamps, step pauses, listeners get every change once', () => {
  const t = new Timeline(10, 30);
  const seen = [];
  t.on((f) => seen.push(f));
  t.seek(4);
  t.seek(4);
  t.seek(99);
  t.seek(-3);
  assert.deepEqual(seen, [4, 9, 0]);
  t.play();
  assert.equal(t.playing, true);
  t.step(2);
  assert.equal(t.playing, false);
  assert.equal(t.frame, 2);
});

test('playback advances by wall-clock time and speed, loops at the end', () => {
  const t = new Timeline(10, 10);
  t.play();
  t.tick(0);
  t.tick(200); // 0.2 s at 10 fps
  assert.equal(t.frame, 2);
  t.setSpeed(2);
  t.tick(400); // 0.2 s at 2x -> 4 frames more
  assert.equal(t.frame, 6);
  t.tick(650); // 0.25 s at 2x -> 5 frames: past the end, loops
  assert.equal(t.frame, 1);
  t.tick(5000); // a long pause (background tab) counts as 0.25 s at most
  assert.equal(t.frame, 6);
  t.loop = false;
  t.tick(5250); // 5 more frames: past the end, stops on the last frame
  assert.equal(t.frame, 9);
  assert.equal(t.playing, false);
});

test('play from the last frame starts over; one-frame clips do not play', () => {
  const t = new Timeline(5, 30);
  t.seek(4);
  t.play();
  assert.equal(t.frame, 0);
  const one = new Timeline(1, 30);
  one.play();
  assert.equal(one.playing, false);
});

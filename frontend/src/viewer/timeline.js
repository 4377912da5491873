/**
 * The one clock of the review viewer: a frame number shared by every view and chart (frame-locked), with play,
 * pause, step, speed and scrubbing. Listeners get the integer frame; nothing else keeps time.
 */
export class Timeline {
  constructor(frames = 1, fps = 30) {
    this.frames = Math.max(1, frames);
    this.fps = fps > 0 ? fps : 30;
    this.frame = 0;
    this.playing = false;
    this.speed = 1;
    this.loop = true;
    this.listeners = new Set();
    this._pos = 0; // fractional frame while playing
    this._last = null;
  }

  /** Call `fn(frame, timeline)` on every frame change and play-state change; returns an unsubscribe. */
  on(fn) {
    this.listeners.add(fn);
    return () => this.listeners.delete(fn);
  }

  emit() {
    for (const fn of this.listeners) fn(this.frame, this);
  }

  setLength(frames, fps) {
    this.frames = Math.max(1, frames);
    if (fps > 0) this.fps = fps;
    if (this.frame >= this.frames) this.seek(this.frames - 1);
  }

  /** Go to a frame (clamped); stops nothing. */
  seek(frame) {
    const f = Math.max(0, Math.min(this.frames - 1, Math.round(frame)));
    this._pos = f;
    if (f !== this.frame) {
      this.frame = f;
      this.emit();
    }
  }

  step(delta) {
    this.pause();
    this.seek(this.frame + delta);
  }

  play() {
    if (this.playing || this.frames < 2) return;
    if (this.frame >= this.frames - 1) this.seek(0);
    this.playing = true;
    this._last = null;
    this._pos = this.frame;
    this.emit();
  }

  pause() {
    if (!this.playing) return;
    this.playing = false;
    this.emit();
  }

  toggle() {
    if (this.playing) this.pause();
    else this.play();
  }

  setSpeed(s) {
    this.speed = s > 0 ? s : 1;
  }

  /** Advance by wall-clock time (ms, from requestAnimationFrame); called by the render loop. */
  tick(now) {
    if (!this.playing) { this._last = null; return; }
    if (this._last === null) { this._last = now; return; }
    const dt = Math.min(0.25, (now - this._last) / 1000);
    this._last = now;
    this._pos += dt * this.fps * this.speed;
    if (this._pos >= this.frames - 1 + 0.999) {
      if (this.loop) this._pos %= this.frames;
      else { this._pos = this.frames - 1; this.playing = false; }
    }
    const f = Math.min(this.frames - 1, Math.floor(this._pos + 1e-6));
    if (f !== this.frame || !this.playing) {
      this.frame = f;
      this.emit();
    }
  }
}

// A WebXR test shim: just enough of navigator.xr for the phone page, driven by scripted poses.
// Injected with addInitScript before the page's own scripts. The test moves the "phone" with
// window.__xr.moveTo([x, y, z], ms) (linear, per frame) or window.__xr.jump([x, y, z]) (one frame), in the
// WebXR `local` frame (+X right, +Y up, -Z forward, metres). Vibrations are recorded in window.__vibrations.
(() => {
  const FRAME_MS = 1000 / 60;
  const xr = {
    pose: { p: [0, 1.4, 0], q: [0, 0, 0, 1] },
    track: 'tracking', // 'tracking' | 'limited' | 'lost'
    frames: 0,
    sessions: 0,
    motion: null,
    moveTo(p, ms) {
      this.motion = { from: this.pose.p.slice(), to: p.slice(), start: performance.now(), ms: Math.max(ms, 1) };
    },
    jump(p) {
      this.motion = null;
      this.pose = { p: p.slice(), q: this.pose.q.slice() };
    },
    step(now) {
      if (!this.motion) return;
      const t = Math.min(1, (now - this.motion.start) / this.motion.ms);
      const { from, to } = this.motion;
      this.pose = { p: from.map((f, i) => f + (to[i] - f) * t), q: this.pose.q };
      if (t >= 1) this.motion = null;
    },
  };
  window.__xr = xr;
  window.__vibrations = [];
  Object.defineProperty(navigator, 'vibrate', {
    configurable: true,
    value: (pattern) => { window.__vibrations.push(pattern); return true; },
  });

  class FakeSession extends EventTarget {
    constructor() {
      super();
      this.renderState = { baseLayer: null };
      this.ended = false;
      this.callbacks = new Map();
      this.nextHandle = 1;
    }
    updateRenderState(state) { Object.assign(this.renderState, state); }
    async requestReferenceSpace(type) {
      if (!['local', 'viewer', 'local-floor'].includes(type)) throw new DOMException('unsupported', 'NotSupportedError');
      return { type };
    }
    requestAnimationFrame(cb) {
      const handle = this.nextHandle++;
      const id = setTimeout(() => {
        this.callbacks.delete(handle);
        if (this.ended) return;
        const now = performance.now();
        xr.step(now);
        xr.frames += 1;
        const frame = {
          session: this,
          getViewerPose: () => {
            if (xr.track === 'lost') return null;
            const [x, y, z] = xr.pose.p;
            const [qx, qy, qz, qw] = xr.pose.q;
            return {
              emulatedPosition: xr.track === 'limited',
              transform: { position: { x, y, z, w: 1 }, orientation: { x: qx, y: qy, z: qz, w: qw } },
              views: [],
            };
          },
        };
        cb(now, frame);
      }, FRAME_MS);
      this.callbacks.set(handle, id);
      return handle;
    }
    cancelAnimationFrame(handle) {
      clearTimeout(this.callbacks.get(handle));
      this.callbacks.delete(handle);
    }
    async end() {
      this.ended = true;
      this.dispatchEvent(new Event('end'));
    }
  }

  const fakeXr = {
    async isSessionSupported(mode) { return mode === 'immersive-ar'; },
    async requestSession(mode, options) {
      if (mode !== 'immersive-ar') throw new DOMException('unsupported mode', 'NotSupportedError');
      const required = (options && options.requiredFeatures) || [];
      for (const f of required) {
        if (!['local', 'viewer', 'local-floor', 'dom-overlay'].includes(f)) {
          throw new DOMException(`unsupported feature ${f}`, 'NotSupportedError');
        }
      }
      xr.sessions += 1;
      xr.session = new FakeSession();
      return xr.session;
    },
  };
  Object.defineProperty(navigator, 'xr', { configurable: true, value: fakeXr });
  window.XRWebGLLayer = class { constructor() { this.framebuffer = null; } };
})();

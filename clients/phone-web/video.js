// phone2act live video: the camera picked for the preview, as WebRTC H.264 from the gateway (decoded by the
// browser, in hardware where it has a decoder), with glass-to-glass latency shown continuously. Signalling
// goes over the page's own authenticated socket. Each frame's capture time arrives on a data channel keyed by
// its RTP timestamp; the page's clock offset to the gateway comes from `clock` round trips on the control socket
// (the sample of the shortest round trip of the last 20 wins). Where WebRTC cannot connect, the page turns the
// JPEG preview on instead. Loaded after app.js; uses its state (window.phone2act).
'use strict';

(() => {
  const app = window.phone2act;
  const $ = (id) => document.getElementById(id);
  // No decoded frame this long after asking: WebRTC did not get through (UDP blocked, no H.264 decoder).
  const CONNECT_MS = 6000;
  const CLOCK_EVERY_MS = 1000;

  const v = {
    want: false,
    pc: null,
    camera: '',
    since: 0,
    frames: 0,
    frameTimes: [],
    g2g: [], // glass-to-glass latency of recent frames, ms
    g2gAll: [], // of every frame since start (for tests and the summary)
    unmatched: 0,
    captures: new Map(), // rtp timestamp -> capture time (gateway's Unix ms)
    clock: [], // [round trip ms, offset ms] samples: gateway clock - page clock
    offsetMs: null,
    state: 'off',
    reason: '',
    fallbacks: 0,
    bitrateBps: null, // what the gateway's encoder aims at (it follows the link's estimate)
    linkEstimateBps: null, // the gateway's estimate of this page's link
    notes: [], // [page ms, bitrate_bps, link_estimate_bps] of recent frames (for tests)
    generation: 0, // one requestVideoFrameCallback chain per connection
    // The JPEG preview's glass-to-glass latency, on the same clock offset: capture times by frame size.
    previewCaptures: new Map(),
    previewG2g: [],
    lastCaptureMs: null, // capture time (gateway's Unix ms) of the frame last shown, for the headset's panel
    lastFrameAt: 0, // performance.now() of the last frame callback
  };
  app.video = v;

  const pageUnixMs = () => performance.timeOrigin + performance.now();

  function setPill(text, cls) {
    const el = $('st-video');
    el.textContent = text;
    el.className = 'pill' + (cls ? ' ' + cls : '');
  }

  function quantile(values, q) {
    if (!values.length) return NaN;
    const s = values.slice().sort((a, b) => a - b);
    return s[Math.min(s.length - 1, Math.floor(q * s.length))];
  }
  v.quantile = quantile;

  function render() {
    if (!v.want) {
      setPill(v.reason ? `video off · ${v.reason}` : 'video off', v.reason ? 'warn' : '');
      return;
    }
    if (!v.frames) {
      setPill(`${v.camera}: connecting…`, 'warn');
      return;
    }
    const n = v.frameTimes.length;
    const fps = n > 1 ? ((n - 1) * 1000) / (v.frameTimes[n - 1] - v.frameTimes[0]) : 0;
    const p50 = quantile(v.g2g, 0.5);
    const lat = Number.isFinite(p50) ? ` · glass-to-glass ${p50.toFixed(0)} ms` : '';
    const rate = v.bitrateBps ? ` · ${(v.bitrateBps / 1e6).toFixed(2)} Mbit/s` : '';
    setPill(`${v.camera} · ${fps.toFixed(0)} fps${lat}${rate}`, p50 < 150 ? 'ok' : 'warn');
  }

  // ---- clock offset from control-socket round trips -------------------------------------------------------

  function onClock(msg) {
    const now = pageUnixMs();
    const rtt = now - msg.t_page_ms;
    if (!(rtt >= 0 && rtt < 5000)) return;
    v.clock.push([rtt, msg.t_gateway_unix_ms - (msg.t_page_ms + rtt / 2)]);
    if (v.clock.length > 20) v.clock.shift();
    // The shortest round trip bounds the offset's error best (half of it at most).
    v.offsetMs = v.clock.reduce((best, s) => (s[0] < best[0] ? s : best))[1];
  }
  setInterval(() => {
    if (v.want || app.preview.want) app.send({ type: 'clock', t_page_ms: pageUnixMs() });
  }, CLOCK_EVERY_MS);

  // A preview image is on screen once decoded (its load event; the next paint follows within a frame).
  $('preview').addEventListener('load', () => {
    const capture = v.previewCaptures.get(app.preview.bytes);
    if (capture === undefined || v.offsetMs === null) return;
    v.previewG2g.push(pageUnixMs() + v.offsetMs - capture);
    if (v.previewG2g.length > 300) v.previewG2g.shift();
  });

  // ---- WebRTC ---------------------------------------------------------------------------------------------

  function onVideoFrame(generation, now, md) {
    // A callback of an earlier connection ends its chain.
    if (!v.pc || generation !== v.generation) return;
    $('video').requestVideoFrameCallback((t, m) => onVideoFrame(generation, t, m));
    v.frames += 1;
    const t = performance.now();
    v.lastFrameAt = t;
    v.frameTimes.push(t);
    while (v.frameTimes.length && t - v.frameTimes[0] > 2000) v.frameTimes.shift();
    const capture = v.captures.get(md.rtpTimestamp);
    if (capture === undefined || v.offsetMs === null) {
      v.unmatched += 1;
    } else {
      // When the frame is on screen, on the gateway's clock, minus when the camera captured it.
      const shown = performance.timeOrigin + (md.expectedDisplayTime || now) + v.offsetMs;
      const ms = shown - capture;
      v.lastCaptureMs = capture;
      v.g2g.push(ms);
      if (v.g2g.length > 90) v.g2g.shift();
      v.g2gAll.push(ms);
    }
    if (v.frames % 10 === 1) render();
  }

  async function start() {
    teardown();
    $('video-on').checked = true;
    v.want = true;
    v.reason = '';
    v.camera = app.preview.camera;
    v.since = performance.now();
    v.frames = 0;
    v.frameTimes = [];
    v.g2g = [];
    v.g2gAll = [];
    v.unmatched = 0;
    v.captures.clear();
    v.generation += 1;
    v.bitrateBps = null;
    v.linkEstimateBps = null;
    v.state = 'connecting';
    const pc = new RTCPeerConnection({ iceServers: [] });
    v.pc = pc;
    pc.addTransceiver('video', { direction: 'recvonly' });
    // Unordered and never retransmitted: a late note is worth nothing.
    const dc = pc.createDataChannel('frames', { ordered: false, maxRetransmits: 0 });
    dc.onmessage = (e) => {
      let m;
      try { m = JSON.parse(e.data); } catch (_) { return; }
      v.captures.set(m.rtp, m.capture_unix_ms);
      if (m.bitrate_bps) {
        v.bitrateBps = m.bitrate_bps;
        v.linkEstimateBps = m.link_estimate_bps ?? null;
        v.notes.push([performance.now(), m.bitrate_bps, v.linkEstimateBps]);
        if (v.notes.length > 600) v.notes.shift();
      }
      if (v.captures.size > 300) v.captures.delete(v.captures.keys().next().value);
    };
    pc.ontrack = (e) => {
      const el = $('video');
      el.srcObject = new MediaStream([e.track]);
      el.hidden = false;
      el.play().catch(() => { /* muted autoplay is allowed; a refusal shows as no frames */ });
      const generation = v.generation;
      el.requestVideoFrameCallback((t, m) => onVideoFrame(generation, t, m));
    };
    pc.onconnectionstatechange = () => {
      v.state = pc.connectionState;
      if (pc.connectionState === 'failed') fallback('WebRTC could not connect');
    };
    const offer = await pc.createOffer();
    await pc.setLocalDescription(offer);
    if (!app.send({ type: 'video_offer', camera: v.camera, sdp: offer.sdp, host: location.hostname })) {
      fallback('not connected to the gateway');
      return;
    }
    app.send({ type: 'clock', t_page_ms: pageUnixMs() });
    render();
  }

  // Closes the connection (a new offer replaces the gateway's viewer, so no video_off is needed for that).
  function teardown() {
    if (v.pc) {
      v.pc.close();
      v.pc = null;
    }
    v.want = false;
    v.state = 'off';
    const el = $('video');
    el.srcObject = null;
    el.hidden = true;
  }

  function stop() {
    const was = !!v.pc;
    teardown();
    if (was) app.send({ type: 'video_off' });
    $('video-on').checked = false;
    render();
  }

  // WebRTC did not work here: the JPEG preview (over the control socket, which evidently works) instead.
  function fallback(reason) {
    if (!v.want) return;
    stop();
    v.reason = `${reason}; JPEG preview instead`;
    v.fallbacks += 1;
    const cb = $('preview-on');
    if (!cb.checked) {
      cb.checked = true;
      cb.dispatchEvent(new Event('change'));
    }
    render();
  }

  // For the headset (headset.js shows the same video on a panel in the scene).
  v.start = start;
  v.stop = stop;
  v.available = () => !$('video-box').hidden;
  v.pageUnixMs = pageUnixMs;

  app.listeners.push((msg) => {
    if (msg.type === 'clock') onClock(msg);
    else if (msg.type === 'preview_frame') {
      v.previewCaptures.set(msg.bytes, msg.capture_unix_ms);
      if (v.previewCaptures.size > 20) v.previewCaptures.delete(v.previewCaptures.keys().next().value);
      if (v.offsetMs === null) app.send({ type: 'clock', t_page_ms: pageUnixMs() });
    }
    else if (msg.type === 'video_answer' && v.pc && msg.camera === v.camera) {
      v.pc.setRemoteDescription({ type: 'answer', sdp: msg.sdp }).catch((e) => fallback(`bad answer: ${e.message}`));
    } else if (msg.type === 'video' && msg.state === 'error') {
      fallback(msg.message);
    } else if (msg.type === 'welcome') {
      // After a reconnect the gateway has forgotten the viewer.
      // No switch where the gateway's video is off ([gateway.video] enabled = false) or the browser has no WebRTC.
      $('video-box').hidden = !(msg.cameras && msg.cameras.length) || !window.RTCPeerConnection || msg.video === false;
      if (v.want) start();
    }
  });

  setInterval(() => {
    if (v.want && !v.frames && performance.now() - v.since > CONNECT_MS) {
      fallback(`no video frame in ${CONNECT_MS / 1000} s`);
    }
    if (v.want) render();
  }, 500);

  $('video-on').addEventListener('change', (e) => {
    if (e.target.checked) start();
    else stop();
  });
  $('preview-camera').addEventListener('change', () => { if (v.want) start(); });
})();

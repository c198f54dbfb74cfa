// phone2act phone page: streams the WebXR viewer pose (immersive-ar, ARCore on Android Chrome) to the gateway
// over wss at the XR frame rate, with on-screen clutch, gripper and recording buttons, and shows what the
// server did with it. Plain JS, no build step. The pose goes out raw, in WebXR's frame (+X right, +Y up,
// -Z forward, metres): the server's planner does the axis mapping.
'use strict';

(() => {
  const $ = (id) => document.getElementById(id);
  const params = new URLSearchParams(location.search);
  // The token comes from the QR code URL; kept so that a reload or a bookmark without it still works.
  const token = params.get('token') || localStorage.getItem('phone2act.token') || '';
  if (params.get('token')) localStorage.setItem('phone2act.token', token);

  const state = {
    ws: null,
    connected: false,
    fatal: false,
    arm: localStorage.getItem('phone2act.arm') || '',
    arms: [],
    // The gateway says where its rosbridge listens in `welcome` (null when it serves none).
    rosbridgePort: undefined,
    noXrReason: null,
    sessionOpen: false,
    seq: 0,
    engaged: false,
    gripperClosed: false,
    tracking: 'not started',
    xrSession: null,
    refSpace: null,
    xrFrames: 0,
    xrFpsSince: performance.now(),
    xrFps: 0,
    rtts: [],
    last: null, // last feedback
    // The driving policy's plan preview as the gateway last sent it ({p: [[x, y, z]], g: [...], dt_s}, or
    // null), how many previews arrived and how many were drawn, for tests.
    plan: null,
    plansReceived: 0,
    plansDrawn: 0,
    waitingPolicy: '',
    counters: null, // {rejected, clamped}
    recPhase: null,
    // The episode clock's phase ('recording' / 'resetting' / 'idle', from `[recorder] episode_time_s` /
    // `reset_time_s`) and the cues given at its transitions, for tests.
    timerPhase: null,
    cues: [],
    audio: null,
    lastClampBuzz: 0,
    feedbackCount: 0,
    errors: [],
    wasOpen: false,
    cameras: [],
    // [arrival ms, round trip ms] of recent feedback, for the preview's slow-link rule.
    rttLog: [],
    preview: {
      want: false, // the operator turned it on (and the page has not turned it off since)
      camera: localStorage.getItem('phone2act.camera') || '',
      since: 0, // when it was asked for
      lastFrameAt: 0,
      received: 0, // binary messages that arrived, wanted or not
      shown: 0,
      frameTimes: [],
      bytes: 0,
      url: null,
      offReason: '',
      gatewayState: 'off', // what the gateway last said: on / off
    },
  };
  // For tests and debugging from the console, and for headset.js (its own sockets use the same token).
  window.phone2act = state;
  state.token = token;
  state.listeners = [];

  // The camera preview: small and slow on purpose (the recorder has the full images), and it gives way to
  // control. The gateway sends a frame only after the page acknowledged the previous one; the page turns the
  // preview off itself on a slow link, when either
  //  - no frame arrived for 3 s (5 s after asking, for the first one), i.e. 15 frame periods at 5 fps; or
  //  - the control round trip (pose sample -> feedback) has a median above 150 ms over the last 2 s (at
  //    least 10 round trips): the operator's control is suffering, and the images are the first to go.
  const PREVIEW = {
    maxFps: 5, width: 320, firstFrameMs: 5000, lateMs: 3000, rttWindowMs: 2000, rttLimitMs: 150, rttMinCount: 10,
  };

  // Why the preview should be turned off now, or null. Pure, so that it can be checked with made-up numbers.
  function previewVerdict(nowMs, since, lastFrameAt, rttLog) {
    const late = lastFrameAt > since ? nowMs - lastFrameAt : nowMs - since;
    const limit = lastFrameAt > since ? PREVIEW.lateMs : PREVIEW.firstFrameMs;
    if (late > limit) return `no camera frame for ${(late / 1000).toFixed(1)} s`;
    const recent = rttLog.filter(([at]) => nowMs - at <= PREVIEW.rttWindowMs).map(([, ms]) => ms);
    if (recent.length >= PREVIEW.rttMinCount) {
      recent.sort((a, b) => a - b);
      const median = recent[Math.floor(recent.length / 2)];
      if (median > PREVIEW.rttLimitMs) {
        return `slow link: control round trip ${median.toFixed(0)} ms (over ${PREVIEW.rttLimitMs} ms)`;
      }
    }
    return null;
  }
  state.previewVerdict = previewVerdict;

  function nowNs() {
    return Math.round(performance.now() * 1e6);
  }

  function buzz(pattern) {
    if (navigator.vibrate) {
      try { navigator.vibrate(pattern); } catch (_) { /* vibration is best effort */ }
    }
  }

  // A short tone at an episode clock transition: high when an episode starts recording, low when the reset
  // period starts. WebAudio needs a user gesture first (see the pointerdown listener); before one, and where
  // there is no WebAudio, the vibration alone is the cue.
  function beep(freqHz) {
    const ctx = state.audio;
    if (!ctx || ctx.state !== 'running') return false;
    const osc = ctx.createOscillator();
    const gain = ctx.createGain();
    osc.frequency.value = freqHz;
    gain.gain.setValueAtTime(0.2, ctx.currentTime);
    gain.gain.exponentialRampToValueAtTime(0.001, ctx.currentTime + 0.18);
    osc.connect(gain).connect(ctx.destination);
    osc.start();
    osc.stop(ctx.currentTime + 0.2);
    return true;
  }
  document.addEventListener('pointerdown', () => {
    const Ctx = window.AudioContext || window.webkitAudioContext;
    if (!Ctx) return;
    if (!state.audio) state.audio = new Ctx();
    if (state.audio.state === 'suspended') state.audio.resume().catch(() => {});
  }, { capture: true });

  function clockCue(from, to) {
    if (from === null || from === to) return;
    let sound = false;
    if (to === 'resetting') {
      buzz([300, 100, 300]);
      sound = beep(440);
    } else if (to === 'recording' && from === 'resetting') {
      buzz([500]);
      sound = beep(880);
    } else {
      return;
    }
    state.cues.push({ to, sound, at: performance.now() });
  }

  function setPill(el, text, cls) {
    el.textContent = text;
    el.className = 'pill' + (cls ? ' ' + cls : '');
  }

  function notice(text) {
    const n = $('notice');
    n.hidden = !text;
    n.textContent = text || '';
  }

  // ---- socket -------------------------------------------------------------------------------------------

  function connect() {
    if (state.fatal) return;
    const url = `wss://${location.host}/ws?token=${encodeURIComponent(token)}`;
    const ws = new WebSocket(url);
    state.ws = ws;
    setPill($('st-conn'), 'connecting…', 'warn');
    ws.onopen = () => {
      state.connected = true;
      setPill($('st-conn'), 'gateway ok', 'ok');
    };
    ws.onmessage = (ev) => {
      if (typeof ev.data !== 'string') {
        onPreviewFrame(ev.data);
        return;
      }
      let msg;
      try { msg = JSON.parse(ev.data); } catch (_) { return; }
      onMessage(msg);
    };
    ws.onclose = () => {
      state.connected = false;
      state.sessionOpen = false;
      if (state.fatal) return;
      setPill($('st-conn'), 'reconnecting…', 'bad');
      setTimeout(connect, 1000);
    };
  }

  function send(obj) {
    if (state.ws && state.ws.readyState === WebSocket.OPEN) {
      state.ws.send(JSON.stringify(obj));
      return true;
    }
    return false;
  }

  function hello(takeOver) {
    // While headset controllers drive, their own sockets hold the arms (headset.js).
    if (!state.arm || state.headsetActive) return;
    send({ type: 'hello', arm: state.arm, take_over: !!takeOver });
  }

  function onMessage(msg) {
    // video.js and others see every message first (none of them changes this page's state).
    for (const listener of state.listeners) listener(msg);
    switch (msg.type) {
      case 'welcome': {
        state.welcome = msg;
        state.arms = msg.arms && msg.arms.length ? msg.arms : [msg.default_arm];
        if (!state.arms.includes(state.arm)) state.arm = state.arms.includes(msg.default_arm) ? msg.default_arm : state.arms[0];
        const sel = $('arm');
        sel.innerHTML = '';
        for (const a of state.arms) {
          const o = document.createElement('option');
          o.value = a;
          o.textContent = a;
          sel.appendChild(o);
        }
        sel.value = state.arm;
        state.rosbridgePort = msg.rosbridge_port;
        renderNoXr();
        setCameras(msg.cameras || []);
        // After a reconnect this phone takes its arm back: its old stream may not have timed out yet.
        hello(state.wasOpen);
        break;
      }
      case 'session':
        if (msg.state === 'open') {
          state.sessionOpen = true;
          state.wasOpen = true;
          $('take-over').hidden = true;
          notice('');
          setPill($('st-conn'), `driving ${msg.arm}`, 'ok');
        } else if (msg.state === 'retrying') {
          state.sessionOpen = false;
          setPill($('st-conn'), 'server unavailable, retrying', 'warn');
        } else if (msg.state === 'refused') {
          state.sessionOpen = false;
          state.wasOpen = false;
          setPill($('st-conn'), `arm ${msg.arm} refused`, 'bad');
          notice(`Arm "${msg.arm}": ${msg.message}`);
          $('take-over').hidden = msg.code !== 'AlreadyExists';
        }
        break;
      case 'feedback':
        onFeedback(msg);
        break;
      case 'preview':
        state.preview.gatewayState = msg.state;
        // The gateway stopped it (unknown camera, no camera list): nothing to tell it back.
        if (msg.state === 'off' && msg.reason !== 'asked') previewOff(msg.reason, false);
        else renderPreview();
        break;
      case 'error':
        state.errors.push(msg.message);
        if (msg.fatal) {
          state.fatal = true;
          setPill($('st-conn'), 'not paired', 'bad');
          notice(msg.message);
        } else {
          notice(msg.message);
          setTimeout(() => notice(''), 3000);
        }
        break;
      default:
        break;
    }
  }

  function onFeedback(fb) {
    state.last = fb;
    state.feedbackCount += 1;
    if (fb.t_ns > 0) {
      const rtt = performance.now() - fb.t_ns / 1e6;
      if (rtt >= 0 && rtt < 10000) {
        state.rtts.push(rtt);
        if (state.rtts.length > 100) state.rtts.shift();
        const now = performance.now();
        state.rttLog.push([now, rtt]);
        while (state.rttLog.length && now - state.rttLog[0][0] > PREVIEW.rttWindowMs) state.rttLog.shift();
      }
    }
    if (fb.error) notice(fb.error);
    const s = fb.state;
    if (s) {
      state.engaged = !!s.engaged;
      state.gripperClosed = s.gripper_target > 0.5;
      // Counters, not verdicts, so a buzz happens once per event even if feedback is dropped or repeated.
      if (state.counters) {
        if (s.rejected > state.counters.rejected) {
          buzz(120);
          gateEvent('rejected', s.verdict.startsWith('rejected') ? s.reason : 'a step was too large');
        } else if (s.clamped > state.counters.clamped) {
          if (performance.now() - state.lastClampBuzz > 500) {
            state.lastClampBuzz = performance.now();
            buzz(40);
          }
          gateEvent('clamped', s.verdict === 'clamped' ? s.reason : 'workspace limit');
        }
      }
      state.counters = { rejected: s.rejected, clamped: s.clamped };
      // One frame's verdict is gone by the next frame: a rejection or clamp stays on screen for 4 s.
      const gate = $('st-gate');
      const ev = state.gateEvent;
      if (ev && performance.now() - ev.at < 4000) {
        gate.textContent = `${ev.kind}: ${ev.reason} (${s.rejected} rejected, ${s.clamped} clamped)`;
        gate.className = ev.kind === 'rejected' ? 'verdict-rejected_jump' : 'verdict-clamped';
      } else {
        gate.textContent = s.verdict + (s.reason ? ` — ${s.reason}` : '');
        gate.className = 'verdict-' + s.verdict;
      }
      // Who drives: the operator, a policy session (by name, loading or driving), or nobody; and a policy the
      // operator took the arm from, which waits for the hand-back button.
      let driver = 'released (robot holds)';
      if (s.engaged) driver = 'ENGAGED (phone drives)';
      else if (s.owner === 'policy') {
        const name = s.policy || 'policy';
        driver = s.policy_loading ? `policy ${name} loading (robot holds)` : `policy ${name} drives`;
      }
      state.waitingPolicy = s.waiting_policy || '';
      if (state.waitingPolicy) driver += ` · policy ${state.waitingPolicy} waiting`;
      $('st-clutch').textContent = driver;
      const handBack = $('hand-back');
      handBack.hidden = !state.waitingPolicy;
      handBack.textContent = `Hand back to ${state.waitingPolicy}`;
      // A message without `preview` keeps the last one (the gateway sends it at most 5 times a second).
      if ('preview' in fb) {
        state.plan = fb.preview;
        state.plansReceived += 1;
      }
      drawPlan(s.owner === 'policy' ? state.plan : null, s.ee_m);
      $('st-gripper').textContent = state.gripperClosed ? 'closed' : 'open';
    }
    const r = fb.recording;
    if (r) {
      if (state.recPhase !== null && r.phase !== state.recPhase) buzz([60, 60, 60]);
      state.recPhase = r.phase;
      const rec = $('st-rec');
      rec.className = r.phase === 'recording' ? 'recording' : '';
      rec.textContent = r.phase === 'recording' || r.phase === 'paused'
        ? `${r.phase.toUpperCase()} ep ${r.episode} · ${r.frames} frames · ${r.duration_s.toFixed(1)} s · "${r.task}"`
        : `${r.phase} · ${r.saved} saved`;
      const left = typeof r.remaining_s === 'number' ? Math.ceil(r.remaining_s) : null;
      if (r.resetting) {
        rec.textContent = `RESET · ${r.saved} saved · reset the scene`;
      } else if (left !== null && (r.phase === 'recording' || r.phase === 'paused')) {
        rec.textContent += ` · ${left} s left`;
      }
      const timer = r.resetting ? 'resetting' : (r.phase === 'recording' || r.phase === 'paused' ? 'recording' : 'idle');
      clockCue(state.timerPhase, timer);
      state.timerPhase = timer;
      const cd = $('countdown');
      cd.hidden = left === null;
      if (left !== null) {
        cd.textContent = r.resetting ? `reset ${left} s` : `${left} s`;
        cd.className = r.resetting ? 'countdown resetting' : 'countdown';
      }
      if (r.warning) rec.textContent += ` · ${r.warning}`;
      // The outcome buttons save the episode in progress, so they are live only while one is.
      const live = r.phase === 'recording' || r.phase === 'paused';
      $('rec-success').disabled = !live;
      $('rec-failure').disabled = !live;
      // `[recorder] highlight_s`: while idle the recorder keeps the last seconds; the button saves them.
      const hl = $('rec-highlight');
      const kept = typeof r.highlight_buffered_s === 'number' ? r.highlight_buffered_s : 0;
      hl.hidden = !(r.highlight_s > 0);
      hl.disabled = live || kept <= 0;
      hl.textContent = `⟲ SAVE LAST ${kept.toFixed(1)} s`;
      // Storage upload of the saved episodes (empty when the server has no [storage]).
      if (r.upload) rec.textContent += ` · upload: ${r.upload}`;
    }
    render();
  }

  // The plan preview: the remaining steps of the policy's chunk as a path seen from above (x, y) and from the
  // side (x, z), one scale for both so that distances compare, the arm's measured tool position as a ring;
  // below, the gripper targets over the same steps (0 open at the bottom, 1 closed at the top).
  function drawPlan(plan, eeM) {
    const box = $('plan-box');
    box.hidden = !plan || !plan.p || plan.p.length === 0;
    if (box.hidden) return;
    const pts = plan.p;
    const here = Array.isArray(eeM) ? eeM : pts[0];
    const all = pts.concat([here]);
    const lo = [0, 1, 2].map((i) => Math.min(...all.map((p) => p[i])));
    const hi = [0, 1, 2].map((i) => Math.max(...all.map((p) => p[i])));
    // At least 4 cm across, so that a plan that barely moves does not look like a big one.
    const span = Math.max(0.04, ...[0, 1, 2].map((i) => hi[i] - lo[i]));
    const mid = [0, 1, 2].map((i) => (lo[i] + hi[i]) / 2);
    const c = $('plan-path');
    const g = c.getContext('2d');
    g.clearRect(0, 0, c.width, c.height);
    const half = c.width / 2;
    const scale = (Math.min(half, c.height) - 20) / span;
    // Each view maps (horizontal axis, vertical axis) of the robot frame to canvas pixels; up is +y or +z.
    const views = [
      { x0: half / 2, h: 1, v: 0, hSign: -1, label: 'top' },   // from above: robot +y to the left, +x up
      { x0: half + half / 2, h: 0, v: 2, hSign: 1, label: 'side' }, // from the side: +x right, +z up
    ];
    g.strokeStyle = '#444';
    g.beginPath(); g.moveTo(half, 0); g.lineTo(half, c.height); g.stroke();
    for (const view of views) {
      const px = (p) => [view.x0 + view.hSign * (p[view.h] - mid[view.h]) * scale,
        c.height / 2 - (p[view.v] - mid[view.v]) * scale];
      g.fillStyle = '#777';
      g.font = '11px system-ui';
      g.fillText(view.label, view.x0 - half / 2 + 4, 12);
      g.strokeStyle = '#4fc3f7';
      g.lineWidth = 2;
      g.beginPath();
      pts.forEach((p, k) => { const [x, y] = px(p); if (k === 0) g.moveTo(x, y); else g.lineTo(x, y); });
      g.stroke();
      g.fillStyle = '#4fc3f7';
      for (const p of pts) { const [x, y] = px(p); g.fillRect(x - 1.5, y - 1.5, 3, 3); }
      const [ex, ey] = px(pts[pts.length - 1]);
      g.fillStyle = '#ffca28';
      g.beginPath(); g.arc(ex, ey, 4, 0, 2 * Math.PI); g.fill();
      const [hx, hy] = px(here);
      g.strokeStyle = '#fff';
      g.lineWidth = 2;
      g.beginPath(); g.arc(hx, hy, 6, 0, 2 * Math.PI); g.stroke();
    }
    const gc = $('plan-gripper');
    const gg = gc.getContext('2d');
    gg.clearRect(0, 0, gc.width, gc.height);
    const w = gc.width / Math.max(1, plan.g.length);
    gg.fillStyle = '#ce93d8';
    plan.g.forEach((v, k) => {
      const h = Math.max(1, v * (gc.height - 4));
      gg.fillRect(k * w + 1, gc.height - 2 - h, w - 2, h);
    });
    const d = pts.length > 1 ? Math.hypot(...[0, 1, 2].map((i) => pts[pts.length - 1][i] - pts[0][i])) : 0;
    const secs = (pts.length - 1) * (plan.dt_s || 0);
    $('st-plan').textContent = `${pts.length} points · ${(d * 100).toFixed(1)} cm in ${secs.toFixed(1)} s · gripper ${
      plan.g[0].toFixed(2)} → ${plan.g[plan.g.length - 1].toFixed(2)}`;
    state.plansDrawn += 1;
  }

  function gateEvent(kind, reason) {
    state.gateEvent = { kind, reason: reason || '', at: performance.now() };
  }

  function render() {
    const c = $('clutch');
    c.classList.toggle('engaged', state.engaged);
    c.textContent = $('clutch-toggle').checked ? (state.engaged ? 'ENGAGED — tap to release' : 'TAP TO ENGAGE')
      : (state.engaged ? 'MOVING' : 'HOLD TO MOVE');
    c.disabled = !state.xrSession;
    $('gripper').classList.toggle('closed', state.gripperClosed);
    $('gripper').textContent = state.gripperClosed ? 'GRIPPER: CLOSED' : 'GRIPPER: OPEN';
    $('st-track').textContent = state.xrSession ? `${state.tracking} · ${state.xrFps.toFixed(0)} Hz` : state.tracking;
    if (state.rtts.length) {
      const min = Math.min(...state.rtts);
      const max = Math.max(...state.rtts);
      const avg = state.rtts.reduce((a, b) => a + b, 0) / state.rtts.length;
      setPill($('st-rtt'), `rtt ${min.toFixed(0)}/${avg.toFixed(0)}/${max.toFixed(0)} ms`,
        avg < 30 ? 'ok' : avg < 80 ? 'warn' : 'bad');
    }
  }

  // ---- camera preview -----------------------------------------------------------------------------------

  function setCameras(cameras) {
    state.cameras = cameras;
    const sel = $('preview-camera');
    sel.innerHTML = '';
    for (const c of cameras) {
      const o = document.createElement('option');
      o.value = c;
      o.textContent = c;
      sel.appendChild(o);
    }
    if (!cameras.includes(state.preview.camera)) state.preview.camera = cameras[0] || '';
    sel.value = state.preview.camera;
    $('preview-box').hidden = cameras.length === 0;
    // After a reconnect the gateway has forgotten the preview: ask again.
    if (state.preview.want && state.preview.camera) askPreview();
    else if (state.preview.want) previewOff('this server has no camera');
  }

  function askPreview() {
    const p = state.preview;
    p.since = performance.now();
    p.lastFrameAt = 0;
    p.frameTimes = [];
    send({ type: 'preview', camera: p.camera, max_fps: PREVIEW.maxFps, width: PREVIEW.width });
    renderPreview();
  }

  // Off, by the operator (reason empty) or by the page or gateway (reason shown).
  function previewOff(reason, tellGateway = true) {
    const p = state.preview;
    const was = p.want && tellGateway;
    p.want = false;
    p.offReason = reason || '';
    $('preview-on').checked = false;
    $('preview').hidden = true;
    if (was) send({ type: 'preview_off' });
    renderPreview();
  }

  function onPreviewFrame(data) {
    const p = state.preview;
    p.received += 1;
    // Tells the gateway the frame is off the link, so it may send the next one.
    send({ type: 'preview_ack' });
    if (!p.want) return;
    const now = performance.now();
    p.lastFrameAt = now;
    p.frameTimes.push(now);
    while (p.frameTimes.length && now - p.frameTimes[0] > 2000) p.frameTimes.shift();
    p.bytes = data.size;
    const img = $('preview');
    const old = p.url;
    p.url = URL.createObjectURL(new Blob([data], { type: 'image/jpeg' }));
    img.onload = () => {
      p.shown += 1;
      img.hidden = !p.want;
      if (old) URL.revokeObjectURL(old);
    };
    img.onerror = () => { if (old) URL.revokeObjectURL(old); };
    img.src = p.url;
    renderPreview();
  }

  function renderPreview() {
    const p = state.preview;
    const pill = $('st-preview');
    if (!p.want) {
      setPill(pill, p.offReason ? `preview off · ${p.offReason}` : 'preview off', p.offReason ? 'warn' : '');
      return;
    }
    if (!p.lastFrameAt) {
      setPill(pill, `${p.camera}: starting…`, 'warn');
      return;
    }
    const n = p.frameTimes.length;
    const fps = n > 1 ? ((n - 1) * 1000) / (p.frameTimes[n - 1] - p.frameTimes[0]) : 0;
    setPill(pill, `${p.camera} · ${fps.toFixed(1)} fps · ${(p.bytes / 1024).toFixed(0)} kB`, 'ok');
  }

  $('preview-on').addEventListener('change', (e) => {
    if (e.target.checked && state.preview.camera) {
      state.preview.want = true;
      state.preview.offReason = '';
      askPreview();
    } else {
      previewOff('');
    }
  });
  $('preview-camera').addEventListener('change', (e) => {
    state.preview.camera = e.target.value;
    localStorage.setItem('phone2act.camera', state.preview.camera);
    if (state.preview.want) askPreview();
  });
  setInterval(() => {
    if (!state.preview.want || !state.connected) return;
    const why = previewVerdict(performance.now(), state.preview.since, state.preview.lastFrameAt, state.rttLog);
    if (why) previewOff(why);
  }, 500);

  // ---- buttons ------------------------------------------------------------------------------------------

  // Button events go out at once in a pose-less sample; the gateway merges them into the next pose if needed.
  function buttons(list) {
    // The page's socket released its arm to the headset controllers: a sample here would claim one again.
    if (state.headsetActive) return;
    state.seq += 1;
    if (!send({ type: 'sample', seq: state.seq, t_ns: nowNs(), buttons: list })) {
      notice('Not connected to the gateway.');
    }
  }

  function bindHold(el, onDown, onUp) {
    el.addEventListener('pointerdown', (e) => { e.preventDefault(); el.setPointerCapture(e.pointerId); onDown(); });
    for (const ev of ['pointerup', 'pointercancel', 'lostpointercapture']) {
      el.addEventListener(ev, (e) => { e.preventDefault(); onUp(); });
    }
  }

  let holding = false;
  bindHold($('clutch'), () => {
    if ($('clutch-toggle').checked) {
      buttons([{ clutch: state.engaged ? 'disengage' : 'engage' }]);
      state.engaged = !state.engaged;
    } else {
      holding = true;
      buttons([{ clutch: 'engage' }]);
      state.engaged = true;
    }
    render();
  }, () => {
    if (holding) {
      holding = false;
      buttons([{ clutch: 'disengage' }]);
      state.engaged = false;
      render();
    }
  });
  $('clutch-toggle').addEventListener('change', () => {
    if (holding) { holding = false; buttons([{ clutch: 'disengage' }]); state.engaged = false; }
    render();
  });
  $('gripper').addEventListener('click', () => buttons([{ gripper: 'toggle' }]));
  $('rec-start').addEventListener('click', () => {
    const task = $('task').value.trim();
    if (!task) { notice('Type the task first (it is stored with every frame of the episode).'); $('task').focus(); return; }
    localStorage.setItem('phone2act.task', task);
    buttons([{ record: 'start', task }]);
  });
  $('rec-stop').addEventListener('click', () => buttons([{ record: 'stop' }]));
  // The last seconds the recorder kept while idle, saved as an episode of the task (LeRobot's `highlight`).
  $('rec-highlight').addEventListener('click', () => {
    const task = $('task').value.trim();
    if (!task) { notice('Type the task first (it is stored with every frame of the episode).'); $('task').focus(); return; }
    localStorage.setItem('phone2act.task', task);
    buttons([{ record: 'highlight', task }]);
  });
  // The operator's verdict, given as the episode is saved: kept in its provenance, and `next.success` of its
  // last frame in a dataset that records the column (docs/datasets.md).
  $('rec-success').addEventListener('click', () => buttons([{ record: 'stop', outcome: 'success' }]));
  $('rec-failure').addEventListener('click', () => buttons([{ record: 'stop', outcome: 'failure' }]));
  $('rec-discard').addEventListener('click', () => {
    if (confirm('Discard the episode in progress?')) buttons([{ record: 'discard' }]);
  });
  $('task').value = localStorage.getItem('phone2act.task') || '';
  $('arm').addEventListener('change', (e) => {
    state.arm = e.target.value;
    localStorage.setItem('phone2act.arm', state.arm);
    state.wasOpen = false;
    state.counters = null;
    hello(false);
  });
  $('take-over').addEventListener('click', () => hello(true));
  // One explicit gesture: the arm goes back to the waiting policy, which drives again only with a chunk that
  // answers a fresh observation (the arm holds until then).
  $('hand-back').addEventListener('click', () => {
    state.seq += 1;
    if (send({ type: 'hand_back', seq: state.seq })) buzz([30, 40, 30]);
  });
  state.send = send;
  state.hello = hello;

  // ---- WebXR ---------------------------------------------------------------------------------------------

  function appHint() {
    if (state.rosbridgePort === undefined) return 'the Phone2Act Android app (rosbridge; the gateway prints its port)';
    if (state.rosbridgePort === null) return 'the Phone2Act Android app (this gateway serves no rosbridge port)';
    return `the Phone2Act Android app (rosbridge, port ${state.rosbridgePort})`;
  }

  function renderNoXr() {
    if (!state.noXrReason) return;
    const el = $('no-xr');
    el.hidden = false;
    if (state.noXrReason === 'insecure') {
      el.textContent = 'This page must be opened over https:// (WebXR needs a secure context). Use the URL the '
        + 'gateway printed, or scan its QR code.';
    } else if (state.noXrReason === 'ios') {
      // No browser on iOS ships WebXR; a few App Store browser apps add immersive-ar on top of ARKit.
      el.textContent = 'This iPhone/iPad browser has no WebXR AR (Safari and the browsers built on it have none), '
        + 'so this page cannot read the phone\'s pose here. On this device: open this same URL in a WebXR browser '
        + 'app from the App Store (such as "XR Browser" or Mozilla\'s "WebXR Viewer"), where the page drives the arm '
        + 'as on Android; here, the buttons below still control recording. '
        + `Or use an Android phone with ARCore in Chrome, or ${appHint()}.`;
    } else if (state.noXrReason === 'vr-only') {
      el.textContent = 'This browser has WebXR VR but no AR, so the phone\'s own pose cannot drive an arm here. '
        + 'With tracked controllers (a VR headset), press "Start headset" to drive with them. '
        + `For a phone: Chrome on an ARCore Android phone, or ${appHint()}.`;
    } else {
      el.textContent = 'This browser has no WebXR AR (immersive-ar). Use Chrome on an ARCore-supported Android '
        + `phone with "Google Play Services for AR" installed, a WebXR browser app on an iPhone, or ${appHint()}. `
        + 'The buttons below still control recording.';
    }
  }

  // Decides by what WebXR offers, never by the user agent: wherever immersive-ar exists the phone path drives.
  // The user agent only picks the wording of the message for a device that has no immersive-ar.
  async function checkXr() {
    const isIos = /iPhone|iPad|iPod/.test(navigator.userAgent);
    const ask = async (mode) => {
      try { return await navigator.xr.isSessionSupported(mode); } catch (_) { return false; }
    };
    const secure = window.isSecureContext && !!navigator.xr;
    if (secure && await ask('immersive-ar')) return true;
    const vr = secure && await ask('immersive-vr');
    state.noXrReason = !window.isSecureContext ? 'insecure' : (vr ? 'vr-only' : (isIos ? 'ios' : 'no-ar'));
    renderNoXr();
    $('start-ar').disabled = true;
    return false;
  }

  function onXrFrame(time, frame) {
    const session = frame.session;
    session.requestAnimationFrame(onXrFrame);
    state.xrFrames += 1;
    const now = performance.now();
    if (now - state.xrFpsSince >= 1000) {
      state.xrFps = (state.xrFrames * 1000) / (now - state.xrFpsSince);
      state.xrFrames = 0;
      state.xrFpsSince = now;
      render();
    }
    const layer = session.renderState && session.renderState.baseLayer;
    if (layer && state.gl) {
      // Transparent clear: the camera image shows through in immersive-ar.
      state.gl.bindFramebuffer(state.gl.FRAMEBUFFER, layer.framebuffer);
      state.gl.clearColor(0, 0, 0, 0);
      state.gl.clear(state.gl.COLOR_BUFFER_BIT);
    }
    const pose = frame.getViewerPose(state.refSpace);
    state.seq += 1;
    if (!pose) {
      state.tracking = 'lost';
      send({ type: 'sample', seq: state.seq, t_ns: nowNs(), tracking: 'lost' });
      return;
    }
    const p = pose.transform.position;
    const q = pose.transform.orientation;
    state.tracking = pose.emulatedPosition ? 'limited' : 'tracking';
    send({
      type: 'sample',
      seq: state.seq,
      t_ns: nowNs(),
      tracking: state.tracking,
      pose: { p: [p.x, p.y, p.z], q: [q.x, q.y, q.z, q.w] },
    });
  }

  async function startAr() {
    if (state.xrSession || state.headsetActive) return;
    try {
      const session = await navigator.xr.requestSession('immersive-ar', {
        requiredFeatures: ['local'],
        optionalFeatures: ['dom-overlay'],
        domOverlay: { root: $('overlay') },
      });
      state.xrSession = session;
      document.body.classList.add('in-ar');
      try {
        const canvas = document.createElement('canvas');
        const gl = canvas.getContext('webgl', { xrCompatible: true, alpha: true });
        if (gl && window.XRWebGLLayer) {
          state.gl = gl;
          session.updateRenderState({ baseLayer: new XRWebGLLayer(session, gl) });
        }
      } catch (e) {
        // Chrome delivers frames only with a base layer; without WebGL it may still work on some builds.
        console.warn('no WebGL layer', e);
      }
      state.refSpace = await session.requestReferenceSpace('local');
      session.addEventListener('end', () => {
        state.xrSession = null;
        state.tracking = 'AR ended';
        document.body.classList.remove('in-ar');
        // Never leave the arm engaged without a pose stream.
        buttons([{ clutch: 'disengage' }]);
        state.engaged = false;
        $('start-ar').hidden = false;
        render();
      });
      $('start-ar').hidden = true;
      session.requestAnimationFrame(onXrFrame);
      render();
    } catch (e) {
      notice(`Could not start AR: ${e.message || e}`);
    }
  }
  $('start-ar').addEventListener('click', startAr);

  document.addEventListener('visibilitychange', () => {
    if (document.hidden && state.engaged) {
      buttons([{ clutch: 'disengage' }]);
      state.engaged = false;
    }
  });

  checkXr();
  if (!token) notice('No pairing token in the URL: open the URL the gateway printed, or scan its QR code.');
  connect();
  render();
})();

// phone2act headset controllers: on a WebXR device with tracked controllers (a Quest or Pico in its browser),
// each controller's grip pose drives an arm, through the same gateway socket protocol as the phone (one socket
// per controller, so each arm has its own stream through the same planner, gate, arbiter and pairing).
//   grip (squeeze) held = clutch engaged; trigger = gripper position, 0 open .. 1 closed (analog);
//   lower face button (A / X) = start recording, or save while recording;
//   upper face button (B / Y) held for 1 s while recording = discard.
// Which controller drives which arm comes from the gateway's `welcome` (`[gateway.controllers]`).
// The live video (video.js, started with the session where the gateway offers it) hangs in the scene above eye
// level and ahead, so that the controllers held in front of the chest stay in view: where the browser has the
// WebXR layers API's media binding (Quest Browser) as a media quad layer, which the headset's compositor draws
// from the video itself; elsewhere as a WebGL panel, the video uploaded as a texture once per new frame. Where
// WebRTC cannot connect, the JPEG preview the page falls back to is drawn on the WebGL panel instead. A
// thumbstick press hides or shows the video.
// Loaded after app.js; uses its state (window.phone2act) for the token, the arm list and the task field.
'use strict';

(() => {
  const app = window.phone2act;
  const $ = (id) => document.getElementById(id);
  // xr-standard gamepad mapping (WebXR Gamepads Module): the indices every tracked controller shares.
  const BUTTON = { trigger: 0, squeeze: 1, thumbstick: 3, lower: 4, upper: 5 };
  const DISCARD_HOLD_MS = 1000;
  // A hello refused because our own released stream still holds the arm is retried this many times, 300 ms
  // apart; any other holder keeps its arm.
  const CLAIM_RETRIES = 10;

  const hs = {
    supported: { vr: false, ar: false },
    session: null,
    mode: null,
    refSpace: null,
    gl: null,
    hands: {}, // handedness -> Hand
    frames: 0,
  };
  app.headset = hs;

  // ---- the live video on a panel in the scene ------------------------------------------------------------

  // Where the panel hangs in the session's 'local' space (origin: the head at the session's start, -Z ahead):
  // 1.6 m ahead, its centre 0.35 m above the eyes, 1.2 m wide. Hands work below eye level, so the panel
  // leaves them in view; looking up a little shows the robot.
  const PANEL = { aheadM: 1.6, upM: 0.35, widthM: 1.2 };
  // Without a frame callback from the page (a headset browser may not composite the page while immersive), a
  // new texture is uploaded at most this often.
  const UPLOAD_EVERY_MS = 33;
  const pv = {
    shown: true, // the operator's choice (thumbstick press)
    mode: null, // 'layer' (a media quad layer) or 'panel' (WebGL), once the session chose
    layer: null, // the media quad layer, where there is one
    layerFrames: 0, // XR frames with the media layer in the session's layers
    uploads: 0, // texture uploads (one per video frame shown)
    previewUploads: 0, // uploads of the JPEG preview's image, where the page fell back to it
    previewLoads: 0,
    lastPreviewLoads: 0,
    drawn: 0, // XR frames with the panel drawn
    glErrors: 0, // error checks that found WebGL refusing a panel draw
    glChecks: 0,
    g2g: [], // glass to glass at upload: capture on the gateway's clock to the panel's frame, ms
    startedVideo: false,
    lastFrames: -1,
    lastDecoded: -1,
    lastUploadMs: 0,
    texW: 0,
    texH: 0,
    checkGl: false, // the next draw asks WebGL for errors (a round trip to the GPU process: not every frame)
    gl: null,
    prog: null,
    buf: null,
    tex: null,
    loc: null,
  };
  hs.video = pv;

  $('preview').addEventListener('load', () => { pv.previewLoads += 1; });

  function panelSetup(gl) {
    const shader = (type, src) => {
      const sh = gl.createShader(type);
      gl.shaderSource(sh, src);
      gl.compileShader(sh);
      if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(sh));
      return sh;
    };
    const prog = gl.createProgram();
    gl.attachShader(prog, shader(gl.VERTEX_SHADER, `
      attribute vec2 a;
      uniform mat4 proj, view, model;
      varying vec2 uv;
      void main() { uv = vec2(a.x * 0.5 + 0.5, 0.5 - a.y * 0.5); gl_Position = proj * view * model * vec4(a, 0.0, 1.0); }`));
    gl.attachShader(prog, shader(gl.FRAGMENT_SHADER, `
      precision mediump float;
      uniform sampler2D tex;
      varying vec2 uv;
      void main() { gl_FragColor = texture2D(tex, uv); }`));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
    pv.buf = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, pv.buf);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
    pv.tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, pv.tex);
    // A camera's size is rarely a power of two: WebGL 1 then needs clamping and no mipmaps.
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    pv.loc = {
      a: gl.getAttribLocation(prog, 'a'),
      proj: gl.getUniformLocation(prog, 'proj'),
      view: gl.getUniformLocation(prog, 'view'),
      model: gl.getUniformLocation(prog, 'model'),
    };
    pv.prog = prog;
    pv.gl = gl;
    pv.texW = 0;
    pv.texH = 0;
  }

  // Whether the video element shows a frame not yet uploaded. The page's frame callback counts the frames it
  // shows; where no callback comes (a headset browser may not composite the page while immersive), the
  // element's count of decoded frames tells, checked at most every UPLOAD_EVERY_MS.
  function newVideoFrame(video, v, now) {
    if (v.frames !== pv.lastFrames) return 'shown';
    if (now - v.lastFrameAt <= 500 || now - pv.lastUploadMs < UPLOAD_EVERY_MS) return null;
    const q = video.getVideoPlaybackQuality ? video.getVideoPlaybackQuality() : null;
    const decoded = q ? q.totalVideoFrames : -1;
    // Without a count, the picture is taken as new at most every UPLOAD_EVERY_MS.
    if (decoded === -1 || decoded !== pv.lastDecoded) {
      pv.lastDecoded = decoded;
      return 'decoded';
    }
    return null;
  }

  // Uploads `el` into the panel's texture (RGBA): storage is allocated at a new size only, otherwise
  // overwritten.
  function upload(gl, el, width, height) {
    if (width !== pv.texW || height !== pv.texH) {
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA, gl.RGBA, gl.UNSIGNED_BYTE, el);
      pv.texW = width;
      pv.texH = height;
      pv.checkGl = true;
    } else {
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, gl.RGBA, gl.UNSIGNED_BYTE, el);
    }
  }

  // Draws the live video's newest frame on the panel, in every view of this XR frame. Nothing here waits for the
  // GPU: WebGL's commands are queued, and an error check (a synchronous round trip to the GPU process, which
  // holds the page's thread, and the controllers' feedback behind it, while it waits) is made only on the
  // first draw after the texture's storage changed.
  function drawVideo(frame, layer) {
    const gl = hs.gl;
    const v = app.video;
    const video = $('video');
    const img = $('preview');
    // The live video; where WebRTC could not connect (the page fell back), the JPEG preview's image.
    let el = null;
    if (v && v.pc && video && video.readyState >= 2 && video.videoWidth) el = video;
    else if (app.preview && app.preview.want && img && img.complete && img.naturalWidth) el = img;
    if (!gl || !el || !pv.shown) return;
    if (pv.gl !== gl) {
      try {
        panelSetup(gl);
      } catch (e) {
        console.warn('no video panel', e);
        hs.gl = null;
        return;
      }
    }
    gl.bindTexture(gl.TEXTURE_2D, pv.tex);
    const now = performance.now();
    if (el === img) {
      if (pv.previewLoads !== pv.lastPreviewLoads) {
        upload(gl, img, img.naturalWidth, img.naturalHeight);
        pv.previewUploads += 1;
        pv.lastPreviewLoads = pv.previewLoads;
      }
    } else {
      const fresh = newVideoFrame(video, v, now);
      if (fresh) {
        upload(gl, video, video.videoWidth, video.videoHeight);
        pv.uploads += 1;
        pv.lastUploadMs = now;
        // Glass to glass of a frame the page showed (its capture time is known), on the panel from this frame.
        if (fresh === 'shown' && v.lastCaptureMs !== null && v.offsetMs !== null) {
          pv.g2g.push(v.pageUnixMs() + v.offsetMs - v.lastCaptureMs);
          if (pv.g2g.length > 300) pv.g2g.shift();
        }
        pv.lastFrames = v.frames;
      }
    }
    const pose = frame.getViewerPose(hs.refSpace);
    if (!pose) return;
    const halfW = PANEL.widthM / 2;
    const halfH = el === video ? (halfW * video.videoHeight) / video.videoWidth : (halfW * img.naturalHeight) / img.naturalWidth;
    // Column-major: scale the unit quad to the panel, then move it ahead and up.
    const model = new Float32Array([halfW, 0, 0, 0, 0, halfH, 0, 0, 0, 0, 1, 0, 0, PANEL.upM, -PANEL.aheadM, 1]);
    gl.useProgram(pv.prog);
    gl.bindBuffer(gl.ARRAY_BUFFER, pv.buf);
    gl.enableVertexAttribArray(pv.loc.a);
    gl.vertexAttribPointer(pv.loc.a, 2, gl.FLOAT, false, 0, 0);
    gl.uniformMatrix4fv(pv.loc.model, false, model);
    for (const view of pose.views) {
      const vp = layer.getViewport(view);
      if (!vp) continue;
      gl.viewport(vp.x, vp.y, vp.width, vp.height);
      gl.uniformMatrix4fv(pv.loc.proj, false, view.projectionMatrix);
      gl.uniformMatrix4fv(pv.loc.view, false, view.transform.inverse.matrix);
      gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
    }
    if (pv.checkGl) {
      pv.checkGl = false;
      pv.glChecks += 1;
      if (gl.getError() !== gl.NO_ERROR) pv.glErrors += 1;
    }
    pv.drawn += 1;
  }

  // ---- the live video as a media quad layer (WebXR layers API), where the browser has one -----------------

  // The browser offers media layers: XRMediaBinding, and a session render state with a `layers` list (a
  // session without the layers feature refuses to create one, and the panel takes over then).
  function mediaLayersOffered(session) {
    return typeof window.XRMediaBinding === 'function' && !!session.renderState
      && Array.isArray(session.renderState.layers);
  }

  // A WebGL context and layer for the panel (the JPEG preview; the live video too where there are no media
  // layers).
  function glLayer(session) {
    if (!hs.glLayer) {
      const gl = document.createElement('canvas').getContext('webgl', { xrCompatible: true, alpha: true });
      if (!gl || !window.XRWebGLLayer) return null;
      hs.gl = gl;
      hs.glLayer = new XRWebGLLayer(session, gl);
    }
    return hs.glLayer;
  }

  // In a session with media layers, what the operator sees: the live video as a media quad layer once it has a
  // picture (its size gives the quad's height), the JPEG preview on the WebGL panel where the page fell back to
  // it, or nothing (a cleared WebGL layer) while the operator hid the video. The headset's compositor draws the
  // media layer from the video itself: the page uploads and draws nothing for it.
  function updateLayers(session) {
    const v = app.video;
    const video = $('video');
    const img = $('preview');
    let want = 'none';
    if (pv.shown && v && v.pc && video && video.videoWidth > 0) want = 'video';
    else if (pv.shown && app.preview && app.preview.want && img && img.complete && img.naturalWidth) want = 'preview';
    if (want !== pv.showing) {
      if (want === 'video') {
        try {
          pv.layer = new XRMediaBinding(session).createQuadLayer(video, {
            space: hs.refSpace,
            layout: 'mono',
            transform: new XRRigidTransform({ x: 0, y: PANEL.upM, z: -PANEL.aheadM }),
            width: PANEL.widthM,
            height: (PANEL.widthM * video.videoHeight) / video.videoWidth,
          });
        } catch (e) {
          // Not granted after all: the WebGL panel on the WebGL layer the session already shows, as in a
          // browser without layers.
          console.warn('no media layer, the video goes on a WebGL panel', e);
          pv.mode = 'panel';
          pv.layer = null;
          return;
        }
        session.updateRenderState({ layers: [pv.layer] });
      } else {
        // The WebGL layer (cleared, or the preview on the panel): a session with no layer gets no frames, and
        // the controllers' samples go out in the frames.
        pv.layer = null;
        session.updateRenderState({ layers: hs.glLayer ? [hs.glLayer] : [] });
      }
      pv.showing = want;
    }
    if (pv.layer) pv.layerFrames += 1;
  }

  // Controller -> arm: the gateway's map when it has one, else each controller drives the arm of its own name
  // and, when no arm is named left or right, the right controller drives the arm picked on the page.
  function controllerArms(controllers, arms, pickedArm) {
    const map = {};
    const configured = Object.entries(controllers || {}).filter(([hand]) => hand === 'left' || hand === 'right');
    if (configured.length) {
      for (const [hand, arm] of configured) map[hand] = arm;
      return map;
    }
    for (const hand of ['left', 'right']) if ((arms || []).includes(hand)) map[hand] = hand;
    if (!Object.keys(map).length && pickedArm) map.right = pickedArm;
    return map;
  }
  hs.controllerArms = controllerArms;

  function nowNs() {
    return Math.round(performance.now() * 1e6);
  }

  function pulse(source, intensity, ms) {
    const h = source && source.gamepad && source.gamepad.hapticActuators && source.gamepad.hapticActuators[0];
    if (h && h.pulse) h.pulse(intensity, ms).catch(() => { /* haptics are best effort */ });
  }

  // One controller: its own socket to the gateway, claimed for its arm.
  class Hand {
    constructor(handedness, arm) {
      this.handedness = handedness;
      this.arm = arm;
      this.seq = 0;
      this.ws = null;
      this.open = false;
      this.state = 'connecting';
      this.engaged = false;
      this.gripperSent = null; // the trigger value last sent; null until the first frame sees the trigger
      this.lower = false;
      this.stick = false;
      this.upperSince = 0;
      this.discardSent = false;
      this.recPhase = null;
      this.feedbackCount = 0;
      this.last = null;
      this.rtts = [];
      this.rttLog = []; // [performance.now(), round trip ms] of the last 1000 feedback messages (for tests)
      this.claims = 0;
      this.tracking = 'not seen';
      this.closed = false;
      this.connect();
    }

    connect() {
      const ws = new WebSocket(`wss://${location.host}/ws?token=${encodeURIComponent(app.token)}`);
      this.ws = ws;
      ws.onmessage = (ev) => {
        if (typeof ev.data !== 'string') return;
        let msg;
        try { msg = JSON.parse(ev.data); } catch (_) { return; }
        this.onMessage(msg);
      };
      ws.onclose = () => {
        this.open = false;
        if (!this.closed) {
          this.state = 'reconnecting';
          setTimeout(() => { if (!this.closed) this.connect(); }, 1000);
        }
        render();
      };
    }

    send(obj) {
      if (this.ws && this.ws.readyState === WebSocket.OPEN) {
        this.ws.send(JSON.stringify(obj));
        return true;
      }
      return false;
    }

    onMessage(msg) {
      if (msg.type === 'welcome') {
        this.send({ type: 'hello', arm: this.arm, take_over: false });
      } else if (msg.type === 'session') {
        if (msg.state === 'open') {
          this.open = true;
          this.state = `driving ${msg.arm}`;
        } else if (msg.state === 'refused') {
          this.open = false;
          if (msg.code === 'AlreadyExists' && this.claims < CLAIM_RETRIES) {
            this.claims += 1;
            setTimeout(() => this.send({ type: 'hello', arm: this.arm, take_over: false }), 300);
          } else {
            this.state = `arm ${msg.arm} refused: ${msg.message}`;
          }
        } else {
          this.open = false;
          this.state = msg.state;
        }
        render();
      } else if (msg.type === 'feedback') {
        this.last = msg;
        this.feedbackCount += 1;
        if (msg.t_ns > 0) {
          const rtt = performance.now() - msg.t_ns / 1e6;
          if (rtt >= 0 && rtt < 10000) {
            this.rtts.push(rtt);
            if (this.rtts.length > 100) this.rtts.shift();
            this.rttLog.push([performance.now(), rtt]);
            if (this.rttLog.length > 1000) this.rttLog.shift();
          }
        }
        if (msg.recording) this.recPhase = msg.recording.phase;
      } else if (msg.type === 'error') {
        this.state = `error: ${msg.message}`;
        render();
      }
    }

    // One XR frame with this controller present.
    frame(frame, source) {
      const pad = source.gamepad;
      const buttons = [];
      const b = (i) => (pad && pad.buttons[i]) || { pressed: false, value: 0 };
      const trigger = Math.min(1, Math.max(0, b(BUTTON.trigger).value));
      // A thumbstick press hides the video (an unobstructed view of the robot) or shows it again.
      const stick = b(BUTTON.thumbstick).pressed;
      if (stick && !this.stick) pv.shown = !pv.shown;
      this.stick = stick;
      // Nothing goes out before the arm is claimed: the gateway would give a pose-less socket the default arm.
      if (!this.open) {
        if (this.gripperSent === null) this.gripperSent = trigger;
        return;
      }
      const squeeze = b(BUTTON.squeeze).pressed;
      if (squeeze !== this.engaged) {
        buttons.push({ clutch: squeeze ? 'engage' : 'disengage' });
        this.engaged = squeeze;
        pulse(source, 0.3, 30);
      }
      // The trigger sets the gripper only once it moves: entering the headset must not move the gripper.
      if (this.gripperSent === null) {
        this.gripperSent = trigger;
      } else if (Math.abs(trigger - this.gripperSent) >= 0.01 || (trigger !== this.gripperSent && (trigger === 0 || trigger === 1))) {
        buttons.push({ gripper: Math.round(trigger * 1000) / 1000 });
        this.gripperSent = trigger;
      }
      const recording = this.recPhase === 'recording' || this.recPhase === 'paused';
      const lower = b(BUTTON.lower).pressed;
      if (lower && !this.lower) {
        if (recording) {
          buttons.push({ record: 'stop' });
        } else {
          const task = ($('task') && $('task').value.trim()) || '';
          if (task) {
            buttons.push({ record: 'start', task });
          } else {
            // No keyboard in the headset: the task is typed on the page before entering.
            pulse(source, 1.0, 300);
            hs.notice = 'Type the task on the page before entering the headset; recording needs it.';
          }
        }
      }
      this.lower = lower;
      const upper = b(BUTTON.upper).pressed;
      const now = performance.now();
      if (upper && !this.upperSince) this.upperSince = now;
      if (!upper) { this.upperSince = 0; this.discardSent = false; }
      if (upper && recording && !this.discardSent && now - this.upperSince >= DISCARD_HOLD_MS) {
        buttons.push({ record: 'discard' });
        this.discardSent = true;
        pulse(source, 1.0, 150);
      }

      this.seq += 1;
      const pose = frame.getPose(source.gripSpace, hs.refSpace);
      if (!pose) {
        this.tracking = 'lost';
        this.send({ type: 'sample', seq: this.seq, t_ns: nowNs(), tracking: 'lost', buttons });
        return;
      }
      const p = pose.transform.position;
      const q = pose.transform.orientation;
      this.tracking = pose.emulatedPosition ? 'limited' : 'tracking';
      this.send({
        type: 'sample',
        seq: this.seq,
        t_ns: nowNs(),
        tracking: this.tracking,
        pose: { p: [p.x, p.y, p.z], q: [q.x, q.y, q.z, q.w] },
        buttons,
      });
    }

    // The controller is gone (switched off, out of view of the headset, put down for hand tracking): the arm
    // holds.
    missing() {
      if (!this.open) return;
      this.seq += 1;
      const buttons = this.engaged ? [{ clutch: 'disengage' }] : [];
      this.engaged = false;
      this.tracking = 'not seen';
      this.send({ type: 'sample', seq: this.seq, t_ns: nowNs(), tracking: 'lost', buttons });
    }

    close() {
      this.closed = true;
      if (this.engaged && this.open) {
        this.send({ type: 'sample', seq: ++this.seq, t_ns: nowNs(), buttons: [{ clutch: 'disengage' }] });
      }
      this.engaged = false;
      if (this.ws) this.ws.close();
    }
  }
  hs.Hand = Hand;

  function render() {
    const box = $('headset-status');
    if (!box) return;
    const hands = Object.values(hs.hands);
    box.hidden = !hs.session && !hands.length;
    box.textContent = '';
    for (const h of hands) {
      const div = document.createElement('div');
      const rtt = h.rtts.length ? ` · rtt ${(h.rtts.reduce((a, c) => a + c, 0) / h.rtts.length).toFixed(0)} ms` : '';
      div.textContent = `${h.handedness} controller → ${h.arm}: ${h.state} · ${h.tracking}`
        + `${h.engaged ? ' · ENGAGED' : ''}${rtt}`;
      box.appendChild(div);
    }
    if (hs.notice) {
      const div = document.createElement('div');
      div.textContent = hs.notice;
      box.appendChild(div);
    }
  }

  function onFrame(time, frame) {
    const session = frame.session;
    session.requestAnimationFrame(onFrame);
    hs.frames += 1;
    const seen = new Set();
    for (const source of session.inputSources) {
      // Tracked controllers only: a hand-tracking source has no gamepad buttons for the clutch.
      const hand = hs.hands[source.handedness];
      if (!hand || !source.gripSpace || !source.gamepad || seen.has(source.handedness)) continue;
      seen.add(source.handedness);
      hand.frame(frame, source);
    }
    for (const [handedness, hand] of Object.entries(hs.hands)) {
      if (!seen.has(handedness)) hand.missing();
    }
    // Drawn after the samples went out: a slow texture upload never holds a pose back.
    if (pv.mode === 'layer') updateLayers(session);
    const layer = pv.mode === 'layer' && pv.showing === 'video' ? null : hs.glLayer;
    if (layer && hs.gl) {
      // Transparent clear: in immersive-ar the passthrough shows through.
      hs.gl.bindFramebuffer(hs.gl.FRAMEBUFFER, layer.framebuffer);
      hs.gl.clearColor(0, 0, 0, 0);
      hs.gl.clear(hs.gl.COLOR_BUFFER_BIT);
      drawVideo(frame, layer);
    }
    if (hs.frames % 30 === 0) render();
  }

  async function start() {
    if (hs.session || app.xrSession) return;
    const welcome = app.welcome || {};
    const map = controllerArms(welcome.controllers, app.arms, app.arm);
    if (!Object.keys(map).length) {
      hs.notice = 'No arm to drive: the gateway listed none.';
      render();
      return;
    }
    // The passthrough mode where there is one, so the operator sees the robot.
    const mode = hs.supported.ar ? 'immersive-ar' : 'immersive-vr';
    let session;
    try {
      // The layers feature where the browser has media layers: the video then goes to the compositor as is.
      const optionalFeatures = typeof window.XRMediaBinding === 'function' ? ['layers'] : [];
      session = await navigator.xr.requestSession(mode, { requiredFeatures: ['local'], optionalFeatures });
    } catch (e) {
      hs.notice = `Could not start the headset session: ${e.message || e}`;
      render();
      return;
    }
    hs.session = session;
    hs.mode = mode;
    hs.notice = '';
    hs.gl = null;
    hs.glLayer = null;
    pv.layer = null;
    pv.showing = null;
    pv.mode = mediaLayersOffered(session) ? 'layer' : 'panel';
    try {
      const layer = glLayer(session);
      if (layer && pv.mode === 'layer') {
        try {
          session.updateRenderState({ layers: [layer] });
          pv.showing = 'none';
        } catch (e) {
          // A session without the layers feature refuses a layers list: the panel as a base layer.
          pv.mode = 'panel';
        }
      }
      if (layer && pv.mode === 'panel') session.updateRenderState({ baseLayer: layer });
    } catch (e) {
      console.warn('no WebGL layer', e);
    }
    hs.refSpace = await session.requestReferenceSpace('local');
    // The page's own socket lets go of its arm; the controllers' sockets claim theirs.
    app.headsetActive = true;
    app.send({ type: 'release' });
    for (const [handedness, arm] of Object.entries(map)) hs.hands[handedness] = new Hand(handedness, arm);
    session.addEventListener('end', stop);
    // The operator cannot reach the page's switch in the headset: the video starts with the session (and
    // stops with it if it started here).
    const video = app.video;
    pv.startedVideo = false;
    if (video && !video.want && video.available()) {
      video.start();
      pv.startedVideo = true;
    }
    $('start-headset').hidden = true;
    session.requestAnimationFrame(onFrame);
    render();
  }

  function stop() {
    const hands = Object.values(hs.hands);
    hs.hands = {};
    hs.session = null;
    if (pv.startedVideo && app.video && app.video.want) app.video.stop();
    pv.startedVideo = false;
    let left = hands.length;
    const back = () => {
      // The page's socket takes its arm back once the controllers' sockets are gone.
      app.headsetActive = false;
      hs.reclaims = CLAIM_RETRIES;
      app.hello(false);
    };
    for (const h of hands) {
      h.ws.addEventListener('close', () => { left -= 1; if (!left) back(); });
      h.close();
    }
    if (!hands.length) back();
    $('start-headset').hidden = false;
    render();
  }
  hs.stop = () => { if (hs.session) hs.session.end(); };

  async function detect() {
    if (!window.isSecureContext || !navigator.xr) return;
    const ask = async (mode) => {
      try { return await navigator.xr.isSessionSupported(mode); } catch (_) { return false; }
    };
    [hs.supported.vr, hs.supported.ar] = await Promise.all([ask('immersive-vr'), ask('immersive-ar')]);
    // Every immersive mode may have controllers; a phone's immersive-ar has none and its session shows so.
    $('start-headset').hidden = !(hs.supported.vr || hs.supported.ar);
    hs.detected = true;
  }

  // The server learns that a controller's stream ended on its own time: the page's claim of the arm right after
  // the session may be refused as still held, and is retried like a controller's.
  hs.reclaims = 0;
  app.listeners.push((msg) => {
    if (msg.type !== 'session') return;
    if (msg.state === 'refused' && msg.code === 'AlreadyExists' && hs.reclaims > 0 && !app.headsetActive) {
      hs.reclaims -= 1;
      setTimeout(() => app.hello(false), 300);
    } else if (msg.state === 'open') {
      hs.reclaims = 0;
    }
  });

  $('start-headset').addEventListener('click', start);
  document.addEventListener('visibilitychange', () => {
    if (!document.hidden) return;
    for (const h of Object.values(hs.hands)) {
      if (h.engaged && h.open) {
        h.send({ type: 'sample', seq: ++h.seq, t_ns: nowNs(), buttons: [{ clutch: 'disengage' }] });
        h.engaged = false;
      }
    }
  });
  detect();
})();

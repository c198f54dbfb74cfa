// Live video against control, in headless Chromium (Debian's) over loopback, against the real server and gateway:
//  - the control round trip (pose sample -> feedback) with video on and off, in alternating windows of one run,
//    optionally with CPU hogs beside it (VIDEO_CPU_HOGS=N busy threads), printed as p50 / p95 for each;
//  - a page on the gateway's own machine gets the ceiling bitrate (no congestion control to misread CPU load);
//  - glass to glass of the WebRTC video and of the JPEG preview, one after the other in one run;
//  - a throttled link: a relay in this process carries both the page's socket (TCP) and the video (UDP) through
//    one bandwidth-limited queue towards the page, like a slow Wi-Fi hop; the gateway's video bitrate must come
//    down under the link's rate and the control round trip must not stall behind the video. The relay talks to
//    the gateway from 127.0.0.2, so that the gateway takes the page for another machine;
//  - a gateway stalled for want of CPU (stopped and resumed by the test) keeps a remote page's bitrate up.
// Prints "video: N passed, M failed".
import { createServer, connect } from 'node:net';
import { createSocket } from 'node:dgram';
import { join } from 'node:path';
import { Worker } from 'node:worker_threads';
import {
  BASE, HTTPS_PORT, PAIRING_TOKEN, assert, check as harnessCheck, finish, here, launch, sleep, waitPage,
} from './harness.mjs';

// VIDEO_ONLY=text runs only the checks whose name contains it (repeated measurements of one check).
const check = (name, fn) => (!process.env.VIDEO_ONLY || name.includes(process.env.VIDEO_ONLY) ? harnessCheck(name, fn) : null);

const browser = await launch();

async function phonePage(base = BASE) {
  const context = await browser.newContext({ ignoreHTTPSErrors: true, viewport: { width: 412, height: 915 } });
  await context.addInitScript({ path: join(here, 'webxr-shim.js') });
  const page = await context.newPage();
  page.on('dialog', (d) => d.accept());
  page.on('pageerror', (e) => console.log(`page error: ${e.message}`));
  await page.goto(`${base}/?token=${encodeURIComponent(PAIRING_TOKEN)}`);
  await waitPage(page, () => window.phone2act && window.phone2act.sessionOpen, 'session open');
  return { context, page };
}

const q = (xs, f) => { const s = xs.slice().sort((a, b) => a - b); return s[Math.min(s.length - 1, Math.floor(f * s.length))]; };
const fmt = (xs) => `p50 ${q(xs, 0.5).toFixed(1)} ms, p95 ${q(xs, 0.95).toFixed(1)} ms (${xs.length})`;
// Round trips of feedback that arrived after `sinceMs` (page clock).
const rttsSince = (page, sinceMs) => page.evaluate((t) => window.phone2act.rttLog.filter(([at]) => at > t).map(([, ms]) => ms), sinceMs);
const pageNow = (page) => page.evaluate(() => performance.now());
const videoFrames = (page) => page.evaluate(() => window.phone2act.video.frames);
// The page's receive statistics of the video (Chromium's inbound-rtp): NACKs and PLIs it sent, keyframes decoded.
const inboundStats = (page) => page.evaluate(async () => {
  const { pc } = window.phone2act.video;
  if (!pc) return {};
  let found = {};
  (await pc.getStats()).forEach((r) => { if (r.type === 'inbound-rtp' && r.kind === 'video') found = r; });
  return {
    nack: found.nackCount || 0, pli: found.pliCount || 0, keyframes: found.keyFramesDecoded || 0,
    rtxBytes: found.retransmittedBytesReceived || 0, lost: found.packetsLost || 0,
  };
});
// kbit/s of each kind of traffic the link carried towards the page between two snapshots of `link.byKind`.
const KINDS = ['video', 'rtx', 'padding', 'rtcp', 'dtls', 'stun', 'other', 'control'];
function kindKbps(from, to, ms) {
  const out = {};
  for (const k of KINDS) out[k] = (((to[k] || 0) - (from[k] || 0)) * 8) / ms;
  return out;
}
const fmtKinds = (kb) => KINDS.filter((k) => kb[k] >= 0.5).map((k) => `${k} ${kb[k].toFixed(0)}`).join(', ');

// Busy threads beside the test (VIDEO_CPU_HOGS=2 loads both cores of the test machine).
function cpuHogs(n) {
  const workers = [];
  for (let i = 0; i < n; i += 1) workers.push(new Worker('for (;;) {}', { eval: true }));
  return { stop: () => Promise.all(workers.map((w) => w.terminate())) };
}

await check('control round trip with video on and off, alternating windows of one run', async () => {
  const { context, page } = await phonePage();
  const hogs = cpuHogs(Number(process.env.VIDEO_CPU_HOGS || 0));
  try {
    await page.click('#start-ar');
    await waitPage(page, () => window.phone2act.feedbackCount > 20, 'feedback');
    const on = []; const off = []; const g2g = []; let frames = 0; let onMs = 0; const rates = [];
    // Three rounds of 3 s off, 3 s on: alternating spreads the other load on the shared machine over both.
    for (let round = 0; round < 3; round += 1) {
      let t = await pageNow(page);
      await sleep(3000);
      off.push(...await rttsSince(page, t));
      await page.check('#video-on');
      // The first frame can take seconds on a loaded machine (ICE, DTLS, a keyframe); the window starts there.
      await waitPage(page, () => window.phone2act.video.frames >= 1, 'a decoded frame', 20000);
      const f0 = await videoFrames(page);
      const g0 = await page.evaluate(() => window.phone2act.video.g2gAll.length);
      t = await pageNow(page);
      await sleep(3000);
      on.push(...await rttsSince(page, t));
      frames += (await videoFrames(page)) - f0;
      g2g.push(...await page.evaluate((n) => window.phone2act.video.g2gAll.slice(n), g0));
      rates.push(...await page.evaluate((since) => window.phone2act.video.notes.filter(([at]) => at > since).map(([, b, e]) => [b, e]), t));
      onMs += (await pageNow(page)) - t;
      await page.uncheck('#video-on');
    }
    console.log(`  control round trip, video off: ${fmt(off)}`);
    console.log(`  control round trip, video on:  ${fmt(on)}; video ${(frames * 1000 / onMs).toFixed(1)} fps decoded`
      + `${process.env.VIDEO_CPU_HOGS ? `; ${process.env.VIDEO_CPU_HOGS} busy threads beside` : ''}`);
    if (g2g.length) console.log(`  glass to glass: ${fmt(g2g)}`);
    if (rates.length) {
      const b = rates.map(([x]) => x / 1e3); const e = rates.filter(([, x]) => x).map(([, x]) => x / 1e3);
      console.log(`  encoder bitrate ${Math.min(...b).toFixed(0)}-${Math.max(...b).toFixed(0)} kbit/s`
        + (e.length ? `, link estimate ${Math.min(...e).toFixed(0)}-${Math.max(...e).toFixed(0)} kbit/s` : ''));
    }
    // The page is on the gateway's machine: no congestion control, the bitrate stays at the ceiling (1.5 Mbit/s)
    // however loaded the machine is.
    assert(rates.length && rates.every(([b, e]) => b === 1500000 && e === null),
      `the bitrate left the ceiling on this machine: ${JSON.stringify(rates.slice(0, 5))}`);
    // The page streams at 60 Hz: 9 s of each give 540 round trips on an idle machine; 50 is "control kept going".
    assert(on.length >= 50 && off.length >= 50, `too few round trips: ${on.length} on, ${off.length} off`);
    // Not a latency bound (the machine is shared and its load varies between windows): a stall of control
    // behind video would show as seconds.
    assert(q(on, 0.95) < 2000, `control round trip p95 ${q(on, 0.95).toFixed(0)} ms with video on`);
  } finally {
    await hogs.stop();
    await context.close();
  }
});

await check('glass to glass of the WebRTC video and of the JPEG preview, one run', async () => {
  const { context, page } = await phonePage();
  try {
    await page.check('#video-on');
    // Up to 20 s for the first frames: ICE, DTLS and a keyframe on a machine with a load average near 18.
    await waitPage(page, () => window.phone2act.video.frames >= 10, 'video frames', 20000);
    const n = await page.evaluate(() => window.phone2act.video.g2gAll.length);
    await sleep(4000);
    const video = await page.evaluate((k) => window.phone2act.video.g2gAll.slice(k), n);
    await page.uncheck('#video-on');
    await page.check('#preview-on');
    // The preview runs at 5 fps at most: 8 frames take 1.6 s, and up to 15 s on a loaded machine.
    await waitPage(page, () => window.phone2act.video.previewG2g.length >= 8, 'preview frames with a capture time', 15000);
    await sleep(4000);
    const jpeg = await page.evaluate(() => window.phone2act.video.previewG2g.slice());
    await page.uncheck('#preview-on');
    console.log(`  glass to glass, WebRTC video: ${fmt(video)}; JPEG preview: ${fmt(jpeg)}`);
    assert(video.length >= 5, `latency known for only ${video.length} video frames in 4 s`);
    assert(jpeg.every((ms) => ms > 0 && ms < 5000), `implausible preview latencies: ${jpeg.slice(0, 10)}`);
  } finally {
    await context.close();
  }
});

// A slow link towards the page, shared by the page's socket and its video like one Wi-Fi hop: everything the
// gateway sends (TCP through a relay in front of its HTTPS port, UDP through a relay the page's answer is
// pointed at) waits in one FIFO drained at `bps`. UDP datagrams that would wait longer than `bufferMs` are
// dropped, as a router's queue does; TCP bytes are never dropped (TCP would resend them). The page's own
// traffic towards the gateway passes unthrottled.
// The relay's address towards the gateway: another loopback address, which the gateway takes for another machine.
const RELAY_IP = '127.0.0.2';
async function throttledLink() {
  const link = {
    bps: Infinity, bufferMs: 300, queue: [], queuedBytes: 0, dropped: 0, sentBytes: 0, maxWaitMs: 0, sockets: new Set(),
    // Bytes delivered towards the page by kind (see `classify`), and the RTP payload types of the answer.
    byKind: {}, droppedByKind: {}, pts: { video: new Set(), rtx: new Set() },
  };
  let pumping = null;
  const pump = () => {
    pumping = null;
    if (link.closed) return;
    const now = performance.now();
    while (link.queue.length && link.queue[0].at <= now) {
      const item = link.queue.shift();
      link.queuedBytes -= item.bytes;
      link.sentBytes += item.bytes;
      link.byKind[item.kind] = (link.byKind[item.kind] || 0) + item.bytes;
      item.send();
    }
    if (link.queue.length) pumping = setTimeout(pump, Math.max(0, link.queue[0].at - performance.now()));
  };
  // Departure times follow the link's rate from the last queued item: FIFO, so TCP bytes stay in order.
  link.enqueue = (bytes, send, droppable, kind) => {
    if (link.closed) return;
    const now = performance.now();
    const last = link.queue.length ? link.queue[link.queue.length - 1].at : now;
    const at = Number.isFinite(link.bps) ? Math.max(now, last) + (bytes * 8 * 1000) / link.bps : now;
    if (droppable && at - now > link.bufferMs) {
      link.dropped += 1;
      link.droppedByKind[kind] = (link.droppedByKind[kind] || 0) + 1;
      return;
    }
    link.maxWaitMs = Math.max(link.maxWaitMs, at - now);
    link.queue.push({ at, bytes, send, kind });
    link.queuedBytes += bytes;
    if (!pumping) pumping = setTimeout(pump, Math.max(0, at - now));
  };
  link.tcp = createServer((client) => {
    const gateway = connect({ port: Number(HTTPS_PORT), host: '127.0.0.1', localAddress: RELAY_IP });
    for (const s of [client, gateway]) link.sockets.add(s);
    client.on('data', (chunk) => gateway.write(chunk));
    gateway.on('data', (chunk) => link.enqueue(chunk.length, () => client.write(chunk), false, 'control'));
    client.on('close', () => gateway.destroy());
    gateway.on('close', () => link.enqueue(0, () => client.destroy(), false, 'control'));
    client.on('error', () => gateway.destroy());
    gateway.on('error', () => client.destroy());
  });
  await new Promise((resolve) => link.tcp.listen(0, '127.0.0.1', resolve));
  link.base = `https://127.0.0.1:${link.tcp.address().port}`;
  // UDP: `toPage` faces the page, `toGateway` the gateway's video socket (its port learnt from the answer).
  link.toPage = createSocket('udp4');
  link.toGateway = createSocket('udp4');
  await new Promise((r) => link.toPage.bind(0, '127.0.0.1', r));
  await new Promise((r) => link.toGateway.bind(0, RELAY_IP, r));
  link.udpPort = link.toPage.address().port;
  link.gatewayPort = null;
  let pageAddr = null;
  link.toPage.on('message', (msg, from) => {
    pageAddr = from;
    if (link.gatewayPort) link.toGateway.send(msg, link.gatewayPort, '127.0.0.1');
  });
  link.toGateway.on('message', (msg) => {
    if (!pageAddr) return;
    const to = pageAddr;
    link.enqueue(msg.length + 28, () => link.toPage.send(msg, to.port, to.address), true, link.classify(msg));
  });
  // What a datagram from the gateway is, from its clear-text first bytes (RFC 7983 demultiplexing; SRTP leaves the
  // RTP header in the clear): STUN, DTLS (the handshake and the data channel's SCTP), RTCP (packet types 192-223),
  // or RTP by payload type, a packet with the padding bit set counting as padding (str0m's padding and probes
  // are padding-only packets on the RTX stream, or, for larger requests, old video packets resent on it).
  link.classify = (msg) => {
    const b0 = msg[0];
    if (b0 <= 3) return 'stun';
    if (b0 >= 20 && b0 <= 63) return 'dtls';
    if (b0 < 128 || b0 > 191 || msg.length < 12) return 'other';
    if (msg[1] >= 192 && msg[1] <= 223) return 'rtcp';
    if (b0 & 0x20) return 'padding';
    const pt = msg[1] & 0x7f;
    if (link.pts.video.has(pt)) return 'video';
    if (link.pts.rtx.has(pt)) return 'rtx';
    return 'other';
  };
  // The answer's payload types: H.264 is the video, rtx its resends.
  link.learnAnswer = (sdp) => {
    for (const [, pt, codec] of sdp.matchAll(/a=rtpmap:(\d+) ([\w-]+)\//g)) {
      if (/^H264$/i.test(codec)) link.pts.video.add(Number(pt));
      if (/^rtx$/i.test(codec)) link.pts.rtx.add(Number(pt));
    }
  };
  link.close = () => {
    link.closed = true;
    clearTimeout(pumping);
    for (const s of link.sockets) s.destroy();
    link.tcp.close();
    link.toPage.close();
    link.toGateway.close();
  };
  return link;
}

// A phone page that reaches the gateway only through `link`: its socket through the TCP relay, and its video
// through the UDP relay (the answer's candidate points at the relay, which learns the gateway's real port).
async function relayedPage(link) {
  const initScript = `(() => {
    const set = RTCPeerConnection.prototype.setRemoteDescription;
    RTCPeerConnection.prototype.setRemoteDescription = async function patched(d) {
      const m = /a=candidate:\\S+ \\d+ \\S+ \\d+ \\S+ (\\d+)/.exec(d.sdp);
      if (m) await window.__videoTarget(Number(m[1]), d.sdp);
      const sdp = d.sdp.replace(/(a=candidate:\\S+ \\d+ \\S+ \\d+ \\S+ )\\d+/g, '$1${link.udpPort}');
      return set.call(this, { type: d.type, sdp });
    };
  })();`;
  const context = await browser.newContext({ ignoreHTTPSErrors: true, viewport: { width: 412, height: 915 } });
  await context.exposeBinding('__videoTarget', (_src, port, sdp) => { link.gatewayPort = port; link.learnAnswer(sdp); });
  await context.addInitScript({ path: join(here, 'webxr-shim.js') });
  await context.addInitScript(initScript);
  const page = await context.newPage();
  page.on('pageerror', (e) => console.log(`page error: ${e.message}`));
  await page.goto(`${link.base}/?token=${encodeURIComponent(PAIRING_TOKEN)}`);
  await waitPage(page, () => window.phone2act && window.phone2act.sessionOpen, 'session open');
  return { context, page };
}

await check('on a throttled link the video bitrate comes down and control does not stall', async () => {
  const link = await throttledLink();
  let context = null;
  try {
    const relayed = await relayedPage(link);
    context = relayed.context;
    const { page } = relayed;
    await page.click('#start-ar');
    await waitPage(page, () => window.phone2act.feedbackCount > 20, 'feedback');
    await page.check('#video-on');
    // Up to 20 s for the first frame: ICE, DTLS and a keyframe on a machine with a load average near 18.
    // VIDEO_BASELINE=1 measures a gateway that sends no bitrate (one without rate adaptation) and checks nothing.
    const baseline = !!process.env.VIDEO_BASELINE;
    await waitPage(page, `window.phone2act.video.frames >= 10 && (${baseline} || window.phone2act.video.bitrateBps)`,
      'video through the relay', 20000);
    let t = await pageNow(page);
    let sent0 = link.sentBytes;
    let kinds0 = { ...link.byKind };
    await sleep(3000);
    const before = {
      rtt: await rttsSince(page, t),
      bitrate: await page.evaluate(() => window.phone2act.video.bitrateBps),
      kbps: ((link.sentBytes - sent0) * 8) / 3000,
      kinds: kindKbps(kinds0, link.byKind, 3000),
    };
    const kbps = Number(process.env.VIDEO_LINK_KBPS || 600);
    link.bps = kbps * 1000;
    const throttledAt = Date.now();
    // Congestion control lowers its estimate within a few seconds of the queue growing; 30 s leaves room for a
    // loaded machine, where the page's feedback and the gateway's video thread run late.
    if (baseline) await sleep(8000);
    else {
      await waitPage(page, `window.phone2act.video.bitrateBps && window.phone2act.video.bitrateBps <= ${0.8 * kbps * 1000}`,
        `the bitrate to fall under 80% of the ${kbps} kbit/s link`, 30000);
    }
    const adaptedS = (Date.now() - throttledAt) / 1000;
    // Settled: control and video over the slow link together.
    await sleep(2000);
    const f0 = await videoFrames(page);
    link.maxWaitMs = 0;
    const dropped0 = link.dropped;
    const droppedKinds0 = { ...link.droppedByKind };
    const stats0 = await inboundStats(page);
    t = await pageNow(page);
    sent0 = link.sentBytes;
    kinds0 = { ...link.byKind };
    const windowStart = performance.now();
    await sleep(4000);
    const windowMs = performance.now() - windowStart;
    const after = {
      kbps: ((link.sentBytes - sent0) * 8) / windowMs,
      kinds: kindKbps(kinds0, link.byKind, windowMs),
      rtt: await rttsSince(page, t),
      bitrate: await page.evaluate(() => window.phone2act.video.bitrateBps),
      estimate: await page.evaluate(() => window.phone2act.video.linkEstimateBps),
      notes: await page.evaluate(() => window.phone2act.video.notes.map(([, b, e]) => `${(b / 1e3).toFixed(0)}/${((e || 0) / 1e3).toFixed(0)}`).filter((x, i, a) => i === 0 || x !== a[i - 1]).join(' ')),
      fps: ((await videoFrames(page)) - f0) / 4,
    };
    const stats1 = await inboundStats(page);
    const droppedKinds = Object.entries(link.droppedByKind).map(([k, n]) => [k, n - (droppedKinds0[k] || 0)]).filter(([, n]) => n > 0);
    console.log(`  unthrottled: bitrate ${(before.bitrate / 1e3).toFixed(0)} kbit/s, ${before.kbps.toFixed(0)} kbit/s towards the page, control ${fmt(before.rtt)}`);
    console.log(`  link at ${kbps} kbit/s (300 ms queue): bitrate under 80% of it after ${adaptedS.toFixed(1)} s; then `
      + `bitrate ${(after.bitrate / 1e3).toFixed(0)} kbit/s (link estimate ${(after.estimate / 1e3).toFixed(0)} kbit/s), `
      + `${after.fps.toFixed(1)} fps decoded, ${after.kbps.toFixed(0)} kbit/s towards the page, control ${fmt(after.rtt)}, longest queue wait ${link.maxWaitMs.toFixed(0)} ms, `
      + `${link.dropped - dropped0} datagrams dropped`);
    // What the link carried towards the page, by kind: how much of it was the video, of all and of what the
    // video's connection sent (everything but the control socket).
    const connKbps = KINDS.filter((k) => k !== 'control').reduce((sum, k) => sum + after.kinds[k], 0);
    const videoShare = connKbps > 0 ? after.kinds.video / connKbps : 0;
    console.log(`  towards the page, kbit/s by kind: unthrottled ${fmtKinds(before.kinds)}; slow link ${fmtKinds(after.kinds)}`
      + ` (video ${((100 * after.kinds.video) / after.kbps).toFixed(0)}% of it, ${(100 * videoShare).toFixed(0)}% of the video connection's); dropped ${droppedKinds.map(([k, n]) => `${k} ${n}`).join(', ') || 'none'};`
      + ` page sent ${stats1.nack - stats0.nack} NACKs, ${stats1.pli - stats0.pli} PLIs, decoded ${stats1.keyframes - stats0.keyframes} keyframes`
      + `, got ${(((stats1.rtxBytes - stats0.rtxBytes) * 8) / windowMs).toFixed(0)} kbit/s of resends`);
    if (process.env.VIDEO_VERBOSE) console.log(`  bitrate/estimate kbit/s over time: ${after.notes}`);
    if (baseline) return;
    // Most of what the video's connection sends is the video (the control socket, 320-343 kbit/s of this link in
    // every run, is the page's own traffic and not counted here). x264 spreads its bitrate over the camera's frame
    // rate, so an encoder starved of frames (the CPU or the server's camera short, as on this loaded machine at
    // 2 fps decoded) would carry a fraction of its target; the link then looks idle to str0m, which fills it with
    // its padding (50 kbit/s) and probes: video 17 kbit/s beside 56-59 kbit/s of padding, 20-22% of the
    // connection, in 2 of 10 runs of builds that budgeted for the camera's rate (68-89% in the other 8, where
    // frames were not short). Spread over the frames actually encoded, the video carries its target: 70-93% of
    // the connection in 17 runs on the same machine at load averages of 5-8, the rest RTCP (1 kbit/s), the data
    // channel's notes (3-33 kbit/s, one a frame) and resends after losses (up to 38 kbit/s). The machine's load
    // lowers the frame rate, which no longer lowers the video's bytes, so half holds with margin.
    assert(videoShare >= 0.5, `the video is ${(100 * videoShare).toFixed(0)}% of its connection's bytes on the slow link: ${fmtKinds(after.kinds)}`);
    // The bitrate after settling is printed, not checked: where the CPU is short the encoder makes fewer frames
    // than the link carries, the link is then not full, and the estimate may rightly rise again.
    assert(after.rtt.length >= 20, `control nearly stopped on the slow link: ${after.rtt.length} round trips in 4 s`);
    // A sender that ignored the link would keep the 300 ms queue full, and every feedback message would wait in
    // it: a median round trip of 300 ms or more. The machine's own load adds tens of milliseconds (26 ms median
    // measured with two busy threads at a load average of 17), so 150 ms tells the two apart.
    assert(q(after.rtt, 0.5) < 150, `control round trip median ${q(after.rtt, 0.5).toFixed(0)} ms on the slow link`);
    // The video keeps coming on the slow link. Not necessarily within the 4 s window: after a loss the page waits
    // for a keyframe, which takes seconds to cross a link the video gets under 100 kbit/s of, so 10 s more.
    const framesNow = await videoFrames(page);
    await waitPage(page, `window.phone2act.video.frames > ${framesNow}`, 'a video frame on the slow link', 10000);
  } finally {
    if (context) await context.close();
    link.close();
  }
});

await check('a gateway that stalls for want of CPU keeps the video going to a remote page (bitrate printed)', async () => {
  // The page through the relay, unthrottled: the gateway takes it for another machine and runs congestion
  // control. Then the gateway alone is stalled, as a loaded server stalls it (stopped 40 ms of every 100 ms
  // for 8 s), while Chromium and the relay run on: nothing limits the link, so a falling estimate would be the
  // server's stalls misread as a queue. (stress-ng on this one machine would also load the browser and the
  // relay, whose delays are then real ones on the page's side.)
  const pid = Number(process.env.GATEWAY_PID);
  assert(pid > 0, 'GATEWAY_PID not set (run through tests/browser/run.sh)');
  const link = await throttledLink();
  let context = null;
  let stopped = false;
  try {
    const relayed = await relayedPage(link);
    context = relayed.context;
    const { page } = relayed;
    await page.check('#video-on');
    // Up to 20 s for the first frames (ICE, DTLS and a keyframe on a loaded machine), as above.
    await waitPage(page, () => window.phone2act.video.frames >= 10 && window.phone2act.video.bitrateBps, 'video through the relay', 20000);
    await sleep(2000);
    const t0 = await pageNow(page);
    const end = Date.now() + 8000;
    while (Date.now() < end) {
      process.kill(pid, 'SIGSTOP');
      stopped = true;
      await sleep(40);
      process.kill(pid, 'SIGCONT');
      stopped = false;
      await sleep(60);
    }
    // The notes of the last frames sent during the stalls arrive after them.
    await sleep(500);
    const notes = await page.evaluate((since) => window.phone2act.video.notes.filter(([at]) => at > since).map(([, b, e]) => [b, e]), t0);
    const b = notes.map(([x]) => x / 1e3);
    const e = notes.filter(([, x]) => x).map(([, x]) => x / 1e3);
    console.log(`  gateway stalled 40 ms in every 100 ms for 8 s: encoder bitrate ${Math.min(...b).toFixed(0)}-${Math.max(...b).toFixed(0)} kbit/s`
      + ` (median ${q(b, 0.5).toFixed(0)}), link estimate ${Math.min(...e).toFixed(0)}-${Math.max(...e).toFixed(0)} kbit/s, ${notes.length} frames`);
    assert(notes.length >= 20, `only ${notes.length} frames through the stalls`);
    // The bitrate is printed, not bounded: the lowest bitrate of a build that stamped each frame's first packets
    // with the time of its last input was 581 and 959 kbit/s in two runs, this one's 1.5 Mbit/s in three and
    // 736 and 692 kbit/s in two more, so no bound separates the two builds on this loaded machine.
  } finally {
    if (stopped) process.kill(pid, 'SIGCONT');
    if (context) await context.close();
    link.close();
  }
});

await browser.close();
finish('video');

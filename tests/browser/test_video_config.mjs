// [gateway.video] against the page, in headless Chromium against the real server and gateway, one stack per
// mode (tests/browser/run.sh starts them):
//  - `off`: a gateway with `enabled = false` (video-off-gateway.toml). The page offers no video switch and keeps
//    the JPEG preview; an offer sent anyway is refused with the key that turned the video off.
//  - `scaled`: a 1920x1080 camera (camera-1080p.toml) and the default limit of 1280x720. The gateway scales the
//    picture down before encoding; Chromium decodes it at 1280x720.
// Prints "video-config: N passed, M failed".
import { join } from 'node:path';
import { BASE, PAIRING_TOKEN, assert, check, finish, here, launch, waitPage } from './harness.mjs';

const mode = process.argv[2];
if (mode !== 'off' && mode !== 'scaled') throw new Error('usage: test_video_config.mjs off|scaled');
const browser = await launch();
const context = await browser.newContext({ ignoreHTTPSErrors: true, viewport: { width: 412, height: 915 } });
await context.addInitScript({ path: join(here, 'webxr-shim.js') });
const page = await context.newPage();
page.on('pageerror', (e) => console.log(`page error: ${e.message}`));
await page.goto(`${BASE}/?token=${encodeURIComponent(PAIRING_TOKEN)}`);
await waitPage(page, () => window.phone2act && window.phone2act.sessionOpen && window.phone2act.welcome, 'session open');

if (mode === 'off') {
  await check('with [gateway.video] enabled = false the page has no video switch and keeps the JPEG preview', async () => {
    assert(await page.evaluate(() => window.phone2act.welcome.video) === false, 'the welcome does not say the video is off');
    assert(await page.isHidden('#video-box'), 'the page offers the live video switch');
    await page.check('#preview-on');
    // The preview runs at up to 5 fps: 3 images in 15 s leave room for a loaded machine.
    await waitPage(page, () => document.querySelector('#preview').naturalWidth > 0
      && window.phone2act.video.previewG2g.length >= 3, 'JPEG preview images', 15000);
    const size = await page.evaluate(() => [document.querySelector('#preview').naturalWidth, document.querySelector('#preview').naturalHeight]);
    console.log(`  JPEG preview shown (${size[0]}x${size[1]}), no video switch`);
    await page.uncheck('#preview-on');
  });

  await check('an offer sent anyway is refused, saying why', async () => {
    const reply = await page.evaluate(async () => {
      const app = window.phone2act;
      const pc = new RTCPeerConnection({ iceServers: [] });
      pc.addTransceiver('video', { direction: 'recvonly' });
      const offer = await pc.createOffer();
      const got = new Promise((resolve) => {
        app.listeners.push((msg) => {
          if (msg.type === 'video_answer' || (msg.type === 'video' && msg.state === 'error')) resolve(msg);
        });
      });
      app.send({ type: 'video_offer', camera: app.preview.camera || 'front', sdp: offer.sdp, host: location.hostname });
      const msg = await Promise.race([got, new Promise((r) => setTimeout(() => r({ type: 'timeout' }), 10000))]);
      pc.close();
      return msg;
    });
    assert(reply.type === 'video' && reply.state === 'error', `the gateway answered the offer: ${JSON.stringify(reply).slice(0, 200)}`);
    assert(/enabled = false/.test(reply.message), `the refusal does not name the setting: ${reply.message}`);
    console.log(`  offer refused: ${reply.message}`);
  });
} else {
  await check('a 1920x1080 camera is scaled to 1280x720 before encoding and decoded at that size', async () => {
    await page.check('#video-on');
    // Up to 20 s for the first frames: ICE, DTLS and a keyframe on a loaded machine.
    await waitPage(page, () => window.phone2act.video.frames >= 10, 'decoded frames', 20000);
    const got = await page.evaluate(() => {
      const v = document.querySelector('#video');
      return { w: v.videoWidth, h: v.videoHeight, frames: window.phone2act.video.frames };
    });
    // The track's own statistics: what the decoder produced.
    const stats = await page.evaluate(async () => {
      const s = await window.phone2act.video.pc.getStats();
      for (const r of s.values()) {
        if (r.type === 'inbound-rtp' && r.kind === 'video') return { w: r.frameWidth, h: r.frameHeight, decoded: r.framesDecoded, codec: r.codecId };
      }
      return null;
    });
    console.log(`  1920x1080 camera: decoded ${got.w}x${got.h} (${got.frames} frames shown; decoder ${stats && `${stats.w}x${stats.h}, ${stats.decoded} frames`})`);
    assert(got.w === 1280 && got.h === 720, `decoded at ${got.w}x${got.h}`);
    assert(stats && stats.w === 1280 && stats.h === 720 && stats.decoded >= 10, `decoder statistics: ${JSON.stringify(stats)}`);
    await page.uncheck('#video-on');
  });
}

await context.close();
await browser.close();
finish(`video-config (${mode})`);

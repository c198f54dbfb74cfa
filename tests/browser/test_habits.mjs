// Recording habits on the phone page (issue 27). `node test_habits.mjs outcome`: the operator saves an episode
// as a success or a failure with the page's outcome buttons. `node test_habits.mjs countdown` (a server with
// [recorder] episode_time_s, reset_time_s and start_next_after_reset, see run.sh): the page counts the episode
// and the reset period down and cues their transitions. `node test_habits.mjs highlight` (a server with
// [recorder] highlight_s = 2): the SAVE LAST button saves the last seconds the recorder kept while idle. Checked on the server side through independent paths:
// the status topic (rosbridge) and the dataset on disk. Prints "habits: N passed, M failed".
import { readFileSync } from 'node:fs';
import { join } from 'node:path';
import {
  BASE, OUT_DIR, PAIRING_TOKEN, STACK_DIR, ServerView, assert, check, finish, here, launch, pageState, waitPage,
} from './harness.mjs';

const browser = await launch();
const server = new ServerView();
await server.ready;

const context = await browser.newContext({ ignoreHTTPSErrors: true, viewport: { width: 412, height: 915 } });
await context.addInitScript({ path: join(here, 'webxr-shim.js') });
const page = await context.newPage();
page.on('dialog', (d) => d.accept());
page.on('pageerror', (e) => console.log(`page error: ${e.message}`));
await page.goto(`${BASE}/?token=${encodeURIComponent(PAIRING_TOKEN)}`);

// The episodes' outcomes as the recorder kept them (meta/phone2act_provenance.json, written at each save).
function provenanceOutcomes() {
  const prov = JSON.parse(readFileSync(join(STACK_DIR, 'dataset', 'meta', 'phone2act_provenance.json'), 'utf8'));
  return prov.episodes.map((e) => (e.success === undefined ? null : e.success));
}

async function recordThenPress(button, task) {
  const saved = server.status.recording.saved;
  await page.fill('#task', task);
  await page.click('#rec-start');
  await server.until((s) => s.recording.phase === 'recording', 'recording to start');
  // The page enables the outcome buttons from its own feedback, which may lag the server view by a message.
  await waitPage(page, () => !document.querySelector('#rec-success').disabled
    && !document.querySelector('#rec-failure').disabled, 'the outcome buttons enabled while recording');
  // A few frames first: an episode with none is refused (nothing to mark).
  await server.until((s) => s.recording.frames >= 5, 'a few frames recorded');
  await page.click(button);
  await server.until((s) => s.recording.saved === saved + 1 && s.recording.phase === 'idle', 'the episode to be saved', 60000);
  await waitPage(page, () => document.querySelector('#rec-success').disabled, 'outcome buttons disabled again when idle');
  return saved;
}

const suite = process.argv[2] || 'outcome';

if (suite === 'outcome') {
await check('the outcome buttons are off while nothing is recorded', async () => {
  await waitPage(page, () => window.phone2act && window.phone2act.sessionOpen, 'session open');
  await page.click('#start-ar');
  await server.until((s) => s.arm === 'main' && s.recording, 'status of main');
  assert(await page.isDisabled('#rec-success'), 'SUCCESS is enabled while idle');
  assert(await page.isDisabled('#rec-failure'), 'FAILURE is enabled while idle');
  assert(await page.isHidden('#rec-highlight'), 'SAVE LAST is shown by a server that keeps nothing');
});

await check('SUCCESS saves the episode marked as a success', async () => {
  const index = await recordThenPress('#rec-success', 'put the ball in the basket');
  const outcomes = provenanceOutcomes();
  assert(outcomes[index] === true, `episode ${index} outcome ${outcomes[index]} in ${JSON.stringify(outcomes)}`);
  await page.screenshot({ path: join(OUT_DIR, 'phone-page-outcome.png'), fullPage: true });
});

await check('FAILURE saves the episode marked as a failure', async () => {
  const index = await recordThenPress('#rec-failure', 'put the ball in the basket');
  const outcomes = provenanceOutcomes();
  assert(outcomes[index] === false, `episode ${index} outcome ${outcomes[index]} in ${JSON.stringify(outcomes)}`);
});

await check('SAVE keeps an episode without an outcome', async () => {
  const saved = server.status.recording.saved;
  await page.click('#rec-start');
  await server.until((s) => s.recording.phase === 'recording' && s.recording.frames >= 5, 'recording frames');
  await page.click('#rec-stop');
  await server.until((s) => s.recording.saved === saved + 1 && s.recording.phase === 'idle', 'the episode to be saved', 60000);
  const outcomes = provenanceOutcomes();
  assert(outcomes[saved] === null, `episode ${saved} has outcome ${outcomes[saved]}`);
  assert(!(await pageState(page, () => window.phone2act.errors.length)), 'the page reported errors');
});

}

if (suite === 'countdown') {
  const { EPISODE_TIME_S, RESET_TIME_S } = process.env;
  await check('the page counts the episode down, then the reset, and cues each transition', async () => {
    await waitPage(page, () => window.phone2act && window.phone2act.sessionOpen, 'session open');
    await page.click('#start-ar');
    await page.fill('#task', 'put the ball in the basket');
    await page.click('#rec-start');
    await server.until((s) => s.recording.phase === 'recording', 'recording to start');
    await waitPage(page, () => !document.querySelector('#countdown').hidden
      && /^\d+ s$/.test(document.querySelector('#countdown').textContent), 'the episode countdown');
    const shown = Number((await page.textContent('#countdown')).split(' ')[0]);
    assert(shown >= 0 && shown <= Number(EPISODE_TIME_S), `countdown ${shown} s for a ${EPISODE_TIME_S} s limit`);
    assert(/s left/.test(await page.textContent('#st-rec')), 'the status line does not say the time left');
    // The limit saves the episode and the reset period begins: the server says so, and the page follows.
    // Each wait allows several times the configured periods: a loaded machine slows the page, not the rule.
    await server.until((s) => s.recording.resetting && s.recording.saved >= 1, 'the reset period', 30000);
    await waitPage(page, () => /^reset \d+ s$/.test(document.querySelector('#countdown').textContent), 'the reset countdown');
    await page.screenshot({ path: join(OUT_DIR, 'phone-page-reset-countdown.png'), fullPage: true });
    await waitPage(page, () => window.phone2act.cues.some((c) => c.to === 'resetting'), 'a cue at the reset');
    // start_next_after_reset: the next episode starts by itself with the same task.
    await server.until((s) => !s.recording.resetting && s.recording.phase === 'recording' && s.recording.saved >= 1,
      'the next episode to start by itself', 30000);
    assert(server.status.recording.task === 'put the ball in the basket', `task ${server.status.recording.task}`);
    await waitPage(page, () => window.phone2act.cues.some((c) => c.to === 'recording'), 'a cue at the next start');
    const [cues, vibrations] = await pageState(page, () => [window.phone2act.cues, window.__vibrations]);
    const patterns = vibrations.map((v) => JSON.stringify(v));
    assert(patterns.includes('[300,100,300]') && patterns.includes('[500]'), `vibrations ${patterns}`);
    console.log(`  cues: ${JSON.stringify(cues.map((c) => [c.to, c.sound]))}`);
    assert(cues[0].to === 'resetting' && cues[1].to === 'recording', `cues out of order: ${JSON.stringify(cues)}`);
    // The episode saved at the limit has exactly the limit's frames (info.json, the dataset's own count).
    const info = JSON.parse(readFileSync(join(STACK_DIR, 'dataset', 'meta', 'info.json'), 'utf8'));
    assert(info.total_frames % Math.round(Number(EPISODE_TIME_S) * info.fps) === 0,
      `total_frames ${info.total_frames} for ${info.total_episodes} episodes of ${EPISODE_TIME_S} s`);
    // Stop the loop: a discard starts no reset period and no next episode.
    await page.click('#rec-discard');
    await server.until((s) => s.recording.phase === 'idle' && !s.recording.resetting, 'idle after the discard', 30000);
    await waitPage(page, () => document.querySelector('#countdown').hidden, 'the countdown hidden when idle');
  });
}

if (suite === 'highlight') {
  const keepS = Number(process.env.HIGHLIGHT_S);
  await check('SAVE LAST saves the last seconds kept while idle as an episode', async () => {
    await waitPage(page, () => window.phone2act && window.phone2act.sessionOpen, 'session open');
    await page.click('#start-ar');
    await server.until((s) => s.recording && s.recording.highlight_s === keepS, 'the server keeps the last seconds');
    // The button says how much is kept, and is live once something is.
    await page.evaluate((k) => { window.__keepS = k.toFixed(1); }, keepS);
    await waitPage(page, () => !document.querySelector('#rec-highlight').hidden
      && !document.querySelector('#rec-highlight').disabled
      && document.querySelector('#rec-highlight').textContent.includes(`SAVE LAST ${window.__keepS} s`),
    'SAVE LAST with the seconds kept', 30000);
    await page.fill('#task', 'the last two seconds');
    await page.click('#rec-highlight');
    await server.until((s) => s.recording.saved === 1 && s.recording.phase === 'idle', 'the kept seconds saved', 60000);
    // From the oldest kept tick at a multiple of the video GOP (2): N·fps frames, or one more.
    const info = JSON.parse(readFileSync(join(STACK_DIR, 'dataset', 'meta', 'info.json'), 'utf8'));
    const want = Math.round(keepS * info.fps);
    assert(info.total_episodes === 1 && info.total_frames >= want && info.total_frames <= want + 1,
      `${info.total_episodes} episodes, ${info.total_frames} frames for ${keepS} s at ${info.fps} fps`);
    await page.screenshot({ path: join(OUT_DIR, 'phone-page-highlight.png'), fullPage: true });
  });

  await check('SAVE LAST is off while an episode records (it holds these seconds itself)', async () => {
    await page.click('#rec-start');
    await server.until((s) => s.recording.phase === 'recording', 'recording to start');
    await waitPage(page, () => document.querySelector('#rec-highlight').disabled, 'SAVE LAST disabled while recording');
    await page.click('#rec-discard');
    await server.until((s) => s.recording.phase === 'idle', 'idle after the discard', 30000);
    // The recorder keeps the last seconds again once idle.
    await waitPage(page, () => !document.querySelector('#rec-highlight').disabled, 'SAVE LAST live again', 30000);
    assert(!(await pageState(page, () => window.phone2act.errors.length)), 'the page reported errors');
  });
}

server.close();
await context.close();
await browser.close();
finish('habits');

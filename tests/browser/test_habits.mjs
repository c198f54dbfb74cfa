// Recording habits on the phone page (issue 27): the operator saves an episode as a success or a failure with the
// page's outcome buttons. Checked on the server side through independent paths: the status topic (rosbridge)
// and the episode's provenance in the dataset on disk. Prints "habits: N passed, M failed".
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

await check('the outcome buttons are off while nothing is recorded', async () => {
  await waitPage(page, () => window.phone2act && window.phone2act.sessionOpen, 'session open');
  await page.click('#start-ar');
  await server.until((s) => s.arm === 'main' && s.recording, 'status of main');
  assert(await page.isDisabled('#rec-success'), 'SUCCESS is enabled while idle');
  assert(await page.isDisabled('#rec-failure'), 'FAILURE is enabled while idle');
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

server.close();
await context.close();
await browser.close();
finish('habits');

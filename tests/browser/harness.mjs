// What the browser tests share: the server-side view (a rosbridge subscription to an arm's status topic), the
// pass/fail bookkeeping, Debian's headless Chromium, and waiting on page state.
import { chromium } from 'playwright-core';
import { mkdirSync } from 'node:fs';
import { join, dirname } from 'node:path';
import { fileURLToPath } from 'node:url';

export const here = dirname(fileURLToPath(import.meta.url));
export const { HTTPS_PORT, ROSBRIDGE_PORT, PAIRING_TOKEN, STACK_DIR } = process.env;
if (!HTTPS_PORT || !ROSBRIDGE_PORT || !PAIRING_TOKEN) throw new Error('run through tests/browser/run.sh');
export const BASE = `https://127.0.0.1:${HTTPS_PORT}`;
export const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
// Screenshots go here (kept after the run, ignored by git).
export const OUT_DIR = process.env.BROWSER_OUT || join(here, 'out');
mkdirSync(OUT_DIR, { recursive: true });

// The server's own account of an arm, independent of the page: its status topic through the gateway's rosbridge
// (System.WatchStatus behind it). `topic` is /phone2act/status for the default arm, /<arm>/phone2act/status
// for another.
export class ServerView {
  constructor(topic = '/phone2act/status') {
    this.status = null;
    this.ws = new WebSocket(`ws://127.0.0.1:${ROSBRIDGE_PORT}/`);
    this.ready = new Promise((resolve, reject) => {
      this.ws.onopen = () => {
        this.ws.send(JSON.stringify({ op: 'subscribe', topic, type: 'std_msgs/msg/String' }));
        resolve();
      };
      this.ws.onerror = (e) => reject(new Error(`rosbridge socket: ${e.message || e.type}`));
    });
    this.ws.onmessage = (ev) => {
      const msg = JSON.parse(ev.data);
      if (msg.op === 'publish' && msg.topic === topic) this.status = JSON.parse(msg.msg.data);
    };
  }
  async until(pred, what, timeoutMs = 15000) {
    const deadline = Date.now() + timeoutMs;
    while (Date.now() < deadline) {
      if (this.status && pred(this.status)) return this.status;
      await sleep(25);
    }
    throw new Error(`timed out waiting for ${what}; server status: ${JSON.stringify(this.status)}`);
  }
  close() { this.ws.close(); }
}

export const dist = (a, b) => Math.hypot(a[0] - b[0], a[1] - b[1], a[2] - b[2]);

const results = [];
export async function check(name, fn) {
  const t0 = Date.now();
  try {
    await fn();
    results.push([name, true]);
    console.log(`PASS ${name} (${Date.now() - t0} ms)`);
  } catch (e) {
    results.push([name, false]);
    console.log(`FAIL ${name}: ${e.stack || e}`);
  }
}
export function assert(cond, msg) { if (!cond) throw new Error(msg); }

// Prints "<suite>: N passed, M failed" and exits non-zero on a failure.
export function finish(suite) {
  const passed = results.filter(([, ok]) => ok).length;
  const failed = results.length - passed;
  console.log(`${suite}: ${passed} passed, ${failed} failed`);
  process.exit(failed ? 1 : 0);
}

// Playwright starts Chromium with a new, empty profile directory of its own and removes it afterwards.
export function launch() {
  return chromium.launch({
    executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
    headless: true,
    args: [
      '--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run', '--disable-background-networking',
      '--disable-component-update', '--disable-sync', '--ignore-certificate-errors',
    ],
  });
}

export const pageState = (page, expr) => page.evaluate(expr);
export async function waitPage(page, fn, what, timeoutMs = 15000) {
  try {
    await page.waitForFunction(fn, null, { timeout: timeoutMs, polling: 25 });
  } catch (e) {
    throw new Error(`page: timed out waiting for ${what}: ${e.message.split('\n')[0]}`);
  }
}

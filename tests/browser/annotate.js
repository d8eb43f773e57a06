// Drives the annotate page in headless chromium (playwright-core): waits for
// the cloud, drags a rectangle around one object in the top view, names the
// box, saves, waits for the live check and takes a screenshot.
// Usage: node annotate.js URL CORNERS_JSON SCREENSHOT CHROMIUM
const { chromium } = require('playwright-core');

(async () => {
  const [url, cornersJson, shot, exe] = process.argv.slice(2);
  const browser = await chromium.launch({
    executablePath: exe,
    headless: true,
    args: ['--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run', '--disable-background-networking',
      '--disable-component-update', '--disable-sync', '--use-angle=swiftshader', '--enable-unsafe-swiftshader'],
  });
  try {
    const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
    page.on('console', (m) => console.error(`page: ${m.text()}`));
    page.on('pageerror', (e) => console.error(`page error: ${e.message}`));
    await page.goto(url);
    await page.waitForFunction(() => document.body.dataset.ready, null, { timeout: 120000 });
    const ready = await page.evaluate(() => document.body.dataset.ready);
    if (ready !== '1') throw new Error(`the page did not load: ${await page.textContent('#status')}`);
    // Gesture 1: the new-box tool (switches to the top view); gesture 2: the drag.
    await page.click('#tool-box');
    const corners = JSON.parse(cornersJson);
    const pts = await page.evaluate((c) => c.map((p) => window.annotate.worldToScreen(p)), corners);
    const xs = pts.map((p) => p[0]), ys = pts.map((p) => p[1]);
    const margin = 10;
    const [x0, x1, y0, y1] = [Math.min(...xs) - margin, Math.max(...xs) + margin, Math.min(...ys) - margin, Math.max(...ys) + margin];
    await page.mouse.move(x0, y0);
    await page.mouse.down();
    await page.mouse.move(x1, y1, { steps: 10 });
    await page.mouse.up();
    await page.waitForFunction(() => window.annotate.boxes().length === 1, null, { timeout: 60000 });
    // Keys: a nudge moves the box 1 cm along the ground's x, undo brings it back,
    // redo repeats it, Q turns it 1 degree, F flips its heading.
    const centre = () => page.evaluate(() => window.annotate.boxes()[0].center.slice());
    const yaw = () => page.evaluate(() => { const r = window.annotate.boxes()[0].rotation; return Math.atan2(r[1][0], r[0][0]) * 180 / Math.PI; });
    const c0 = await centre();
    await page.keyboard.press('ArrowRight');
    const c1 = await centre();
    await page.keyboard.press('Control+z');
    const c2 = await centre();
    await page.keyboard.press('Control+y');
    const c3 = await centre();
    await page.keyboard.press('Control+z');
    const t0 = await yaw();
    await page.keyboard.press('q');
    const t1 = await yaw();
    await page.keyboard.press('f');
    const t2 = await yaw();
    await page.keyboard.press('Control+z');
    await page.keyboard.press('Control+z');
    const t3 = await yaw();
    const near = (a, b, tol) => Math.abs(a - b) < tol;
    const turn = (a) => ((a % 360) + 540) % 360 - 180;
    const checks = {
      nudge: near(Math.hypot(c1[0] - c0[0], c1[1] - c0[1]), 0.01, 1e-6),
      undo: near(Math.hypot(c2[0] - c0[0], c2[1] - c0[1]), 0, 1e-9),
      redo: near(Math.hypot(c3[0] - c1[0], c3[1] - c1[1]), 0, 1e-9),
      yaw: near(turn(t1 - t0), 1, 1e-6),
      flip: near(Math.abs(turn(t2 - t1)), 180, 1e-6),
      undo_turns: near(turn(t3 - t0), 0, 1e-6),
    };
    const failed = Object.entries(checks).filter(([, ok]) => !ok).map(([k]) => k);
    if (failed.length) throw new Error(`editing keys failed: ${failed.join(', ')} (${JSON.stringify({ c0, c1, c2, c3, t0, t1, t2, t3 })})`);
    // A drag inside the top ortho view moves the box along its own x axis.
    const before = await page.evaluate(() => JSON.parse(JSON.stringify(window.annotate.boxes()[0])));
    const ortho = await page.locator('#ortho-top').boundingBox();
    const [ox, oy] = [ortho.x + ortho.width / 2, ortho.y + ortho.height / 2];
    await page.mouse.move(ox, oy);
    await page.mouse.down();
    await page.mouse.move(ox + 20, oy, { steps: 5 });
    await page.mouse.up();
    const after = await page.evaluate(() => window.annotate.boxes()[0]);
    const d = after.center.map((c, k) => c - before.center[k]);
    const axis = [0, 1, 2].map((k) => before.rotation[k][0]);
    const along = d[0] * axis[0] + d[1] * axis[1] + d[2] * axis[2];
    const across = Math.hypot(d[0] - along * axis[0], d[1] - along * axis[1], d[2] - along * axis[2]);
    const sameSize = after.size.every((v, k) => Math.abs(v - before.size[k]) < 1e-9);
    if (!(along > 0.005 && across < 1e-6 && sameSize)) {
      throw new Error(`the ortho drag did not move the box along x: ${JSON.stringify({ d, along, across, sameSize })}`);
    }
    await page.keyboard.press('Control+z');
    const undone = await page.evaluate(() => window.annotate.boxes()[0].center);
    if (Math.hypot(...undone.map((c, k) => c - before.center[k])) > 1e-9) throw new Error('undo after the ortho drag');
    await page.fill('#box-label', 'box');
    await page.press('#box-label', 'Enter');
    await page.click('#save');
    await page.waitForFunction(() => document.getElementById('status').textContent.startsWith('saved'), null, { timeout: 30000 });
    await page.click('#view-3d');
    await page.waitForFunction(() => document.getElementById('preview').src.startsWith('blob:'), null, { timeout: 60000 });
    await page.waitForTimeout(1500);
    await page.screenshot({ path: shot });
    console.log(JSON.stringify({ status: await page.textContent('#status'), rect: [x0, y0, x1, y1] }));
  } finally {
    await browser.close();
  }
})().catch((e) => {
  console.error(e);
  process.exit(1);
});

// End-to-end test of the live viewer in headless Chromium, driven by playwright-core.
//
//   node tests/browser/view.mjs URL SCREENSHOT.png
//
// Opens the page of a running `geese run --view` and checks: the step counter advances;
// the canvas shows agents; pause stops the counter; clicking an agent shows its tree;
// a click with "click adds an obstacle" adds an obstacle there, which the world's next
// frame shows; resume restarts the counter. Saves a screenshot. Prints one JSON line of
// what it saw; exits 1 naming the first check that failed. Every wait is bounded.
import { chromium } from "playwright-core";

const [url, shot] = process.argv.slice(2);
if (!url || !shot) {
  console.error("usage: node view.mjs URL SCREENSHOT.png");
  process.exit(2);
}
const executablePath = process.env.CHROMIUM || "/usr/bin/chromium";
const seen = { ms: {} };
const t0 = Date.now();
const mark = what => { seen.ms[what] = Date.now() - t0; };
const sleep = ms => new Promise(r => setTimeout(r, ms));

function check(ok, what) {
  if (!ok) throw new Error(`check failed: ${what} (seen so far: ${JSON.stringify(seen)})`);
}

const browser = await chromium.launch({ executablePath, headless: true, args: ["--no-sandbox", "--disable-gpu"], timeout: 30000 });
try {
  const page = await browser.newPage({ viewport: { width: 1250, height: 900 } });
  page.setDefaultTimeout(15000);
  await page.goto(url);
  const step = async () => Number(await page.textContent("#step"));
  await page.waitForFunction(() => Number(document.getElementById("step").textContent) > 0);

  // 1. The counter advances.
  const s1 = await step();
  await sleep(1000);
  const s2 = await step();
  mark("advance");
  seen.advance = [s1, s2];
  check(s2 > s1, "the step counter advances");

  // 2. The canvas shows agents: pixels of the behaviour-class colours.
  const painted = await page.evaluate(() => {
    const c = document.getElementById("arena"), d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
    const colours = Object.values(CLASSES).map(h => [1, 3, 5].map(i => parseInt(h.slice(i, i + 2), 16)));
    let n = 0;
    for (let i = 0; i < d.length; i += 4) {
      if (colours.some(([r, g, b]) => d[i] === r && d[i + 1] === g && d[i + 2] === b)) n++;
    }
    return { pixels: n, agents: frame.agents.length };
  });
  mark("canvas");
  seen.canvas = painted;
  check(painted.agents > 0 && painted.pixels >= painted.agents, "the canvas shows agents");

  // 3. Pause stops the counter.
  await page.click("#pause");
  await page.waitForFunction(() => document.getElementById("state").textContent === "paused");
  const p1 = await step();
  await sleep(1200);
  const p2 = await step();
  mark("paused");
  seen.paused = [p1, p2];
  check(p1 === p2, "pause stops the counter");

  // 4. Clicking an agent shows its tree (agents hold still while paused).
  const target = await page.evaluate(() => {
    const a = frame.agents.find(a => a.live);
    const [x, y] = toPx(a.x, a.y);
    return { id: a.id, x, y };
  });
  await page.click("#arena", { position: { x: target.x, y: target.y } });
  await page.waitForFunction(() => document.querySelectorAll("#tree svg g.node").length > 0);
  mark("agent");
  seen.agent = {
    id: target.id,
    title: await page.textContent("#agentTitle"),
    nodes: await page.evaluate(() => document.querySelectorAll("#tree svg g.node").length),
  };
  check(seen.agent.title.includes(`Agent ${target.id}`), "the clicked agent's detail is shown");

  // 5. A click on the arena adds an obstacle there; the next frame shows it.
  const before = await page.evaluate(() => frame.objects.filter(o => o.kind === "Obstacles").length);
  const spot = await page.evaluate(() => {
    // An empty place away from the hub: (-w/4, h/4) in arena coordinates.
    const wx = Math.round(-frame.width / 4), wy = Math.round(frame.height / 4), [x, y] = toPx(wx, wy);
    return { wx, wy, x, y };
  });
  await page.check("#obstacleMode");
  await page.click("#arena", { position: { x: spot.x, y: spot.y } });
  await page.waitForFunction(
    ([wx, wy]) => frame.objects.some(o => o.kind === "Obstacles" && Math.abs(o.x - wx) <= 1 && Math.abs(o.y - wy) <= 1),
    [spot.wx, spot.wy],
  );
  mark("obstacle");
  seen.obstacle = {
    at: [spot.wx, spot.wy],
    before,
    after: await page.evaluate(() => frame.objects.filter(o => o.kind === "Obstacles").length),
    events: await page.evaluate(() => frame.events),
  };
  check(seen.obstacle.after === before + 1, "exactly one obstacle was added");
  await page.uncheck("#obstacleMode");

  // 6. Resume restarts the counter.
  await page.click("#resume");
  await page.waitForFunction(() => document.getElementById("state").textContent.startsWith("running"));
  const r1 = await step();
  await sleep(1000);
  const r2 = await step();
  mark("resumed");
  seen.resumed = [r1, r2];
  check(r2 > r1, "resume restarts the counter");

  await page.screenshot({ path: shot });
  seen.screenshot = shot;
  console.log(JSON.stringify(seen));
} catch (e) {
  console.error(e.message, JSON.stringify(seen));
  process.exitCode = 1;
} finally {
  await browser.close();
}

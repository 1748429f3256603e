// End-to-end test of rayd's status page in headless Chromium (Debian's `chromium`, driven
// by playwright-core). It starts a real `rayd serve` twice on a free loopback port with a
// temporary data directory (once with --demo, once with --token-file), loads the page,
// uploads scenes (file input and drag and drop), waits for their thumbnails, renders one
// and waits for its image, follows a long render's live progress and cancels and deletes
// it, and fails on any console error, page error, dialog or CSP violation. A scene named
// like markup must show as text; another client then deletes it, and its card must go.
//
//   node tests/browser/status-page.test.mjs [--screenshot docs/status-page.png]
//
// Environment: RAYD_BIN (default target/release/rayd), CHROMIUM (default /usr/bin/chromium).

import { spawn } from "node:child_process";
import fs from "node:fs";
import net from "node:net";
import os from "node:os";
import path from "node:path";
import { fileURLToPath } from "node:url";
import { chromium } from "playwright-core";

const ROOT = path.resolve(path.dirname(fileURLToPath(import.meta.url)), "../..");
const RAYD = process.env.RAYD_BIN || path.join(ROOT, "target/release/rayd");
const CHROMIUM = process.env.CHROMIUM || "/usr/bin/chromium";
const SCENES = path.join(ROOT, "scenes");
const EVIL = "<img src=x onerror=alert(1)>";
const TOKEN = "page-test-token-7f3a9c";
const LIMIT_MS = 120_000;

const shotAt = process.argv.indexOf("--screenshot");
const SCREENSHOT = shotAt > 0 ? path.resolve(process.argv[shotAt + 1]) : null;

function check(cond, what) {
  if (!cond) throw new Error(`check failed: ${what}`);
}

function freePort() {
  return new Promise((resolve, reject) => {
    const srv = net.createServer();
    srv.unref();
    srv.on("error", reject);
    srv.listen(0, "127.0.0.1", () => {
      const { port } = srv.address();
      srv.close(() => resolve(port));
    });
  });
}

/** Starts `rayd serve` with `extra` options; resolves once /readyz answers 200. */
async function startServer(extra, dir) {
  fs.mkdirSync(dir, { recursive: true });
  const port = await freePort();
  const url = `http://127.0.0.1:${port}`;
  const args = ["serve", "--addr", `127.0.0.1:${port}`, "--data-dir", path.join(dir, "store"),
    "--threads", "2", "--grace", "1", ...extra];
  const child = spawn(RAYD, args, {
    stdio: ["ignore", "ignore", "pipe"],
    env: { ...process.env, RAYD_LOG: "warn" },
  });
  let log = "";
  child.stderr.on("data", (d) => (log += d));
  const exited = new Promise((resolve) => child.on("exit", resolve));
  const deadline = Date.now() + 30_000;
  for (;;) {
    if (child.exitCode !== null) throw new Error(`rayd serve exited: ${log}`);
    try {
      if ((await fetch(`${url}/readyz`)).status === 200) break;
    } catch {
      // not listening yet
    }
    if (Date.now() > deadline) throw new Error(`rayd serve did not get ready: ${log}`);
    await new Promise((r) => setTimeout(r, 100));
  }
  return {
    url,
    log: () => log,
    async stop() {
      child.kill("SIGTERM");
      await exited;
    },
  };
}

/** The headers the page and its assets must carry; no cross-origin access anywhere. */
async function checkHeaders(url, auth) {
  const html = await fetch(`${url}/`, { headers: { Accept: "text/html" } });
  check(html.status === 200, "GET / (html) is 200");
  check(html.headers.get("content-type").startsWith("text/html"), "the page is text/html");
  const csp = html.headers.get("content-security-policy") || "";
  for (const d of ["default-src 'self'", "script-src 'self'", "img-src 'self' blob: data:", "frame-ancestors 'none'"]) {
    check(csp.includes(d), `the CSP has ${d}: ${csp}`);
  }
  check(!csp.includes("unsafe-inline") && !csp.includes("unsafe-eval"), "no unsafe-* in the CSP");
  check(html.headers.get("x-content-type-options") === "nosniff", "nosniff on the page");
  const index = await (await fetch(`${url}/`)).json();
  check(index.auth === (auth ? "bearer" : "none"), `the index says auth ${index.auth}`);
  for (const [p, type] of [["/page/app.js", "text/javascript"], ["/page/style.css", "text/css"]]) {
    const r = await fetch(`${url}${p}`, { headers: { Origin: "http://evil.example" } });
    check(r.status === 200, `${p} needs no token`);
    check(r.headers.get("content-type").startsWith(type), `${p} is ${type}`);
    check(!r.headers.has("access-control-allow-origin"), `${p} grants no cross-origin access`);
  }
  const headers = { Origin: "http://evil.example" };
  if (auth) headers.Authorization = `Bearer ${TOKEN}`;
  const v1 = await fetch(`${url}/v1/scenes`, { headers });
  check(v1.status === 200, "GET /v1/scenes with the token");
  check(!v1.headers.has("access-control-allow-origin"), "/v1 grants no cross-origin access");
  if (auth) {
    check((await fetch(`${url}/v1/scenes`)).status === 401, "/v1 without a token is 401");
  }
}

/** A page that records everything that must not happen. */
async function openPage(browser, url) {
  const context = await browser.newContext({ viewport: { width: 1200, height: 900 } });
  const page = await context.newPage();
  const problems = [];
  const requests = [];
  page.on("console", (m) => {
    if (m.type() === "error") problems.push(`console ${m.type()}: ${m.text()}`);
  });
  page.on("pageerror", (e) => problems.push(`page error: ${e.message}`));
  page.on("dialog", (d) => {
    problems.push(`dialog: ${d.message()}`);
    d.dismiss().catch(() => {});
  });
  page.on("request", (r) => requests.push(r.url()));
  await page.addInitScript(() => {
    window.__csp = [];
    document.addEventListener("securitypolicyviolation", (e) =>
      window.__csp.push(`${e.violatedDirective} ${e.blockedURI}`));
  });
  await page.goto(`${url}/`);
  return { context, page, problems, requests };
}

async function finish({ page, context, problems }) {
  const csp = await page.evaluate(() => window.__csp);
  check(csp.length === 0, `no CSP violations: ${csp.join("; ")}`);
  check(problems.length === 0, `no console errors, page errors or dialogs:\n  ${problems.join("\n  ")}`);
  await context.close();
}

async function uploadByInput(page, file) {
  await page.setInputFiles("#file", path.join(SCENES, file));
  await page.locator(".scene .name", { hasText: file }).first().waitFor();
}

/** Drops a file named `name` with `file`'s bytes on the drop zone, as a user's drag would. */
async function uploadByDrop(page, file, name) {
  const b64 = fs.readFileSync(path.join(SCENES, file)).toString("base64");
  await page.evaluate(({ b64, name }) => {
    const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
    const dt = new DataTransfer();
    dt.items.add(new File([bytes], name));
    const drop = document.getElementById("drop");
    for (const type of ["dragenter", "dragover", "drop"]) {
      drop.dispatchEvent(new DragEvent(type, { dataTransfer: dt, bubbles: true, cancelable: true }));
    }
  }, { b64, name });
}

async function sceneId(page, name) {
  return page.evaluate((name) => {
    const card = [...document.querySelectorAll(".scene")]
      .find((c) => c.querySelector(".name").textContent === name);
    return card ? card.dataset.id : null;
  }, name);
}

async function waitThumbnails(page, n) {
  await page.waitForFunction((n) => {
    const imgs = [...document.querySelectorAll(".scene img.thumb")];
    return imgs.length >= n && imgs.every((i) => i.complete && i.naturalWidth === 160 && i.naturalHeight === 120);
  }, n, { timeout: 60_000 });
}

/** Submits the render form; resolves to the new job's id. */
async function render(page, scene, { width, height, spp, integrator }) {
  const before = await page.locator(".job").count();
  await page.selectOption("#render-scene", scene);
  await page.fill("#render-width", String(width));
  await page.fill("#render-height", String(height));
  await page.fill("#render-spp", String(spp));
  await page.selectOption("#render-integrator", integrator);
  await page.click("#render-submit");
  await page.waitForFunction((n) => document.querySelectorAll(".job").length > n, before);
  return page.locator(".job").first().getAttribute("data-id");
}

async function waitRendered(page, job, width, height) {
  const card = page.locator(`.job[data-id="${job}"]`);
  await card.locator('img.render').waitFor({ timeout: 60_000 });
  await page.waitForFunction(({ job, width, height }) => {
    const img = document.querySelector(`.job[data-id="${job}"] img.render`);
    return img && img.complete && img.naturalWidth === width && img.naturalHeight === height;
  }, { job, width, height });
  check((await card.getAttribute("data-state")) === "succeeded", "the job succeeded");
  check((await card.locator(".percent").textContent()) === "100%", "its progress is 100%");
}

/** Without a token: the demo scenes, both kinds of upload, a render, a cancel, a delete. */
async function openServer(browser, dir) {
  const server = await startServer(["--demo"], dir);
  try {
    await checkHeaders(server.url, false);
    const t = await openPage(browser, server.url);
    const { page } = t;
    await page.locator("#main").waitFor();
    check(await page.locator("#token-form").isHidden(), "no token asked for");
    // The three demo scenes have thumbnails too.
    await page.waitForFunction(() => document.querySelectorAll(".scene").length >= 3);
    await uploadByDrop(page, "Triangle.glb", EVIL);
    await page.waitForFunction((evil) => [...document.querySelectorAll(".scene .name")]
      .some((n) => n.textContent === evil), EVIL);
    const evil = await page.evaluate((evil) => {
      const n = [...document.querySelectorAll(".scene .name")].find((n) => n.textContent === evil);
      return { children: n.children.length, injected: document.querySelectorAll('img[src="x"]').length };
    }, EVIL);
    check(evil.children === 0 && evil.injected === 0, `a markup name shows as text: ${JSON.stringify(evil)}`);
    // Its thumbnail first (a thumbnail request in flight would fail on the deleted scene).
    await waitThumbnails(page, 4);
    // Another client deletes the markup-named scene: its card goes from the page.
    const evilId = await sceneId(page, EVIL);
    check((await fetch(`${server.url}/v1/scenes/${evilId}`, { method: "DELETE" })).status === 204,
      "the markup-named scene is deleted");
    await page.waitForFunction((id) => !document.querySelector(`.scene[data-id="${id}"]`), evilId,
      { timeout: 30_000 });
    await uploadByInput(page, "OrientationTest.glb");
    await page.waitForFunction(() =>
      document.getElementById("upload-status").textContent === "Uploaded OrientationTest.glb.");
    await waitThumbnails(page, 4);
    const fox = await sceneId(page, "Fox.glb");
    check(fox && (await page.locator(`.scene[data-id="${fox}"] .id`).textContent()) === fox.slice(0, 12),
      "a scene shows the first 12 characters of its id");
    check((await page.locator(`.scene[data-id="${fox}"] .meta`).textContent()).endsWith(" triangles"),
      "a scene shows its triangle count");

    const done = await render(page, fox, { width: 320, height: 240, spp: 2, integrator: "primary" });
    await waitRendered(page, done, 320, 240);

    // A long render: its live progress comes from its events; then it is cancelled.
    const box = await sceneId(page, "Box.glb");
    const long = await render(page, box, { width: 1600, height: 1200, spp: 256, integrator: "path" });
    const card = page.locator(`.job[data-id="${long}"]`);
    await page.waitForFunction((job) => {
      const c = document.querySelector(`.job[data-id="${job}"]`);
      return c.dataset.state === "running" && c.querySelector("progress").value > 0;
    }, long, { timeout: 30_000 });
    check(t.requests.some((u) => u.endsWith(`/v1/jobs/${long}/events`)), "the page follows the job's events");
    if (SCREENSHOT) {
      fs.mkdirSync(path.dirname(SCREENSHOT), { recursive: true });
      await page.screenshot({ path: SCREENSHOT, fullPage: true });
    }
    check(await card.locator(".delete").isHidden(), "a running job has no delete button");
    await card.locator(".cancel").click();
    await page.waitForFunction((job) =>
      document.querySelector(`.job[data-id="${job}"]`).dataset.state === "cancelled", long);
    check(await card.locator(".cancel").isHidden(), "a cancelled job has no cancel button");
    await card.locator(".delete").click();
    await card.waitFor({ state: "detached" });
    check((await fetch(`${server.url}/v1/jobs/${long}`)).status === 404, "the deleted job is gone");

    // A scene another client uploads appears without changing the user's choice.
    await page.selectOption("#render-scene", fox);
    const other = await (await fetch(`${server.url}/v1/scenes?name=other-client.glb`, {
      method: "POST",
      headers: { "Content-Type": "model/gltf-binary" },
      body: fs.readFileSync(path.join(SCENES, "Triangle.glb")),
    })).json();
    await page.locator(`#render-scene option[value="${other.id}"]`).waitFor({ state: "attached", timeout: 30_000 });
    check((await page.locator("#render-scene").inputValue()) === fox, "the render form keeps the user's scene");

    // Six unfinished jobs at once: the page follows at most three event streams, so its
    // other calls still get a connection (a cancel answers at once).
    const spec = JSON.stringify({ width: 1600, height: 1200, spp: 256, integrator: "path" });
    const many = [];
    for (let i = 0; i < 6; i++) {
      const r = await fetch(`${server.url}/v1/scenes/${box}/render`, {
        method: "POST", headers: { "Content-Type": "application/json" }, body: spec,
      });
      check(r.status === 202, `render ${i} accepted: ${r.status}`);
      many.push((await r.json()).id);
    }
    await page.waitForFunction((ids) => ids.every((id) => document.querySelector(`.job[data-id="${id}"]`)),
      many, { timeout: 30_000 });
    for (const id of many) {
      await page.locator(`.job[data-id="${id}"] .cancel`).click();
      await page.waitForFunction((job) =>
        document.querySelector(`.job[data-id="${job}"]`).dataset.state === "cancelled", id, { timeout: 10_000 });
    }
    await finish(t);
  } catch (e) {
    e.message += `\nserver log:\n${server.log()}`;
    throw e;
  } finally {
    await server.stop();
  }
}

/** With --token-file: the page asks for the token and sends it with every call. */
async function tokenServer(browser, dir) {
  fs.mkdirSync(dir, { recursive: true });
  const tokens = path.join(dir, "tokens");
  fs.writeFileSync(tokens, `${TOKEN}\n`);
  const server = await startServer(["--token-file", tokens], dir);
  try {
    await checkHeaders(server.url, true);
    const t = await openPage(browser, server.url);
    const { page } = t;
    await page.locator("#token-form").waitFor();
    check(await page.locator("#main").isHidden(), "nothing shown before the token");
    await page.fill("#token", TOKEN);
    await page.click("#token-form button[type=submit]");
    await page.locator("#main").waitFor();
    await uploadByInput(page, "Box.glb");
    await waitThumbnails(page, 1);
    const box = await sceneId(page, "Box.glb");
    const job = await render(page, box, { width: 64, height: 48, spp: 1, integrator: "normals" });
    await waitRendered(page, job, 64, 48);
    check(await page.evaluate(() => sessionStorage.getItem("rayd-token")) !== null, "the token is in sessionStorage");
    // A reload keeps the token (same tab) and shows the data again.
    await page.reload();
    await page.locator(`.job[data-id="${job}"] img.render`).waitFor();
    check(await page.locator("#token-form").isHidden(), "no second prompt after a reload");
    check(!t.requests.some((u) => u.includes(TOKEN)), "the token is never in a URL");
    await finish(t);
  } catch (e) {
    e.message += `\nserver log:\n${server.log()}`;
    throw e;
  } finally {
    await server.stop();
  }
}

async function main() {
  check(fs.existsSync(RAYD), `${RAYD} exists (cargo build --release)`);
  const dir = fs.mkdtempSync(path.join(os.tmpdir(), "rayd-page-"));
  const browser = await chromium.launch({
    executablePath: CHROMIUM,
    headless: true,
    args: ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
      "--disable-background-networking", "--disable-component-update", "--disable-sync"],
  });
  try {
    await openServer(browser, path.join(dir, "open"));
    console.log("ok: status page without a token (demo scenes, uploads, render, cancel, delete)");
    await tokenServer(browser, path.join(dir, "token"));
    console.log("ok: status page under --token-file");
  } finally {
    await browser.close();
    fs.rmSync(dir, { recursive: true, force: true });
  }
}

const timer = setTimeout(() => {
  console.error(`status page test: over ${LIMIT_MS / 1000} s`);
  process.exit(1);
}, LIMIT_MS);
main().then(
  () => {
    clearTimeout(timer);
    console.log("status page: all checks passed");
  },
  (e) => {
    console.error(e.stack || e.message);
    process.exit(1);
  },
);

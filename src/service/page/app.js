// The status page of rayd: scenes with thumbnails, jobs with live progress, uploads and
// renders, all through the /v1 API (proto/openapi.yaml).
//
// Rules this file keeps: every piece of data goes into the DOM through textContent or a
// property (never parsed as markup), so a scene named like markup shows as text; the bearer token
// lives in sessionStorage and travels only in the Authorization header (never in a URL),
// which is why job events are read with fetch() and a stream reader instead of
// EventSource (EventSource cannot send headers); images that need the token are fetched
// and shown through object URLs.

const TOKEN_KEY = "rayd-token";
const REFRESH_MS = 10000;
const ENDED = new Set(["succeeded", "failed", "cancelled"]);
// The newest jobs shown (the listing is oldest first: the page reads it to its end).
const SHOWN_JOBS = 200;
// Event streams open at once. A browser keeps six HTTP/1.1 connections to one origin, and
// each stream holds one for as long as its job runs: more streams would leave no
// connection for the page's other calls (a cancel, the refresh). Jobs beyond these are
// updated by the refresh.
const MAX_STREAMS = 3;

const state = {
  auth: "none",
  scenes: new Map(), // id -> { view, card }
  jobs: new Map(), // id -> { view, card, resultLoaded }
  streams: new Map(), // job id -> AbortController
  timer: null,
  refreshError: null, // the message a failed refresh showed, cleared by one that works
};

const $ = (id) => document.getElementById(id);

/** An element with properties and children (strings become text nodes). */
function el(tag, props = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(props)) {
    if (k === "class") e.className = v;
    else if (k === "text") e.textContent = v;
    else if (k.startsWith("data-")) e.setAttribute(k, v);
    else e[k] = v;
  }
  e.append(...children);
  return e;
}

function token() {
  return sessionStorage.getItem(TOKEN_KEY);
}

function authHeaders(extra = {}) {
  const t = token();
  return t ? { ...extra, Authorization: `Bearer ${t}` } : extra;
}

/** A failed call: the status and the problem document's detail. */
class ApiError extends Error {
  constructor(status, detail, retryAfter) {
    super(detail);
    this.status = status;
    this.retryAfter = retryAfter;
  }
}

/** Calls the API with the token; resolves to the response when it is a success. */
async function api(path, { method = "GET", body, type, accept, signal } = {}) {
  const headers = authHeaders(accept ? { Accept: accept } : {});
  if (type) headers["Content-Type"] = type;
  const res = await fetch(path, { method, headers, body, signal, cache: "no-store" });
  if (res.ok) return res;
  let detail = `${method} ${path}: ${res.status} ${res.statusText}`;
  try {
    const p = await res.json();
    if (p && typeof p.detail === "string") detail = p.detail;
  } catch {
    // Not a problem document; the status line says enough.
  }
  if (res.status === 401) needToken(token() ? "The token was refused." : "");
  throw new ApiError(res.status, detail, Number(res.headers.get("Retry-After")) || 1);
}

async function json(path, options) {
  return (await api(path, { accept: "application/json", ...options })).json();
}

function say(text) {
  const m = $("message");
  m.textContent = text;
  m.hidden = !text;
}

function report(err) {
  if (err && err.name === "AbortError") return;
  if (err instanceof ApiError && err.status === 401) return; // the token form says it
  say(err instanceof Error ? err.message : String(err));
}

function short(id) {
  return id.slice(0, 12);
}

// ---- token -------------------------------------------------------------------------

function needToken(why) {
  sessionStorage.removeItem(TOKEN_KEY);
  for (const c of state.streams.values()) c.abort();
  state.streams.clear();
  $("main").hidden = true;
  $("forget-token").hidden = true;
  $("token-form").hidden = false;
  say(why);
  $("token").focus();
}

async function useToken(event) {
  event.preventDefault();
  const value = $("token").value.trim();
  if (!value) return;
  sessionStorage.setItem(TOKEN_KEY, value);
  $("token").value = "";
  $("token-form").hidden = true;
  say("");
  await start();
}

// ---- scenes ------------------------------------------------------------------------

async function loadScenes() {
  const seen = new Set();
  let pageToken = "";
  for (let pages = 0; pages < 20; pages++) {
    const q = new URLSearchParams({ limit: "200" });
    if (pageToken) q.set("page_token", pageToken);
    const page = await json(`/v1/scenes?${q}`);
    for (const s of page.scenes) {
      seen.add(s.id);
      showScene(s, false);
    }
    pageToken = page.next_page_token;
    if (!pageToken) break;
  }
  for (const id of [...state.scenes.keys()]) if (!seen.has(id)) dropScene(id);
}

/** Adds a scene's card and its option in the render form, which it selects when `select`
 * (the user's own upload) or when nothing was selected: a scene that another client
 * uploads never changes the user's choice. */
function showScene(view, select = true) {
  if (state.scenes.has(view.id)) return;
  const name = view.name ?? "(unnamed)";
  const img = el("img", {
    class: "thumb",
    alt: `thumbnail of ${name}`,
    width: 160,
    height: 120,
  });
  const card = el(
    "li",
    { class: "scene", "data-id": view.id },
    img,
    el("div", { class: "name", text: name, title: name }),
    el("code", { class: "id", text: short(view.id), title: view.id }),
    el("div", { class: "meta", text: `${view.triangles} triangles` }),
    el("button", {
      type: "button",
      class: "pick",
      text: "Render…",
      onclick: () => {
        $("render-scene").value = view.id;
        $("render-width").focus();
      },
    }),
  );
  state.scenes.set(view.id, { view, card });
  $("scenes").prepend(card);
  const picker = $("render-scene");
  const chosen = picker.value;
  picker.prepend(el("option", { value: view.id, text: `${name} (${short(view.id)})` }));
  picker.value = select || !chosen ? view.id : chosen;
  loadThumbnail(view.id, img).catch(report);
}

function dropScene(id) {
  const s = state.scenes.get(id);
  if (!s) return;
  const img = s.card.querySelector("img");
  if (img.src.startsWith("blob:")) URL.revokeObjectURL(img.src);
  s.card.remove();
  for (const o of $("render-scene").options) if (o.value === id) o.remove();
  state.scenes.delete(id);
}

/** Fetches a thumbnail (with the token), asking again while it is still being made. */
async function loadThumbnail(id, img) {
  for (let attempt = 0; attempt < 60; attempt++) {
    try {
      const blob = await (await api(`/v1/scenes/${id}/thumbnail`, { accept: "image/png" })).blob();
      img.src = URL.createObjectURL(blob);
      img.classList.add("ready");
      return;
    } catch (err) {
      if (!(err instanceof ApiError && err.status === 409) || !state.scenes.has(id)) {
        img.classList.add("missing");
        img.title = err.message;
        if (err instanceof ApiError && err.status === 422) return;
        throw err;
      }
      await new Promise((r) => setTimeout(r, err.retryAfter * 1000));
    }
  }
}

/** The media type of an upload, from its first bytes (the name may say nothing). */
async function mediaType(file) {
  const head = new Uint8Array(await file.slice(0, 16).arrayBuffer());
  const magic = String.fromCharCode(...head.slice(0, 4));
  if (magic === "glTF") return "model/gltf-binary";
  if (magic === "TRI1") return "application/x-rayd-tri";
  const text = new TextDecoder().decode(head).trimStart();
  if (text.startsWith("{")) return "model/gltf+json";
  const lower = file.name.toLowerCase();
  if (lower.endsWith(".glb")) return "model/gltf-binary";
  if (lower.endsWith(".gltf")) return "model/gltf+json";
  if (lower.endsWith(".tri")) return "application/x-rayd-tri";
  throw new Error(`${file.name}: not a glTF (.glb, .gltf) or TRI1 file`);
}

async function upload(files) {
  const status = $("upload-status");
  for (const file of files) {
    status.textContent = `Uploading ${file.name}…`;
    try {
      const type = await mediaType(file);
      const q = new URLSearchParams({ name: file.name });
      const view = await json(`/v1/scenes?${q}`, { method: "POST", type, body: file });
      showScene(view);
      status.textContent = `Uploaded ${file.name}.`;
    } catch (err) {
      status.textContent = `${file.name} was not uploaded.`;
      report(err);
    }
  }
}

// ---- jobs --------------------------------------------------------------------------

async function loadJobs() {
  let jobs = [];
  let pageToken = "";
  for (let pages = 0; pages < 50; pages++) {
    const q = new URLSearchParams({ limit: "1000" });
    if (pageToken) q.set("page_token", pageToken);
    const page = await json(`/v1/jobs?${q}`);
    jobs = jobs.concat(page.jobs);
    // Only the newest are shown: keep the list short while reading a long one.
    if (jobs.length > 4 * SHOWN_JOBS) jobs = jobs.slice(-SHOWN_JOBS);
    pageToken = page.next_page_token;
    if (!pageToken) break;
  }
  const newest = jobs.sort((a, b) => a.created_at - b.created_at).slice(-SHOWN_JOBS);
  const seen = new Set();
  for (const j of newest) {
    seen.add(j.id);
    showJob(j);
  }
  for (const id of [...state.jobs.keys()]) if (!seen.has(id)) dropJob(id);
}

function sceneName(id) {
  const s = state.scenes.get(id);
  return s ? (s.view.name ?? short(id)) : short(id);
}

function showJob(view) {
  let j = state.jobs.get(view.id);
  if (!j) {
    const r = view.request || {};
    const what =
      view.kind === "render"
        ? `${r.width}×${r.height}, ${r.spp} spp, ${r.integrator}`
        : "trace";
    const card = el(
      "li",
      { class: "job", "data-id": view.id },
      el(
        "div",
        { class: "head" },
        el("code", { class: "id", text: short(view.id), title: view.id }),
        el("span", { class: "kind", text: view.kind }),
        el("span", { class: "scene-name", text: sceneName(view.scene) }),
        el("span", { class: "what", text: what }),
      ),
      el(
        "div",
        { class: "status" },
        el("span", { class: "state" }),
        el("progress", { max: 1, value: 0 }),
        el("span", { class: "percent" }),
        el("button", { type: "button", class: "cancel", text: "Cancel", onclick: () => cancel(view.id) }),
        el("button", { type: "button", class: "delete", text: "Delete", onclick: () => remove(view.id) }),
      ),
      el("p", { class: "error" }),
      el("div", { class: "result" }),
    );
    j = { view, card, resultLoaded: false };
    state.jobs.set(view.id, j);
    $("jobs").prepend(card);
  } else if (state.streams.has(view.id)) {
    return; // its events are fresher than a listing
  }
  updateJob(view);
  if (!ENDED.has(view.state)) follow(view.id);
}

function updateJob(view) {
  const j = state.jobs.get(view.id);
  if (!j) return;
  j.view = view;
  const c = j.card;
  const ended = ENDED.has(view.state);
  c.dataset.state = view.state;
  c.querySelector(".state").textContent = view.state;
  c.querySelector("progress").value = view.progress;
  c.querySelector(".percent").textContent = `${Math.round(view.progress * 100)}%`;
  c.querySelector(".cancel").hidden = ended;
  c.querySelector(".delete").hidden = !ended;
  c.querySelector(".error").textContent = view.error ?? "";
  if (
    view.state === "succeeded" &&
    view.kind === "render" &&
    view.request?.format === "png" &&
    !j.resultLoaded
  ) {
    j.resultLoaded = true;
    loadResult(view).catch(report);
  }
}

async function loadResult(view) {
  const blob = await (await api(`/v1/jobs/${view.id}/result`, { accept: "image/png" })).blob();
  const j = state.jobs.get(view.id);
  if (!j) return;
  const img = el("img", {
    class: "render",
    alt: `render of ${sceneName(view.scene)}`,
    src: URL.createObjectURL(blob),
  });
  j.card.querySelector(".result").replaceChildren(img);
}

function dropJob(id) {
  const j = state.jobs.get(id);
  if (!j) return;
  state.streams.get(id)?.abort();
  state.streams.delete(id);
  for (const img of j.card.querySelectorAll("img")) URL.revokeObjectURL(img.src);
  j.card.remove();
  state.jobs.delete(id);
}

/** Reads one job's Server-Sent Events (fetch + a stream reader, so the token can go in
 * the Authorization header) and shows each state as it comes. */
async function follow(id) {
  if (state.streams.has(id) || state.streams.size >= MAX_STREAMS) return;
  const controller = new AbortController();
  state.streams.set(id, controller);
  try {
    const res = await api(`/v1/jobs/${id}/events`, {
      accept: "text/event-stream",
      signal: controller.signal,
    });
    const reader = res.body.pipeThrough(new TextDecoderStream()).getReader();
    let buffer = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      buffer += value;
      let end;
      while ((end = buffer.search(/\r?\n\r?\n/)) >= 0) {
        const block = buffer.slice(0, end);
        buffer = buffer.slice(end).replace(/^\r?\n\r?\n/, "");
        handleEvent(block);
      }
    }
  } catch (err) {
    report(err);
  } finally {
    if (state.streams.get(id) === controller) state.streams.delete(id);
  }
  // The stream ended early (a server shutting down): the list refresh picks it up.
}

/** One SSE event block: `event:` and `data:` lines; comments (`:`) are keep-alives. */
function handleEvent(block) {
  let event = "message";
  const data = [];
  for (const line of block.split(/\r?\n/)) {
    if (line.startsWith(":")) continue;
    const colon = line.indexOf(":");
    const field = colon < 0 ? line : line.slice(0, colon);
    let value = colon < 0 ? "" : line.slice(colon + 1);
    if (value.startsWith(" ")) value = value.slice(1);
    if (field === "event") event = value;
    else if (field === "data") data.push(value);
  }
  if (event === "job" && data.length) updateJob(JSON.parse(data.join("\n")));
}

async function cancel(id) {
  try {
    const res = await api(`/v1/jobs/${id}`, { method: "DELETE", accept: "application/json" });
    if (res.status === 200) updateJob(await res.json());
  } catch (err) {
    report(err);
  }
}

async function remove(id) {
  try {
    await api(`/v1/jobs/${id}`, { method: "DELETE" });
    dropJob(id);
  } catch (err) {
    if (err instanceof ApiError && err.status === 404) dropJob(id);
    else report(err);
  }
}

async function submitRender(event) {
  event.preventDefault();
  const scene = $("render-scene").value;
  if (!scene) {
    say("Upload a scene first.");
    return;
  }
  const spec = {
    width: Number($("render-width").value),
    height: Number($("render-height").value),
    spp: Number($("render-spp").value),
    integrator: $("render-integrator").value,
    format: $("render-format").value,
  };
  try {
    const view = await json(`/v1/scenes/${scene}/render`, {
      method: "POST",
      type: "application/json",
      body: JSON.stringify(spec),
    });
    say("");
    showJob(view);
  } catch (err) {
    report(err);
  }
}

// ---- start -------------------------------------------------------------------------

async function health() {
  const badge = $("health");
  try {
    const res = await fetch("/readyz", { cache: "no-store" });
    badge.textContent = res.ok ? "ready" : "not ready";
    badge.dataset.ok = String(res.ok);
  } catch {
    badge.textContent = "unreachable";
    badge.dataset.ok = "false";
  }
}

async function refresh() {
  try {
    await health();
    await loadScenes();
    await loadJobs();
    // The server answers again: what the last failed refresh said no longer holds.
    if (state.refreshError !== null && $("message").textContent === state.refreshError) say("");
    state.refreshError = null;
  } catch (err) {
    report(err);
    state.refreshError = $("message").textContent;
  }
}

async function start() {
  $("main").hidden = false;
  $("forget-token").hidden = !token();
  await refresh();
  if (!state.timer) state.timer = setInterval(() => !$("main").hidden && refresh(), REFRESH_MS);
}

function bind() {
  $("token-form").addEventListener("submit", useToken);
  $("forget-token").addEventListener("click", () => needToken(""));
  $("render-form").addEventListener("submit", submitRender);
  $("file").addEventListener("change", (e) => {
    upload([...e.target.files]);
    e.target.value = "";
  });
  const drop = $("drop");
  for (const name of ["dragenter", "dragover"]) {
    drop.addEventListener(name, (e) => {
      e.preventDefault();
      drop.classList.add("over");
    });
  }
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (e) => {
    e.preventDefault();
    drop.classList.remove("over");
    upload([...(e.dataTransfer?.files ?? [])]);
  });
}

async function init() {
  bind();
  const info = await (
    await fetch("/", { headers: { Accept: "application/json" }, cache: "no-store" })
  ).json();
  state.auth = info.auth;
  $("version").textContent = `version ${info.version}`;
  await health();
  if (info.auth === "bearer" && !token()) needToken("");
  else await start();
}

init().catch(report);

/*
 * The volfx viewer: one WebSocket to volfxd (JSON-RPC, one request per text message, an
 * attachment as the binary message after the message that announces it), a frame subscription
 * with this viewer's own camera (orbit, pan, zoom), and a scene editor generated from the
 * Scene schema of rpc.discover. Nothing here is fetched from anywhere but the server.
 */
"use strict";

const $ = (id) => document.getElementById(id);

/* JSON-RPC over the WebSocket. */
class Rpc {
  constructor(url, onNotify, onClose) {
    this.url = url;
    this.onNotify = onNotify;
    this.onClose = onClose;
    this.nextId = 1;
    this.pending = new Map();
    this.awaiting = null; /* A message whose attachment is the next binary message. */
    this.bytes = 0; /* Received, for the bytes a second. */
  }

  open() {
    return new Promise((resolve, reject) => {
      const ws = new WebSocket(this.url);
      ws.binaryType = "arraybuffer";
      this.ws = ws;
      ws.onopen = () => resolve();
      ws.onerror = () => reject(new Error("cannot open " + this.url));
      ws.onclose = (ev) => {
        for (const p of this.pending.values())
          p.reject({ code: 0, message: "connection closed" + (ev.reason ? ": " + ev.reason : "") });
        this.pending.clear();
        this.onClose(ev);
      };
      ws.onmessage = (ev) => this.receive(ev.data);
    });
  }

  close() {
    if (this.ws) this.ws.close();
  }

  receive(data) {
    if (data instanceof ArrayBuffer) {
      this.bytes += data.byteLength;
      const msg = this.awaiting;
      this.awaiting = null;
      if (msg) this.deliver(msg, data);
      return;
    }
    this.bytes += data.length;
    let msg;
    try {
      msg = JSON.parse(data);
    } catch (e) {
      return;
    }
    const body = msg && (msg.result || msg.params);
    if (body && body.attachment && body.attachment.bytes > 0 && body.data === undefined) {
      this.awaiting = msg;
      return;
    }
    this.deliver(msg, null);
  }

  deliver(msg, attachment) {
    if (Array.isArray(msg)) return;
    if (msg.method && msg.id === undefined) {
      this.onNotify(msg.method, msg.params, attachment);
      return;
    }
    const p = this.pending.get(msg.id);
    if (!p) {
      if (msg.error) setMessage(msg.error.message);
      return;
    }
    this.pending.delete(msg.id);
    if (msg.error) p.reject(msg.error);
    else p.resolve(attachment ? { result: msg.result, attachment } : msg.result);
  }

  call(method, params) {
    const id = this.nextId++;
    const req = { jsonrpc: "2.0", id, method };
    if (params !== undefined) req.params = params;
    return new Promise((resolve, reject) => {
      if (!this.ws || this.ws.readyState !== WebSocket.OPEN) {
        reject({ code: 0, message: "not connected" });
        return;
      }
      this.pending.set(id, { resolve, reject });
      this.ws.send(JSON.stringify(req));
    });
  }
}

/* --- small vector helpers for the camera --- */
const sub3 = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add3 = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const mul3 = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const len3 = (a) => Math.hypot(a[0], a[1], a[2]);
const cross3 = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
  a[0] * b[1] - a[1] * b[0]];
const norm3 = (a) => mul3(a, 1 / (len3(a) || 1));

/* This viewer's camera: an orbit around 'target', kept apart from the scene's camera. */
class Orbit {
  fromCamera(cam) {
    this.target = cam.target.slice();
    const d = sub3(cam.eye, cam.target);
    this.radius = len3(d) || 1;
    this.yaw = Math.atan2(d[0], d[2]);
    this.pitch = Math.asin(Math.max(-1, Math.min(1, d[1] / this.radius)));
  }

  eye() {
    const c = Math.cos(this.pitch);
    return add3(this.target, mul3([Math.sin(this.yaw) * c, Math.sin(this.pitch),
      Math.cos(this.yaw) * c], this.radius));
  }

  rotate(dx, dy) {
    this.yaw -= dx * 0.008;
    this.pitch = Math.max(-1.45, Math.min(1.45, this.pitch + dy * 0.008));
  }

  pan(dx, dy) {
    const fwd = norm3(sub3(this.target, this.eye()));
    const right = norm3(cross3(fwd, [0, 1, 0]));
    const up = cross3(right, fwd);
    const s = this.radius * 0.0016;
    this.target = add3(this.target, add3(mul3(right, -dx * s), mul3(up, dy * s)));
  }

  zoom(delta) {
    this.radius = Math.max(0.05, Math.min(1e5, this.radius * Math.exp(delta * 0.0012)));
  }

  camera() {
    const r = (v) => v.map((x) => Math.round(x * 1e5) / 1e5);
    return { eye: r(this.eye()), target: r(this.target) };
  }
}

/* --- the viewer's state --- */
const state = {
  rpc: null,
  schema: null, /* components.schemas.Scene */
  scene: "main",
  doc: null,
  sub: null, /* The subscription whose frames are drawn. */
  subScene: null, /* Its scene. */
  oldSub: null, /* The one it replaces, drawn until the new one's first frame. */
  orbit: new Orbit(),
  viewChanged: false,
  resubscribing: false,
  frames: 0,
  lastWork: 0,
  lastFrame: null,
  drawing: false,
};

/* For tests and benchmarks: frame counts and the time of the last frame drawn. */
window.volfxViewer = { state, framesDrawn: 0, lastDrawn: 0, onDrawn: null };

function setMessage(text) {
  $("message").textContent = text || "";
}

function setStatus(on, text) {
  const s = $("status");
  s.textContent = text;
  s.className = "status " + (on ? "on" : "off");
}

/* --- frames --- */
function frameSize() {
  const [w, h] = $("size").value.split("x").map(Number);
  return { width: w, height: h };
}

/* The frame format of the stream: JPEG, about a seventh of PNG's bytes and fast to encode. */
const STREAM = { format: "jpeg", quality: 85, mime: "image/jpeg" };

/*
 * Keeps one subscription of the shown scene with this viewer's view: the first call
 * subscribes, later ones (orbit, pan, zoom, size, fps) move it with frames.update, which takes
 * effect from the next frame without a gap; a new scene subscribes anew and the old stream is
 * drawn until the new one's first frame.
 */
async function subscribe() {
  const rpc = state.rpc;
  if (!rpc || state.resubscribing) {
    state.viewChanged = true;
    return;
  }
  state.resubscribing = true;
  state.viewChanged = false;
  const size = frameSize();
  const canvas = $("view");
  if (canvas.width !== size.width || canvas.height !== size.height) {
    canvas.width = size.width;
    canvas.height = size.height;
  }
  const fps = Math.max(1, Math.min(60, Number($("fps-target").value) || 30));
  const view = { width: size.width, height: size.height, fps, camera: state.orbit.camera() };
  try {
    if (state.sub !== null && state.subScene === state.scene) {
      await rpc.call("frames.update", Object.assign({ id: state.sub }, view));
    } else {
      const r = await rpc.call("frames.subscribe", Object.assign(
        { scene: state.scene, format: STREAM.format, quality: STREAM.quality }, view));
      if (state.sub !== null) {
        if (state.oldSub !== null) rpc.call("frames.unsubscribe", { id: state.oldSub }).catch(() => {});
        state.oldSub = state.sub;
      }
      state.sub = r.id;
      state.subScene = state.scene;
    }
  } catch (e) {
    setMessage("frames: " + e.message);
  }
  state.resubscribing = false;
  if (state.viewChanged) requestAnimationFrame(subscribe);
}

function onFrame(params, bytes) {
  if (!bytes || (params.id !== state.sub && params.id !== state.oldSub)) return;
  if (params.id === state.sub && state.oldSub !== null) {
    state.rpc.call("frames.unsubscribe", { id: state.oldSub }).catch(() => {});
    state.oldSub = null;
  }
  state.frames++;
  state.lastWork = params.work_ms;
  $("frame").textContent = params.frame;
  $("time").textContent = Number(params.time).toFixed(2);
  $("dropped").textContent = params.dropped;
  state.lastFrame = bytes;
  if (!state.drawing) drawLatest();
}

/* Draws the newest frame; frames that arrive while one is decoded replace each other. */
async function drawLatest() {
  state.drawing = true;
  while (state.lastFrame) {
    const bytes = state.lastFrame;
    state.lastFrame = null;
    try {
      const img = await createImageBitmap(new Blob([bytes], { type: STREAM.mime }));
      const canvas = $("view");
      canvas.getContext("2d").drawImage(img, 0, 0, canvas.width, canvas.height);
      img.close();
      const v = window.volfxViewer;
      v.framesDrawn++;
      v.lastDrawn = performance.now();
      if (v.onDrawn) v.onDrawn();
    } catch (e) {
      setMessage("a frame did not decode: " + e.message);
    }
  }
  state.drawing = false;
}

/* fps, render time and bytes a second, once a second. */
setInterval(() => {
  $("fps").textContent = state.frames;
  state.frames = 0;
  $("work").textContent = state.lastWork ? state.lastWork.toFixed(1) : "–";
  const rpc = state.rpc;
  $("rate").textContent = rpc ? (rpc.bytes / 1024).toFixed(0) : "0";
  if (rpc) rpc.bytes = 0;
}, 1000);

/* --- the view: orbit, pan, zoom --- */
function viewMoved() {
  if (!state.viewChanged) {
    state.viewChanged = true;
    requestAnimationFrame(() => {
      if (state.viewChanged) subscribe();
    });
  }
}

function bindView() {
  const canvas = $("view");
  let drag = null;
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button === 2 };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX;
    drag.y = e.clientY;
    if (drag.pan) state.orbit.pan(dx, dy);
    else state.orbit.rotate(dx, dy);
    viewMoved();
  });
  canvas.addEventListener("pointerup", () => (drag = null));
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    state.orbit.zoom(e.deltaY);
    viewMoved();
  }, { passive: false });
  $("reset-view").addEventListener("click", () => {
    if (state.doc) state.orbit.fromCamera(state.doc.camera);
    subscribe();
  });
  $("size").addEventListener("change", subscribe);
  $("fps-target").addEventListener("change", subscribe);
}

/* --- the scene editor, generated from the schema --- */
const COLOR_NAMES = /(^|_)(color|colour|background|albedo|tint)$/;

function isColor(name, s) {
  return s.type === "array" && s.minItems === 3 && s.maxItems === 3 && s.items &&
    s.items.type === "number" && (COLOR_NAMES.test(name) || /RGB/.test(s.description || ""));
}

const toSrgb = (x) => {
  x = Math.max(0, Math.min(1, x));
  return x <= 0.0031308 ? 12.92 * x : 1.055 * Math.pow(x, 1 / 2.4) - 0.055;
};
const toLinear = (x) => (x <= 0.04045 ? x / 12.92 : Math.pow((x + 0.055) / 1.055, 2.4));

function rgbToHex(c) {
  return "#" + c.map((x) => Math.round(toSrgb(x) * 255).toString(16).padStart(2, "0")).join("");
}

function hexToRgb(h) {
  return [1, 3, 5].map((i) => Math.round(toLinear(parseInt(h.substr(i, 2), 16) / 255) * 1e4) / 1e4);
}

function lower(s) {
  return s.minimum !== undefined ? s.minimum : s.exclusiveMinimum;
}

function upper(s) {
  return s.maximum !== undefined ? s.maximum : s.exclusiveMaximum;
}

function el(tag, props, children) {
  const e = document.createElement(tag);
  Object.assign(e, props || {});
  for (const c of children || []) e.append(c);
  return e;
}

/* Sends edits of one path as they come, the newest one waiting while one is in flight. */
const edits = new Map();

function sendEdit(path, value) {
  let e = edits.get(path);
  if (!e) edits.set(path, (e = { busy: false, next: undefined }));
  e.next = { value };
  if (!e.busy) flushEdit(path, e);
}

async function flushEdit(path, e) {
  while (e.next) {
    const { value } = e.next;
    e.next = undefined;
    e.busy = true;
    try {
      await state.rpc.call("scene.set", { scene: state.scene, path, value });
      setAt(state.doc, path, value);
      showFieldError(path, null);
    } catch (err) {
      showFieldError((err.data && err.data.path) || path, err.message, path);
    }
    e.busy = false;
  }
}

function setAt(doc, path, value) {
  const keys = path.split(".");
  let o = doc;
  for (const k of keys.slice(0, -1)) o = o[k];
  o[keys[keys.length - 1]] = value;
}

function getAt(doc, path) {
  return path.split(".").reduce((o, k) => (o == null ? undefined : o[k]), doc);
}

/* Shows 'message' beside the field at 'path' (the deepest field the path lies in), or clears
 * the errors of 'path'. */
function showFieldError(path, message, sentPath) {
  const spans = [...document.querySelectorAll("[data-error-for]")];
  if (!message) {
    for (const s of spans)
      if (s.dataset.errorFor === path) {
        s.textContent = "";
        s.previousElementSibling.querySelectorAll(".bad").forEach((x) => x.classList.remove("bad"));
      }
    return;
  }
  let best = null;
  for (const s of spans) {
    const p = s.dataset.errorFor;
    if ((path === p || path.startsWith(p + ".")) && (!best || p.length > best.dataset.errorFor.length))
      best = s;
  }
  if (!best && sentPath) best = spans.find((s) => s.dataset.errorFor === sentPath);
  if (!best) {
    setMessage(message);
    return;
  }
  best.textContent = message;
  best.previousElementSibling.querySelectorAll("input, select").forEach((x) => x.classList.add("bad"));
}

function field(label, path, control, s) {
  const row = el("div", { className: "field" });
  const l = el("label", { textContent: label, title: (s.description || "") +
    (s["x-unit"] ? " (" + s["x-unit"] + ")" : "") });
  const ctl = el("div", { className: "ctl" }, [control].flat());
  row.append(l, ctl, el("span", { className: "error" }));
  row.lastChild.dataset.errorFor = path;
  return row;
}

function numberInput(s, value, integer) {
  const input = el("input", { type: "number", value: value === undefined ? "" : value });
  if (integer) input.step = 1;
  else input.step = "any";
  return input;
}

/* A number as shown in a small box: at most four decimals. */
const short = (x) => Math.round(x * 1e4) / 1e4;

/* One control for the value at 'path' described by schema 's'. */
function control(name, path, s, value) {
  const t = s.type;
  if (s.enum) {
    const sel = el("select", {}, s.enum.map((v) => el("option", { value: v, textContent: v })));
    sel.value = value;
    sel.dataset.path = path;
    sel.addEventListener("change", () => sendEdit(path, sel.value));
    return field(name, path, sel, s);
  }
  if (t === "boolean") {
    const box = el("input", { type: "checkbox", checked: !!value });
    box.dataset.path = path;
    box.addEventListener("change", () => sendEdit(path, box.checked));
    return field(name, path, box, s);
  }
  if (t === "number" || t === "integer") {
    const lo = lower(s), hi = upper(s);
    const num = numberInput(s, value, t === "integer");
    num.dataset.path = path;
    num.addEventListener("change", () => {
      if (num.value === "") return;
      const v = Number(num.value);
      if (range) range.value = v;
      sendEdit(path, v);
    });
    let range = null;
    if (lo !== undefined && hi !== undefined && hi - lo <= 1e6) {
      range = el("input", { type: "range", min: lo, max: hi,
        step: t === "integer" ? 1 : (hi - lo) / 1000, value });
      range.dataset.path = path;
      range.addEventListener("input", () => {
        const v = t === "integer" ? Math.round(Number(range.value))
          : Math.round(Number(range.value) * 1e6) / 1e6;
        num.value = v;
        sendEdit(path, v);
      });
    }
    return field(name, path, range ? [range, num] : num, s);
  }
  if (t === "string") {
    const text = el("input", { type: "text", value: value === undefined ? "" : value });
    text.dataset.path = path;
    text.addEventListener("change", () => sendEdit(path, text.value));
    return field(name, path, text, s);
  }
  if (t === "array" && isColor(name, s)) {
    const pick = el("input", { type: "color", value: rgbToHex(value || [0, 0, 0]) });
    pick.dataset.path = path;
    const nums = (value || [0, 0, 0]).map((x) => el("input", { type: "number", value: short(x),
      step: "any", className: "vec" }));
    pick.addEventListener("input", () => {
      const c = hexToRgb(pick.value);
      nums.forEach((n, i) => (n.value = c[i]));
      sendEdit(path, c);
    });
    for (const n of nums)
      n.addEventListener("change", () => {
        const c = nums.map((x) => Number(x.value));
        pick.value = rgbToHex(c);
        sendEdit(path, c);
      });
    return field(name, path, [pick, ...nums], s);
  }
  if (t === "array" && s.items && (s.items.type === "number" || s.items.type === "integer") &&
      s.maxItems && s.maxItems <= 4) {
    const nums = (value || []).map((x) => el("input", { type: "number", value: short(x),
      step: s.items.type === "integer" ? 1 : "any", className: "vec" }));
    for (const n of nums)
      n.addEventListener("change", () => sendEdit(path, nums.map((x) => Number(x.value))));
    nums.forEach((n, i) => (n.dataset.path = path + "." + i));
    return field(name, path, nums, s);
  }
  if (t === "array" && s.items && s.items.type === "object") return list(name, path, s, value || []);
  if (t === "object" && s.properties) return group(name, path, s, value || {});
  /* Anything else: its JSON, edited as text. */
  const text = el("input", { type: "text", value: JSON.stringify(value === undefined ? null : value) });
  text.dataset.path = path;
  text.addEventListener("change", () => {
    let v;
    try {
      v = JSON.parse(text.value);
    } catch (e) {
      showFieldError(path, "not JSON: " + e.message);
      return;
    }
    sendEdit(path, v);
  });
  return field(name, path, text, s);
}

function group(name, path, s, value, open) {
  const d = el("details", { open: !!open }, [el("summary", { textContent: name })]);
  for (const [k, sub] of Object.entries(s.properties))
    d.append(control(k, path ? path + "." + k : k, sub, value[k]));
  return d;
}

/* An array of objects: one group per element, with add and remove. */
function list(name, path, s, items) {
  const d = el("details", {}, [el("summary", { textContent: name + " (" + items.length + ")" })]);
  items.forEach((item, i) => {
    const label = [i, item.id, item.shape || item.type].filter((x) => x !== undefined).join(" · ");
    const g = group(label, path + "." + i, s.items, item);
    const remove = el("button", { type: "button", className: "small danger", textContent: "Remove" });
    remove.addEventListener("click", async () => {
      const rest = items.filter((_, j) => j !== i);
      try {
        await state.rpc.call("scene.set", { scene: state.scene, path, value: rest });
        await loadScene();
      } catch (err) {
        showFieldError(path, err.message);
      }
    });
    g.insertBefore(el("div", { className: "item-tools" }, [remove]), g.children[1]);
    d.append(g);
  });
  const add = el("button", { type: "button", className: "small", textContent: "Add " + name });
  add.addEventListener("click", async () => {
    const item = items.length ? JSON.parse(JSON.stringify(items[items.length - 1])) : {};
    if (item.id !== undefined) item.id = item.id + "-" + (items.length + 1);
    try {
      await state.rpc.call("scene.set", { scene: state.scene, path: path + "." + items.length,
        value: item });
      await loadScene();
    } catch (err) {
      showFieldError(path, err.message);
    }
  });
  const row = el("div", { className: "field" }, [el("span"), el("div", { className: "ctl" }, [add]),
    el("span", { className: "error" })]);
  row.lastChild.dataset.errorFor = path;
  d.append(row);
  return d;
}

function buildForm() {
  const form = $("form");
  const open = new Set([...form.querySelectorAll("details[open] > summary")].map((s) => s.textContent));
  form.textContent = "";
  const s = state.schema;
  for (const [k, sub] of Object.entries(s.properties)) {
    const c = control(k, k, sub, state.doc[k]);
    if (c.tagName === "DETAILS" && (open.has(c.firstChild.textContent) ||
        (!open.size && (k === "render" || k === "light")))) c.open = true;
    form.append(c);
  }
}

/* --- scenes --- */
async function refreshScenes() {
  const r = await state.rpc.call("scene.list");
  const ul = $("scene-list");
  ul.textContent = "";
  for (const sc of r.scenes) {
    const li = el("li", {}, [el("span", { textContent: sc.name }),
      el("span", { className: "meta", textContent: (sc.playing ? "playing" : "paused") +
        " · frame " + sc.frame })]);
    li.dataset.scene = sc.name;
    if (sc.name === state.scene) li.className = "current";
    li.addEventListener("click", () => selectScene(sc.name));
    ul.append(li);
  }
}

async function loadScene() {
  state.doc = await state.rpc.call("scene.get", { scene: state.scene });
  $("scene-name").textContent = state.scene;
  buildForm();
}

async function selectScene(name) {
  state.scene = name;
  try {
    await loadScene();
    state.orbit.fromCamera(state.doc.camera);
    await subscribe();
    await refreshScenes();
    $("scene-error").textContent = "";
  } catch (e) {
    $("scene-error").textContent = e.message;
  }
}

function bindScenes() {
  const guard = (fn) => async () => {
    $("scene-error").textContent = "";
    try {
      await fn();
    } catch (e) {
      $("scene-error").textContent = e.message;
    }
  };
  $("create").addEventListener("click", guard(async () => {
    const name = $("create-name").value.trim();
    const params = { name };
    if ($("preset").value) params.preset = $("preset").value;
    await state.rpc.call("scene.create", params);
    await selectScene(name);
  }));
  $("delete").addEventListener("click", guard(async () => {
    await state.rpc.call("scene.delete", { name: state.scene });
    state.sub = state.oldSub = null;
    const r = await state.rpc.call("scene.list");
    await selectScene(r.scenes.length ? r.scenes[0].name : "main");
  }));
  $("save").addEventListener("click", guard(async () => {
    const r = await state.rpc.call("scene.save", { scene: state.scene, file: $("file").value });
    setMessage("saved " + r.file + " (" + r.bytes + " bytes)");
  }));
  $("load").addEventListener("click", guard(async () => {
    await state.rpc.call("scene.load", { scene: state.scene, file: $("file").value });
    await loadScene();
  }));
  $("reload").addEventListener("click", guard(loadScene));
  const sim = (method, params) => guard(async () => {
    const r = await state.rpc.call(method, Object.assign({ scene: state.scene }, params || {}));
    if (r.frame !== undefined) $("frame").textContent = r.frame;
    await refreshScenes();
  });
  $("play").addEventListener("click", sim("sim.play"));
  $("pause").addEventListener("click", sim("sim.pause"));
  $("step").addEventListener("click", sim("sim.step", { steps: 1 }));
}

/* --- connecting --- */
async function connect() {
  if (state.rpc) state.rpc.close();
  state.sub = state.oldSub = null;
  $("token-error").textContent = "";
  setMessage("");
  const url = (location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws";
  const rpc = new Rpc(url, (method, params, bytes) => {
    if (method === "frames") onFrame(params, bytes);
    else if (method === "frames.ended") {
      if (params.id === state.sub) state.sub = null;
      if (params.id === state.oldSub) state.oldSub = null;
      setMessage("the stream ended: " + params.reason);
    }
  }, (ev) => {
    if (state.rpc === rpc) {
      setStatus(false, "disconnected");
      state.rpc = null;
      if (ev.reason) setMessage("closed: " + ev.reason);
    }
  });
  state.rpc = rpc;
  try {
    await rpc.open();
    const token = $("token").value;
    if (token) await rpc.call("auth", { token });
    const info = await rpc.call("server.info");
    setStatus(true, "connected · " + info.opencl.device.slice(0, 40));
    const doc = await rpc.call("rpc.discover");
    state.schema = doc.components.schemas.Scene;
    const presets = await rpc.call("scene.presets");
    const sel = $("preset");
    sel.length = 1;
    for (const p of presets.presets) sel.append(el("option", { value: p, textContent: p }));
    const list = await rpc.call("scene.list");
    const names = list.scenes.map((s) => s.name);
    await selectScene(names.includes(state.scene) ? state.scene : names[0]);
  } catch (e) {
    if (e.code === -32001) {
      $("token-error").textContent = e.message;
      setStatus(false, "not authorized");
    } else {
      setMessage(e.message);
      setStatus(false, "disconnected");
    }
  }
}

window.addEventListener("DOMContentLoaded", () => {
  bindView();
  bindScenes();
  $("connect").addEventListener("click", connect);
  $("token").addEventListener("keydown", (e) => {
    if (e.key === "Enter") connect();
  });
  const saved = new URLSearchParams(location.hash.slice(1)).get("token");
  if (saved) $("token").value = saved;
  connect();
});

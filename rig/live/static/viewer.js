// rig live viewer: frames from /ws drawn on a canvas, the viewpoint sent back. Plain JS, no build step.
// Wire format: rig/live/protocol.py. State for tests and debugging: window.rigLive and document.body.dataset
// (framesDrawn, lastSet, lastViewpoint, requestedViewpoint, seq, seqAnswered, viewer, connection, health,
// banner). The view shows the newest viewpoint asked for when seq == seqAnswered and
// lastViewpoint == requestedViewpoint.
(() => {
  "use strict";

  const MAGIC = [0x52, 0x4c, 0x56, 0x46]; // "RLVF"
  const VERSION = 1;
  const HEADER_LEN = 32;
  const SEND_EVERY_MS = 50; // viewpoint messages at most 20 per second while dragging
  const YAW_PER_PX = 0.3, PITCH_PER_PX = 0.3, PITCH_LIMIT = 89; // degrees (the server clamps further)
  const ZOOM_MIN = 0.1, ZOOM_MAX = 10, ZOOM_PER_WHEEL = 0.0015;

  const $ = (id) => document.getElementById(id);
  const body = document.body;
  const canvas = $("view");
  const ctx = canvas.getContext("2d");
  const slider = $("slider");

  // --- the address: ?token= goes into memory (and the cookie the server set), out of the address bar
  const params = new URLSearchParams(location.search);
  const token = params.get("token");
  if (token !== null) {
    params.delete("token");
    const rest = params.toString();
    history.replaceState(null, "", location.pathname + (rest ? "?" + rest : "") + location.hash);
  }

  // --- the viewpoint this page asks for
  const state = { t: 0.5, yaw: 0, pitch: 0, zoom: 1, preset: null };
  const num = (text, lo, hi) => {
    const v = Number(text);
    return text !== null && text !== "" && Number.isFinite(v) ? Math.min(hi, Math.max(lo, v)) : null;
  };
  if (num(params.get("t"), 0, 1) !== null) state.t = num(params.get("t"), 0, 1);
  if (params.get("preset")) state.preset = params.get("preset");
  if (num(params.get("yaw"), -180, 180) !== null) state.yaw = num(params.get("yaw"), -180, 180);
  if (num(params.get("pitch"), -PITCH_LIMIT, PITCH_LIMIT) !== null) state.pitch = num(params.get("pitch"), -PITCH_LIMIT, PITCH_LIMIT);
  if (num(params.get("zoom"), ZOOM_MIN, ZOOM_MAX) !== null) state.zoom = num(params.get("zoom"), ZOOM_MIN, ZOOM_MAX);

  const live = (window.rigLive = {
    state,
    viewer: null,
    presets: [],
    framesDrawn: 0,
    lastSet: null,
    lastViewpoint: null,
    requestedViewpoint: null, // the id the server gave this page's newest viewpoint message
    seq: 0, // of the newest viewpoint message sent; replies echo it
    seqAnswered: 0, // of the newest viewpoint message answered (applied or refused)
    viewpointsSent: 0,
    lastStatus: null,
    errors: [],
    drawTimes: [],
    // [r, g, b, a] of the canvas pixel at (fx, fy) in 0..1 of its size (default: the centre)
    pixel(fx = 0.5, fy = 0.5) {
      const x = Math.min(canvas.width - 1, Math.floor(fx * canvas.width));
      const y = Math.min(canvas.height - 1, Math.floor(fy * canvas.height));
      return Array.from(ctx.getImageData(x, y, 1, 1).data);
    },
  });

  function viewpointMessage() {
    const m = { type: "viewpoint" };
    if (state.preset !== null) m.preset = state.preset;
    else m.t = state.t;
    if (state.yaw !== 0 || state.pitch !== 0 || state.zoom !== 1) {
      m.yaw = state.yaw;
      m.pitch = state.pitch;
      m.zoom = state.zoom;
    }
    return m;
  }

  // --- connection
  let ws = null;
  let retryMs = 500;

  function send(message) {
    if (ws && ws.readyState === WebSocket.OPEN) {
      ws.send(JSON.stringify(message));
      return true;
    }
    return false;
  }

  let lastSentAt = -Infinity;
  let pendingTimer = null;
  function flushViewpoint() {
    if (pendingTimer !== null) clearTimeout(pendingTimer);
    pendingTimer = null;
    lastSentAt = performance.now();
    const seq = live.seq + 1;
    if (send({ ...viewpointMessage(), seq })) {
      live.seq = seq;
      live.viewpointsSent += 1;
      body.dataset.seq = String(seq);
      body.dataset.viewpointsSent = String(live.viewpointsSent);
    }
  }
  function sendViewpoint() {
    // throttled: at once if the last was long enough ago, else once when it is (with the newest state)
    const wait = lastSentAt + SEND_EVERY_MS - performance.now();
    if (wait <= 0) flushViewpoint();
    else if (pendingTimer === null) pendingTimer = setTimeout(flushViewpoint, wait);
  }

  function setConnection(kind, text) {
    body.dataset.connection = kind;
    const pill = $("connection");
    pill.textContent = text;
    pill.className = "pill " + kind;
  }

  function connect() {
    const url = new URL("ws", location.href);
    url.protocol = location.protocol === "https:" ? "wss:" : "ws:";
    url.search = "";
    url.hash = "";
    if (token !== null) url.searchParams.set("token", token);
    const sock = new WebSocket(url.href);
    sock.binaryType = "arraybuffer";
    ws = sock;
    setConnection("connecting", "connecting…");
    sock.onopen = () => {
      if (ws !== sock) return;
      retryMs = 500;
      setConnection("open", "live");
      if (banner.dataset.kind === "connection") hideBanner();
      flushViewpoint(); // the page's viewpoint, also after a reconnect
    };
    sock.onmessage = (ev) => {
      if (ws !== sock) return;
      if (typeof ev.data === "string") onText(ev.data);
      else onFrame(ev.data, sock);
    };
    sock.onclose = (ev) => {
      if (ws !== sock) return;
      setConnection("closed", "disconnected");
      showBanner(`connection to the server lost (${ev.code}): reconnecting…`, "connection");
      setTimeout(connect, retryMs);
      retryMs = Math.min(retryMs * 2, 5000);
    };
  }

  // --- messages
  function onText(text) {
    let m;
    try {
      m = JSON.parse(text);
    } catch (e) {
      console.warn("rig live: not JSON from the server", e);
      return;
    }
    switch (m.type) {
      case "hello":
        live.viewer = m.viewer;
        body.dataset.viewer = String(m.viewer);
        $("viewer-id").textContent = `viewer ${m.viewer}`;
        live.presets = Array.isArray(m.presets) ? m.presets : [];
        renderPresets();
        break;
      case "status":
        renderStatus(m);
        break;
      case "viewpoint":
        if (m.seq === live.seq) {
          // the newest message applied (replies to older ones, sent while dragging, are passed over)
          live.requestedViewpoint = m.viewpoint;
          live.seqAnswered = m.seq;
          body.dataset.requestedViewpoint = String(m.viewpoint);
          body.dataset.seqAnswered = String(m.seq);
        }
        break;
      case "error":
        if (m.seq === live.seq) {
          live.seqAnswered = m.seq;
          body.dataset.seqAnswered = String(m.seq);
        }
        live.errors.push(m.message);
        if (live.errors.length > 20) live.errors.shift();
        showNotice(m.message);
        break;
      default:
        break;
    }
  }

  function unpack(buf) {
    if (buf.byteLength < HEADER_LEN) throw new Error(`frame message too short (${buf.byteLength} bytes)`);
    const dv = new DataView(buf);
    for (let i = 0; i < 4; i++) if (dv.getUint8(i) !== MAGIC[i]) throw new Error("not a frame message");
    const version = dv.getUint16(4, true);
    const headerLen = dv.getUint16(6, true);
    if (version !== VERSION) throw new Error(`frame message version ${version} is not supported`);
    if (headerLen < HEADER_LEN || headerLen > buf.byteLength) throw new Error(`bad frame header length ${headerLen}`);
    return {
      set: Number(dv.getBigUint64(8, true)),
      viewpoint: dv.getUint32(16, true),
      captureNs: dv.getBigInt64(24, true),
      jpeg: new Uint8Array(buf, headerLen),
    };
  }

  // frames are decoded and drawn in arrival order; each is acknowledged once drawn (or failed), which
  // gives the server the credit for the next one
  let drawing = Promise.resolve();
  function onFrame(buf, sock) {
    drawing = drawing.then(() => drawFrame(buf, sock)).catch((e) => console.warn("rig live:", e));
  }

  async function drawFrame(buf, sock) {
    let f;
    try {
      f = unpack(buf);
    } catch (e) {
      showNotice(e.message);
      return;
    }
    try {
      const bitmap = await createImageBitmap(new Blob([f.jpeg], { type: "image/jpeg" }));
      if (canvas.width !== bitmap.width || canvas.height !== bitmap.height) {
        canvas.width = bitmap.width;
        canvas.height = bitmap.height;
      }
      ctx.drawImage(bitmap, 0, 0);
      bitmap.close();
      live.framesDrawn += 1;
      live.lastSet = f.set;
      live.lastViewpoint = f.viewpoint;
      const now = performance.now();
      live.drawTimes.push(now);
      while (live.drawTimes.length && now - live.drawTimes[0] > 2000) live.drawTimes.shift();
      body.dataset.framesDrawn = String(live.framesDrawn);
      body.dataset.lastSet = String(f.set);
      body.dataset.lastViewpoint = String(f.viewpoint);
      $("waiting").hidden = true;
    } catch (e) {
      console.warn("rig live: a frame could not be decoded", e);
    } finally {
      if (sock === ws && sock.readyState === WebSocket.OPEN) {
        sock.send(JSON.stringify({ type: "ack", set: f.set, viewpoint: f.viewpoint }));
      }
    }
  }

  // --- banner (health, connection) and notices (refused messages)
  const banner = $("banner");
  function showBanner(text, kind) {
    banner.textContent = text;
    banner.dataset.kind = kind;
    banner.className = "banner " + kind;
    banner.hidden = false;
    body.dataset.banner = text;
  }
  function hideBanner() {
    banner.hidden = true;
    banner.textContent = "";
    banner.dataset.kind = "";
    body.dataset.banner = "";
  }
  let noticeTimer = null;
  function showNotice(text) {
    const el = $("notice");
    el.textContent = text;
    el.hidden = false;
    clearTimeout(noticeTimer);
    noticeTimer = setTimeout(() => (el.hidden = true), 4000);
  }

  // --- status panel
  const fmt = (v) => {
    if (v === null || v === undefined) return "–";
    if (typeof v === "number") return Number.isInteger(v) ? String(v) : v.toFixed(1);
    if (typeof v === "boolean") return v ? "yes" : "no";
    return String(v);
  };
  const ORDER = ["fps_in", "fps_out", "latency_ms", "ms", "model_ms", "sets_in", "sets_dropped", "drops", "cameras", "trigger"];
  const SKIP = new Set(["type", "health", "viewer", "viewers", "error"]);

  function flatten(label, value, rows, depth) {
    if (value !== null && typeof value === "object" && !Array.isArray(value)) {
      if (depth >= 3) {
        rows.push([label, JSON.stringify(value)]);
        return;
      }
      for (const [k, v] of Object.entries(value)) flatten(label ? `${label} ${k}` : k, v, rows, depth + 1);
      return;
    }
    if (Array.isArray(value)) {
      const scalar = value.every((v) => v === null || typeof v !== "object");
      rows.push([label, scalar ? value.map(fmt).join(", ") : `${value.length}`]);
      return;
    }
    const bad = (label.endsWith(" ok") && value === false) || (label.endsWith("connected") && value === false);
    rows.push([label, fmt(value), bad]);
  }

  function localFps() {
    const times = live.drawTimes;
    const now = performance.now();
    const recent = times.filter((t) => now - t <= 2000);
    return recent.length / 2;
  }

  function renderStatus(s) {
    live.lastStatus = s;
    // The size the model renders at (a CPU runs a smaller model than a GPU): said beside the view,
    // as the canvas scales it to fit.
    const size = s.model && s.model.sizes ? s.model.sizes.output : null;
    if (size) $("render-size").textContent = `rendered at ${size}`;
    const rows = [];
    const health = s.health || null;
    if (health) rows.push(["health", health.ok === false ? "FAULT" : "ok", health.ok === false]);
    if (s.error) rows.push(["error", String(s.error), true]);
    const keys = Object.keys(s).filter((k) => !SKIP.has(k));
    const first = ORDER.filter((k) => keys.includes(k));
    for (const k of first) flatten(k, s[k], rows, 0);
    rows.push(["drawn here (fps)", localFps().toFixed(1)]);
    rows.push(["frames drawn here", String(live.framesDrawn)]);
    if (Array.isArray(s.viewers)) {
      rows.push(["viewers", String(s.viewers.length)]);
      const me = s.viewers.find((v) => v && v.id === live.viewer);
      if (me) {
        for (const [k, v] of Object.entries(me)) if (k !== "id" && typeof v !== "object") rows.push([`this viewer ${k}`, fmt(v)]);
        adoptClamped(me);
      }
    } else if (s.viewers !== undefined) {
      rows.push(["viewers", fmt(s.viewers)]);
    }
    for (const k of keys) if (!first.includes(k)) flatten(k, s[k], rows, 0);

    const tbody = $("status").tBodies[0];
    const fresh = document.createElement("tbody");
    for (const [label, value, bad] of rows) {
      const tr = fresh.insertRow();
      if (bad) tr.className = "bad";
      tr.insertCell().textContent = label.replaceAll("_", " ");
      tr.insertCell().textContent = value;
    }
    tbody.replaceWith(fresh);

    if (health && health.ok === false) {
      const messages = Array.isArray(health.messages) && health.messages.length ? health.messages : ["the rig reports a fault"];
      showBanner(messages.join(" · "), "health");
      body.dataset.health = "fault";
    } else if (health) {
      if (banner.dataset.kind === "health") hideBanner();
      body.dataset.health = "ok";
    }
  }

  // the engine clamps orbit and zoom: once it has applied this page's last message (and the user is
  // not dragging), the controls show what it rendered, so a drag back acts at once
  function adoptClamped(me) {
    const v = me.viewpoint;
    if (!v || typeof v !== "object" || me.viewpoint_id !== live.requestedViewpoint || drag || pendingTimer !== null) return;
    let changed = false;
    for (const k of ["yaw", "pitch", "zoom"]) {
      if (typeof v[k] === "number" && Number.isFinite(v[k]) && Math.abs(v[k] - state[k]) > 1e-9) {
        state[k] = v[k];
        changed = true;
      }
    }
    if (changed) showOrbit();
  }

  // --- presets
  function renderPresets() {
    const box = $("presets");
    box.replaceChildren();
    const sorted = [...live.presets].sort((a, b) => (a.kind === "source" ? 0 : 1) - (b.kind === "source" ? 0 : 1));
    for (const p of sorted) {
      if (!p || typeof p.name !== "string") continue;
      const b = document.createElement("button");
      b.type = "button";
      b.dataset.preset = p.name;
      b.dataset.kind = p.kind || "";
      b.append(p.name);
      const kind = document.createElement("span");
      kind.className = "kind";
      kind.textContent = p.kind || "";
      b.append(kind);
      b.addEventListener("click", () => choosePreset(p));
      box.append(b);
    }
    if (!box.children.length) box.textContent = "none";
    markPreset();
  }
  function markPreset() {
    for (const b of $("presets").querySelectorAll("button")) b.classList.toggle("active", b.dataset.preset === state.preset);
  }
  function choosePreset(p) {
    state.preset = p.name;
    state.yaw = 0;
    state.pitch = 0;
    state.zoom = 1;
    if (typeof p.t === "number") setSlider(p.t);
    markPreset();
    showOrbit();
    flushViewpoint();
  }

  // --- slider
  function setSlider(t) {
    state.t = t;
    slider.value = String(t);
    $("slider-value").textContent = t.toFixed(3);
  }
  slider.addEventListener("input", () => {
    state.preset = null;
    markPreset();
    setSlider(Number(slider.value));
    sendViewpoint();
  });
  slider.addEventListener("change", () => flushViewpoint()); // the final position, unthrottled

  // --- orbit: drag = yaw/pitch, wheel = zoom
  function showOrbit() {
    $("yaw").textContent = state.yaw.toFixed(1);
    $("pitch").textContent = state.pitch.toFixed(1);
    $("zoom").textContent = state.zoom.toFixed(2);
  }
  const box = $("view-box");
  let drag = null;
  box.addEventListener("pointerdown", (ev) => {
    if (ev.button !== 0) return;
    drag = { x: ev.clientX, y: ev.clientY };
    box.setPointerCapture(ev.pointerId);
    box.classList.add("dragging");
  });
  box.addEventListener("pointermove", (ev) => {
    if (!drag) return;
    const dx = ev.clientX - drag.x, dy = ev.clientY - drag.y;
    drag = { x: ev.clientX, y: ev.clientY };
    if (!dx && !dy) return;
    state.yaw = ((((state.yaw + dx * YAW_PER_PX + 180) % 360) + 360) % 360) - 180;
    state.pitch = Math.max(-PITCH_LIMIT, Math.min(PITCH_LIMIT, state.pitch - dy * PITCH_PER_PX));
    showOrbit();
    sendViewpoint();
  });
  const endDrag = (ev) => {
    if (!drag) return;
    drag = null;
    box.classList.remove("dragging");
    if (box.hasPointerCapture(ev.pointerId)) box.releasePointerCapture(ev.pointerId);
    flushViewpoint();
  };
  box.addEventListener("pointerup", endDrag);
  box.addEventListener("pointercancel", endDrag);
  box.addEventListener(
    "wheel",
    (ev) => {
      ev.preventDefault();
      state.zoom = Math.max(ZOOM_MIN, Math.min(ZOOM_MAX, state.zoom * Math.exp(-ev.deltaY * ZOOM_PER_WHEEL)));
      showOrbit();
      sendViewpoint();
    },
    { passive: false },
  );
  $("reset-view").addEventListener("click", () => {
    state.yaw = 0;
    state.pitch = 0;
    state.zoom = 1;
    showOrbit();
    flushViewpoint();
  });

  setSlider(state.t);
  showOrbit();
  connect();
})();

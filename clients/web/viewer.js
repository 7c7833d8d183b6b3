// fingertrack web viewer: subscribes to one hand's stream (protocol v1, JSON) and draws the 26
// OpenXR joints, the finger angles and the gesture events. The functions exported here are pure
// or take their WebSocket class as an argument, so tests run them in Node against a real service;
// the page glue at the bottom only runs in a browser.

export const FINGERS = ["thumb", "index", "middle", "ring", "little"];

/** Bones as pairs of OpenXR joint names: wrist -> metacarpal -> ... -> tip for every finger. */
export function bones() {
  const out = [["wrist", "palm"]];
  for (const f of FINGERS) {
    const chain = ["wrist", `${f}_metacarpal`, `${f}_proximal`]
      .concat(f === "thumb" ? [`${f}_distal`] : [`${f}_intermediate`, `${f}_distal`])
      .concat([`${f}_tip`]);
    for (let i = 1; i < chain.length; i++) out.push([chain[i - 1], chain[i]]);
  }
  return out;
}

/**
 * Orthographic view of a point p (OpenXR stage space: right-handed, +Y up, metres) around `center`,
 * camera turned by `yaw` about +Y then tilted by `pitch` (radians), `scale` pixels per metre,
 * onto a width x height canvas (x right, y down). Returns [x, y, depth] (depth: larger is nearer).
 */
export function project(p, center, yaw, pitch, scale, width, height) {
  const dx = p[0] - center[0], dy = p[1] - center[1], dz = p[2] - center[2];
  const cy = Math.cos(yaw), sy = Math.sin(yaw);
  const x1 = cy * dx + sy * dz, z1 = -sy * dx + cy * dz;          // about +Y
  const cp = Math.cos(pitch), sp = Math.sin(pitch);
  const y2 = cp * dy - sp * z1, z2 = sp * dy + cp * z1;           // about the camera's x axis
  return [width / 2 + scale * x1, height / 2 - scale * y2, z2];
}

/** One line per finger with its joint angles in degrees (rounded) and estimator mode. */
export function angleLines(frame) {
  const deg = (r) => (r === undefined || r === null ? "  -" : String(Math.round((r * 180) / Math.PI)).padStart(4));
  return FINGERS.filter((f) => frame.fingers && frame.fingers[f]).map((f) => {
    const a = frame.fingers[f];
    const joints = f === "thumb" ? `mcp ${deg(a.mcp)} ip ${deg(a.ip)}` : `mcp ${deg(a.mcp)} pip ${deg(a.pip)} dip ${deg(a.dip)}`;
    return `${f.padEnd(6)} ${joints}  ${a.mode || ""}`;
  });
}

/** A gesture event as a log line. */
export function eventLine(ev) {
  return `t=${ev.t.toFixed(3)}  ${ev.gesture} ${ev.event}  (confidence ${ev.confidence.toFixed(2)})`;
}

/** The stream URL for a service base URL (http[s]:// or ws[s]://), session and viewer token. */
export function streamUrl(base, session, token) {
  const b = base.replace(/\/+$/, "").replace(/^http:/, "ws:").replace(/^https:/, "wss:");
  const q = token ? `?token=${encodeURIComponent(token)}` : "";
  return `${b}/v1/stream/${encodeURIComponent(session)}${q}`;
}

/**
 * Why the service refuses this token for reading sessions (the stream's roles), or null. A
 * WebSocket whose handshake is refused only reports close code 1006, the same as a network
 * failure, so after a connection that never opened the service is asked over REST.
 */
export async function refusal(fetchFn, base, token) {
  try {
    const http = base.replace(/\/+$/, "").replace(/^ws:/, "http:").replace(/^wss:/, "https:");
    const r = await fetchFn(`${http}/v1/sessions`, { headers: token ? { Authorization: `Bearer ${token}` } : {} });
    if (r.status !== 401 && r.status !== 403) return null;
    const body = await r.json().catch(() => ({}));
    return `HTTP ${r.status}: ${body.detail || "refused"}`;
  } catch (err) {
    return null;                                  // unreachable: a network problem, retried
  }
}

/**
 * Subscribe and stay subscribed to `session`: `handlers.frame(msg)`, `.gesture(msg)`,
 * `.error(msg)`, `.status(text)`, `.refused(reason)`. Reconnects with back-off (0.2 s doubling to
 * 5 s) to the same session; a refusal (bad token or role, or a close with 1008) is reported once
 * and not retried. `WebSocketClass` and `fetchFn`: the browser's (or Node's) WebSocket and fetch.
 * Returns { close() }.
 */
export function subscribe(WebSocketClass, fetchFn, base, session, token, handlers, backoff = { initial: 0.2, max: 5 }) {
  const url = streamUrl(base, session, token);
  let delay = backoff.initial, closed = false, ws = null, timer = null;
  const status = (t) => handlers.status && handlers.status(t);
  const refused = (why) => { closed = true; status(`refused: ${why}`); if (handlers.refused) handlers.refused(why); };
  function connect() {
    let opened = false, ended = false;
    ws = new WebSocketClass(url);
    ws.onopen = () => { opened = true; delay = backoff.initial; status("connected"); };
    ws.onmessage = (e) => {
      let msg;
      try { msg = JSON.parse(e.data); } catch (err) { status(`unreadable message: ${err.message}`); return; }
      const h = handlers[msg.type];
      if (h) h(msg);
    };
    // a failed handshake fires "error" and, depending on the implementation, "close" or not
    // (Node 20's experimental WebSocket does not): whichever comes first ends this connection
    const end = async (code, reason) => {
      if (ended || closed) return;
      ended = true;
      if (code === 1008) return refused(reason || "policy");
      if (!opened) {
        const why = await refusal(fetchFn, base, token);
        if (closed) return;
        if (why) return refused(why);
      }
      status(`disconnected (code ${code}); retrying in ${delay.toFixed(1)} s`);
      timer = setTimeout(connect, delay * 1000);
      delay = Math.min(delay * 2, backoff.max);
    };
    ws.onerror = () => { if (!opened) end(1006, ""); };
    ws.onclose = (e) => end(e.code, e.reason);
  }
  connect();
  return { close() { closed = true; clearTimeout(timer); if (ws) ws.close(); } };
}

/** The session the page opens when none is named: the glove's and the watcher's default. */
export const DEFAULT_SESSION = "default";

/** The session and token a URL hash carries (`#session=NAME&token=TOKEN`); each null when absent. */
export function readHash(hash) {
  const p = new URLSearchParams(String(hash || "").replace(/^#/, ""));
  return { session: p.get("session"), token: p.get("token") };
}

/** The hash that names a session and nothing else: a token never goes into the address. */
export function hashFor(session) {
  return `#session=${encodeURIComponent(session)}`;
}

/**
 * What the page says about its subscription. `connection`: the subscriber's own state ("connecting",
 * "connected", "disconnected ...", "refused: ..."); `summary`: the session's entry in /v1/sessions
 * (null until known); `frames`: frames received on this page for this session; `frameAgeS`:
 * seconds since the last one (null before the first); `staleS`: after how long without a frame the
 * stream counts as stalled. Returns { state, text }, state one of "offline", "refused", "connected"
 * (nothing known yet), "waiting" (for a source), "starting" (a source, no frame yet), "stalled",
 * "live". Frames that keep coming prove a source, whatever an older summary said.
 */
export function sessionState(connection, summary, frames, frameAgeS, staleS = 2) {
  if (connection.startsWith("refused")) return { state: "refused", text: connection };
  if (connection !== "connected") return { state: "offline", text: connection };
  if (frames > 0 && frameAgeS !== null && frameAgeS <= staleS) return { state: "live", text: "live" };
  if (summary && summary.sources === 0) {
    return { state: "waiting", text: frames > 0 ? "connected; the source has left, waiting for a source"
                                                : "connected; waiting for a source (no glove is streaming to this session)" };
  }
  if (frames === 0) return summary ? { state: "starting", text: "connected; a source is connected, waiting for its first frame" }
                                    : { state: "connected", text: "connected" };
  return { state: "stalled", text: `connected; no frame for ${Math.floor(frameAgeS)} s` };
}

/** One line per session of /v1/sessions: { name, text, current }. */
export function sessionItems(list, current) {
  const plural = (n, word) => `${n} ${word}${n === 1 ? "" : "s"}`;
  return list.map((s) => ({
    name: s.session,
    current: s.session === current,
    text: `${s.hand} hand, ${plural(s.sources, "source")}, ${plural(s.subscribers, "viewer")}, ${plural(s.frames_out, "frame")} sent`,
  }));
}

/**
 * Every joint angle of one hand (radians, as sent) over the last `windowS` seconds of stream time,
 * at most `maxPoints` frames. Series are keyed "finger.joint" in the order they first appear; a
 * joint missing from a frame is NaN there. A source whose clock goes back (a new source) starts a new
 * history.
 */
export class AngleHistory {
  constructor(windowS = 10, maxPoints = 2000) {
    this.windowS = windowS;
    this.maxPoints = maxPoints;
    this.clear();
  }

  clear() {
    this.t = [];
    this.series = new Map();
  }

  push(frame) {
    if (this.t.length && frame.t < this.t[this.t.length - 1]) this.clear();
    const n = this.t.length;
    this.t.push(frame.t);
    for (const f of FINGERS) {
      for (const [joint, value] of Object.entries((frame.fingers || {})[f] || {})) {
        if (typeof value !== "number") continue;
        const key = `${f}.${joint}`;
        if (!this.series.has(key)) this.series.set(key, new Array(n).fill(NaN));
        this.series.get(key).push(value);
      }
    }
    for (const values of this.series.values()) if (values.length === n) values.push(NaN);
    const tEnd = frame.t;
    let drop = 0;
    while (drop < this.t.length - 1 && (this.t.length - drop > this.maxPoints || this.t[drop] < tEnd - this.windowS)) drop++;
    if (drop) {
      this.t.splice(0, drop);
      for (const values of this.series.values()) values.splice(0, drop);
    }
  }
}

/**
 * The plot of an AngleHistory in a box { x, y, w, h } (pixels, y down): time runs from
 * (last t - windowS) at the left edge to the last t at the right edge; angles in degrees from `lo`
 * at the bottom to `hi` at the top, where [lo, hi] is [-10, 100] widened to whole tens around the
 * data. Returns { lo, hi, tEnd, lines: [{ key, finger, joint, points }] }, a point [x, y] or null
 * where the joint was missing (the line breaks there).
 */
export function plotLines(timeline, box) {
  const deg = (r) => (r * 180) / Math.PI;
  let lo = -10, hi = 100;
  for (const values of timeline.series.values()) {
    for (const v of values) {
      if (Number.isNaN(v)) continue;
      lo = Math.min(lo, Math.floor(deg(v) / 10) * 10);
      hi = Math.max(hi, Math.ceil(deg(v) / 10) * 10);
    }
  }
  const tEnd = timeline.t.length ? timeline.t[timeline.t.length - 1] : 0;
  const x = (t) => box.x + (box.w * (t - (tEnd - timeline.windowS))) / timeline.windowS;
  const y = (r) => box.y + (box.h * (hi - deg(r))) / (hi - lo);
  const lines = [];
  for (const [key, values] of timeline.series) {
    const [finger, joint] = key.split(".");
    lines.push({ key, finger, joint, points: values.map((v, i) => (Number.isNaN(v) ? null : [x(timeline.t[i]), y(v)])) });
  }
  return { lo, hi, tEnd, lines };
}

// ---- page glue (browser only) ------------------------------------------------------------------
// The canvases are drawn only when something changed (a frame, the view turned or zoomed); the
// token lives in this tab's sessionStorage and in memory, never in the address: a token given in
// the hash is read once and taken out of it.
if (typeof document !== "undefined") {
  const $ = (id) => document.getElementById(id);
  const TOKEN_KEY = "fingertrack.viewer.token";
  const POLL_S = 2;                                       // how often /v1/sessions is asked
  const COLORS = { thumb: "#d62728", index: "#1f77b4", middle: "#2ca02c", ring: "#9467bd", little: "#e67e00" };
  const DASHES = { mcp: [], pip: [7, 3], ip: [7, 3], dip: [2, 3] };
  const canvas = $("hand3d"), ctx = canvas.getContext("2d");
  const plot = $("plot"), pctx = plot.getContext("2d");
  const view = { yaw: 0.6, pitch: 0.35, scale: 1400 };
  const timeline = new AngleHistory(10, 2000);
  const log = [];
  let session = DEFAULT_SESSION, token = "", sub = null, drag = null, pending = false;
  let connection = "not connected", summary = null, frames = 0, lastFrameAt = null, last = null, polling = null;

  const storeToken = (t) => { token = t || ""; try { sessionStorage.setItem(TOKEN_KEY, token); } catch (err) { /* memory only */ } };
  try { token = sessionStorage.getItem(TOKEN_KEY) || ""; } catch (err) { token = ""; }

  /** Takes session and token from the hash; a token is stored and removed from the address bar. */
  function takeHash() {
    const h = readHash(location.hash);
    if (h.token !== null) {
      storeToken(h.token);
      // replaceState: the address with the token leaves no entry in the tab's history
      window.history.replaceState(null, "", location.pathname + location.search + (h.session ? hashFor(h.session) : ""));
    }
    return h.session;
  }

  function showStatus() {
    const age = lastFrameAt === null ? null : (performance.now() - lastFrameAt) / 1000;
    const s = sessionState(connection, summary, frames, age);
    const el = $("status");
    if (el.textContent !== s.text) el.textContent = s.text;
    el.dataset.state = s.state;
    const hand = last ? last.hand : summary && summary.sources > 0 ? summary.hand : null;
    $("side").textContent = hand ? `${hand} hand` : "-";
    $("current").textContent = session;
  }

  let shownSessions = null;
  function showSessions(list, problem) {
    const ul = $("sessions");
    const key = JSON.stringify([problem, session, sessionItems(list, session)]);
    if (key === shownSessions) return;                 // unchanged: no new layout
    shownSessions = key;
    ul.replaceChildren();
    if (problem) { ul.append(Object.assign(document.createElement("li"), { textContent: problem })); return; }
    if (!list.length) ul.append(Object.assign(document.createElement("li"), { textContent: "no session yet" }));
    for (const item of sessionItems(list, session)) {
      const li = document.createElement("li");
      const a = Object.assign(document.createElement("a"), { href: hashFor(item.name), textContent: item.name });
      if (item.current) li.className = "current";
      li.dataset.session = item.name;
      li.append(a, `: ${item.text}`);
      ul.append(li);
    }
  }

  let asking = false;
  async function poll() {
    if (asking) return;                                // one request at a time, however slow the service
    asking = true;
    try {
      const r = await fetch("/v1/sessions", { headers: token ? { Authorization: `Bearer ${token}` } : {} });
      if (!r.ok) {
        const body = await r.json().catch(() => ({}));
        summary = null;
        showSessions([], `session list refused: HTTP ${r.status}: ${body.detail || r.statusText}`);
      } else {
        const list = await r.json();
        // a session the list does not hold has no source yet: only a source creates one (the
        // service keeps this page's subscription waiting for it)
        summary = list.find((s) => s.session === session) || { session, sources: 0, hand: null };
        showSessions(list, null);
      }
    } catch (err) {
      showSessions([], `session list unavailable: ${err.message}`);
    } finally {
      asking = false;
    }
    showStatus();
  }

  function requestDraw() {
    if (pending) return;
    pending = true;
    requestAnimationFrame(() => { pending = false; drawHand(); drawPlot(); });
  }

  function drawHand() {
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    if (!last) return;
    const j = last.joints, center = j.palm.position;
    const pt = (p) => project(p, center, view.yaw, view.pitch, view.scale, canvas.width, canvas.height);
    ctx.lineWidth = 3;
    ctx.strokeStyle = "#446";
    for (const [a, b] of bones()) {
      if (!j[a] || !j[b]) continue;
      const [x0, y0] = pt(j[a].position), [x1, y1] = pt(j[b].position);
      ctx.beginPath(); ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); ctx.stroke();
    }
    for (const name of Object.keys(j)) {
      const [x, y] = pt(j[name].position);
      ctx.fillStyle = name.endsWith("_tip") ? "#c33" : "#36c";
      ctx.beginPath(); ctx.arc(x, y, 4, 0, 2 * Math.PI); ctx.fill();
    }
    const ray = last.gesture && last.gesture.ray;
    if (ray) {
      const o = ray.origin, d = ray.direction, far = [o[0] + 0.3 * d[0], o[1] + 0.3 * d[1], o[2] + 0.3 * d[2]];
      const [x0, y0] = pt(o), [x1, y1] = pt(far);
      ctx.strokeStyle = "#e90"; ctx.beginPath(); ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); ctx.stroke();
    }
    const g = last.gesture || {};
    $("angles").textContent = angleLines(last).join("\n") +
      `\n\nactive ${g.active || "-"}  grab ${(g.grab_strength ?? 0).toFixed(2)}  pinch ${(g.pinch_strength ?? 0).toFixed(2)}` +
      `\nt=${last.t.toFixed(3)} seq ${last.seq}  optics ${last.status && last.status.optics}`;
  }

  function drawPlot() {
    const box = { x: 40, y: 8, w: plot.width - 48, h: plot.height - 30 };
    pctx.clearRect(0, 0, plot.width, plot.height);
    const p = plotLines(timeline, box);
    pctx.font = "11px system-ui, sans-serif";
    pctx.lineWidth = 1;
    pctx.setLineDash([]);
    pctx.fillStyle = "#666";
    pctx.strokeStyle = "#e4e4e4";
    for (let d = Math.ceil(p.lo / 30) * 30; d <= p.hi; d += 30) {
      const y = box.y + (box.h * (p.hi - d)) / (p.hi - p.lo);
      pctx.beginPath(); pctx.moveTo(box.x, y); pctx.lineTo(box.x + box.w, y); pctx.stroke();
      pctx.fillText(`${d}°`, 4, y + 4);
    }
    for (let s = 0; s <= timeline.windowS; s += 2) {
      const x = box.x + (box.w * (timeline.windowS - s)) / timeline.windowS;
      pctx.fillText(s === 0 ? `t=${p.tEnd.toFixed(1)} s` : `-${s} s`, Math.min(x - 10, plot.width - 60), plot.height - 6);
    }
    pctx.lineWidth = 1.5;
    for (const line of p.lines) {
      pctx.strokeStyle = COLORS[line.finger] || "#000";
      pctx.setLineDash(DASHES[line.joint] || [1, 2]);
      pctx.beginPath();
      let pen = false;
      for (const pt of line.points) {
        if (pt === null) { pen = false; continue; }
        if (pen) pctx.lineTo(pt[0], pt[1]); else pctx.moveTo(pt[0], pt[1]);
        pen = true;
      }
      pctx.stroke();
    }
    pctx.setLineDash([]);
    const keys = p.lines.map((l) => l.key).join(" ");
    const legend = $("legend");
    if (legend.dataset.keys !== keys) {
      legend.dataset.keys = keys;
      legend.replaceChildren(...p.lines.map((l) => {
        const span = Object.assign(document.createElement("span"), { textContent: `${l.finger} ${l.joint}` });
        span.style.color = COLORS[l.finger] || "#000";
        span.style.borderBottom = `2px ${l.joint === "mcp" ? "solid" : l.joint === "dip" ? "dotted" : "dashed"}`;
        return span;
      }));
    }
  }

  /** (Re)subscribe to `session` with the stored token, and keep the session list fresh. */
  function start() {
    if (sub) sub.close();
    last = null; frames = 0; lastFrameAt = null; summary = null; log.length = 0;
    timeline.clear();
    $("events").textContent = "";
    $("angles").textContent = "";
    $("session").value = session;
    connection = "connecting";
    showStatus();
    requestDraw();
    sub = subscribe(WebSocket, fetch.bind(window), location.origin, session, token, {
      frame: (m) => {
        frames += 1; lastFrameAt = performance.now(); last = m; timeline.push(m);
        if (frames === 1 || $("status").dataset.state !== "live") showStatus();
        requestDraw();
      },
      gesture: (m) => { log.unshift(eventLine(m)); log.length = Math.min(log.length, 30); $("events").textContent = log.join("\n"); },
      error: (m) => { $("errors").textContent = `error ${m.code}: ${m.detail}`; },
      status: (t) => {
        connection = t;
        showStatus();
        if (t === "connected") poll();
        if (t.startsWith("refused")) clearInterval(polling);
      },
    });
    clearInterval(polling);
    polling = setInterval(poll, POLL_S * 1000);
    poll();
  }

  /** The session named in the address (or the default), then connect. */
  function fromAddress() {
    session = takeHash() || session;
    start();
  }

  $("form").onsubmit = (e) => {
    e.preventDefault();
    storeToken($("token").value);
    session = $("session").value.trim() || DEFAULT_SESSION;
    const want = hashFor(session);
    if (location.hash !== want) location.hash = want;        // the hashchange handler connects
    else start();
  };
  window.addEventListener("hashchange", fromAddress);
  canvas.onmousedown = (e) => { drag = [e.clientX, e.clientY, view.yaw, view.pitch]; };
  window.onmouseup = () => { drag = null; };
  window.onmousemove = (e) => {
    if (!drag) return;
    view.yaw = drag[2] + (e.clientX - drag[0]) * 0.01;
    view.pitch = Math.max(-1.5, Math.min(1.5, drag[3] + (e.clientY - drag[1]) * 0.01));
    requestDraw();
  };
  canvas.onwheel = (e) => { e.preventDefault(); view.scale *= Math.exp(-e.deltaY * 0.001); requestDraw(); };
  $("token").value = token;
  session = takeHash() || DEFAULT_SESSION;
  $("session").value = session;
  start();
}

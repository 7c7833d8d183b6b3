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

// ---- page glue (browser only) ------------------------------------------------------------------
if (typeof document !== "undefined") {
  const $ = (id) => document.getElementById(id);
  const params = new URLSearchParams(location.hash.slice(1));
  $("session").value = params.get("session") || "right";
  $("token").value = params.get("token") || "";
  const canvas = $("hand"), ctx = canvas.getContext("2d");
  let view = { yaw: 0.6, pitch: 0.35, scale: 1400 }, last = null, sub = null, drag = null;
  const log = [];

  function draw() {
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    if (!last) return;
    const j = last.joints, center = j.palm.position;
    const pt = (name) => project(j[name].position, center, view.yaw, view.pitch, view.scale, canvas.width, canvas.height);
    ctx.lineWidth = 3;
    for (const [a, b] of bones()) {
      if (!j[a] || !j[b]) continue;
      const [x0, y0] = pt(a), [x1, y1] = pt(b);
      ctx.strokeStyle = "#446";
      ctx.beginPath(); ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); ctx.stroke();
    }
    for (const name of Object.keys(j)) {
      const [x, y] = pt(name);
      ctx.fillStyle = name.endsWith("_tip") ? "#c33" : "#36c";
      ctx.beginPath(); ctx.arc(x, y, 4, 0, 2 * Math.PI); ctx.fill();
    }
    const ray = last.gesture && last.gesture.ray;
    if (ray) {
      const o = ray.origin, d = ray.direction, far = [o[0] + 0.3 * d[0], o[1] + 0.3 * d[1], o[2] + 0.3 * d[2]];
      const [x0, y0] = project(o, center, view.yaw, view.pitch, view.scale, canvas.width, canvas.height);
      const [x1, y1] = project(far, center, view.yaw, view.pitch, view.scale, canvas.width, canvas.height);
      ctx.strokeStyle = "#e90"; ctx.beginPath(); ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); ctx.stroke();
    }
    const g = last.gesture || {};
    $("angles").textContent = angleLines(last).join("\n") +
      `\n\nactive ${g.active || "-"}  grab ${(g.grab_strength ?? 0).toFixed(2)}  pinch ${(g.pinch_strength ?? 0).toFixed(2)}` +
      `\nt=${last.t.toFixed(3)} seq ${last.seq}  optics ${last.status && last.status.optics}`;
  }

  function start() {
    if (sub) sub.close();
    last = null; log.length = 0; $("events").textContent = "";
    location.hash = `session=${encodeURIComponent($("session").value)}&token=${encodeURIComponent($("token").value)}`;
    sub = subscribe(WebSocket, fetch.bind(window), location.origin, $("session").value, $("token").value, {
      frame: (m) => { last = m; },
      gesture: (m) => { log.unshift(eventLine(m)); log.length = Math.min(log.length, 30); $("events").textContent = log.join("\n"); },
      error: (m) => { $("status").textContent = `error ${m.code}: ${m.detail}`; },
      status: (t) => { $("status").textContent = t; },
    });
  }
  $("connect").onclick = start;
  canvas.onmousedown = (e) => { drag = [e.clientX, e.clientY, view.yaw, view.pitch]; };
  window.onmouseup = () => { drag = null; };
  window.onmousemove = (e) => {
    if (!drag) return;
    view.yaw = drag[2] + (e.clientX - drag[0]) * 0.01;
    view.pitch = Math.max(-1.5, Math.min(1.5, drag[3] + (e.clientY - drag[1]) * 0.01));
  };
  canvas.onwheel = (e) => { e.preventDefault(); view.scale *= Math.exp(-e.deltaY * 0.001); };
  (function loop() { draw(); requestAnimationFrame(loop); })();
  if (params.get("session")) start();
}

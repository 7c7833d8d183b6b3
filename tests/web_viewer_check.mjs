// Runs the web viewer's module (clients/web/viewer.js) in Node for tests/test_web_viewer.py:
//   node web_viewer_check.mjs pure FRAMES.json          what the viewer computes for those frames
//   node --experimental-websocket web_viewer_check.mjs subscribe URL SESSION TOKEN refused|stdin
//   node web_viewer_check.mjs plot FRAMES.json WINDOW_S MAX_POINTS
//   node web_viewer_check.mjs page
// Prints one JSON object per line.
import { readFileSync } from "node:fs";
import {
  AngleHistory, angleLines, bones, eventLine, hashFor, plotLines, project, readHash, sessionItems, sessionState, streamUrl,
  subscribe,
} from "../clients/web/viewer.js";

const [mode, ...args] = process.argv.slice(2);
const out = (o) => console.log(JSON.stringify(o));

if (mode === "pure") {
  const msgs = JSON.parse(readFileSync(args[0], "utf8"));
  out({ bones: bones(), url: streamUrl("https://example.org:8765/", "right hand", "a b&c") });
  for (const m of msgs) {
    if (m.type === "gesture") { out({ event: eventLine(m) }); continue; }
    const center = m.joints.palm.position;
    const views = [[0, 0], [0.6, 0.35], [-2.0, -1.2]];
    const projected = views.map(([yaw, pitch]) =>
      Object.fromEntries(Object.entries(m.joints).map(([name, j]) => [name, project(j.position, center, yaw, pitch, 1000, 560, 480)])));
    out({ seq: m.seq, lines: angleLines(m), views, projected });
  }
} else if (mode === "subscribe") {
  // UNTIL: "refused" (1 s after the first refusal, to see that none follows) or "stdin" (after the
  // frame whose seq is read from stdin: the last one the Python subscriber got)
  const [url, session, token, until] = args;
  let n = 0, lastSeq = 0, stopAt = null;
  const finish = () => { sub.close(); out({ type: "summary", frames: n }); process.exit(0); };
  const sub = subscribe(WebSocket, fetch, url, session, token, {
    frame: (m) => {
      n += 1; lastSeq = m.seq;
      out({ type: "frame", seq: m.seq, tip: m.joints.index_tip.position });
      if (stopAt !== null && lastSeq >= stopAt) finish();
    },
    gesture: (m) => out({ type: "gesture", gesture: m.gesture, event: m.event }),
    error: (m) => out({ type: "error", code: m.code }),
    status: (t) => { if (t === "connected") out({ type: "connected" }); },
    refused: (why) => { out({ type: "refused", why }); if (until === "refused") setTimeout(finish, 1000); },
  });
  if (until === "stdin") {
    let text = "";
    process.stdin.on("data", (d) => {
      text += d;
      if (!text.includes("\n")) return;
      stopAt = Number(text.trim());
      if (lastSeq >= stopAt) finish();
    });
  }
} else if (mode === "plot") {
  // the angle history of FRAMES.json and its plot
  const frames = JSON.parse(readFileSync(args[0], "utf8"));
  const history = new AngleHistory(Number(args[1]), Number(args[2]));
  for (const f of frames) history.push(f);
  const plot = plotLines(history, { x: 40, y: 8, w: 900, h: 200 });
  out({ t: history.t, lo: plot.lo, hi: plot.hi, tEnd: plot.tEnd, lines: plot.lines });
  history.push({ ...frames[0], t: frames[0].t - 1 });           // a new source whose clock starts earlier
  out({ restarted: history.t });
} else if (mode === "page") {
  // the page's small decisions: the address, the status line, the session list
  const hashes = ["#session=lab%201&token=a%26b", "#session=x", "#token=t", "", "#"].map(readHash);
  out({ hashes, hashFor: hashFor("lab 1"), back: readHash(hashFor("lab 1")) });
  const cases = [
    ["connecting", null, 0, null], ["refused: HTTP 401: no", null, 0, null], ["connected", null, 0, null],
    ["connected", { sources: 0 }, 0, null], ["connected", { sources: 1 }, 0, null], ["connected", { sources: 1 }, 5, 0.1],
    ["connected", { sources: 0 }, 5, 0.1], ["connected", { sources: 0 }, 5, 3.0], ["connected", { sources: 1 }, 5, 3.0],
    ["disconnected (code 1006); retrying in 0.2 s", { sources: 1 }, 5, 0.1],
  ];
  out({ states: cases.map((c) => sessionState(...c)) });
  out({ items: sessionItems([{ session: "a", hand: "left", sources: 1, subscribers: 2, frames_out: 1 },
                             { session: "b", hand: "right", sources: 0, subscribers: 0, frames_out: 0 }], "b") });
}

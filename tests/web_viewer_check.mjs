// Runs the web viewer's module (clients/web/viewer.js) in Node for tests/test_web_viewer.py:
//   node web_viewer_check.mjs pure FRAMES.json          what the viewer computes for those frames
//   node --experimental-websocket web_viewer_check.mjs subscribe URL SESSION TOKEN SECONDS
// Prints one JSON object per line.
import { readFileSync } from "node:fs";
import { angleLines, bones, eventLine, project, streamUrl, subscribe } from "../clients/web/viewer.js";

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
  const [url, session, token, seconds] = args;
  let n = 0;
  const sub = subscribe(WebSocket, fetch, url, session, token, {
    frame: (m) => { n += 1; out({ type: "frame", seq: m.seq, tip: m.joints.index_tip.position }); },
    gesture: (m) => out({ type: "gesture", gesture: m.gesture, event: m.event }),
    error: (m) => out({ type: "error", code: m.code }),
    status: (t) => { if (t === "connected") out({ type: "connected" }); },
    refused: (why) => out({ type: "refused", why }),
  });
  setTimeout(() => { sub.close(); out({ type: "summary", frames: n }); }, 1000 * Number(seconds));
}

// The browser trainer's page: draws what the agent does, sends the person's feedback over a WebSocket.
"use strict";

const token = new URLSearchParams(location.search).get("token");
const wsUrl = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws${token ? "?token=" + encodeURIComponent(token) : ""}`;
const $ = (id) => document.getElementById(id);
let ws = null;
let keys = { good: "/", bad: "z", pause: "p", presence: "h" };
let paused = false;
let here = true;
let given = 0;
let curve = [];
let view = "tetris";

function send(obj) {
  if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(obj));
}

function flash(kind) {
  const f = $("flash");
  f.className = kind;
  setTimeout(() => { f.className = ""; }, 120);
}

function feedback(value) {
  send({ type: "feedback", value: value });
  given += 1;
  $("given").textContent = String(given);
  flash(value > 0 ? "good" : "bad");
}

function drawTetris(f) {
  const c = $("view");
  const rows = f.board.length, cols = f.board[0].length;
  const cell = Math.floor(Math.min(300 / cols, 600 / rows));
  c.width = cols * cell; c.height = rows * cell;
  const g = c.getContext("2d");
  g.fillStyle = "#111"; g.fillRect(0, 0, c.width, c.height);
  const placed = new Set((f.placed || []).map(([r, col]) => r * cols + col));
  for (let r = 0; r < rows; r++) {
    for (let col = 0; col < cols; col++) {
      if (!f.board[r][col]) continue;
      g.fillStyle = placed.has(r * cols + col) ? "#f0c040" : "#5a8fd0";
      g.fillRect(col * cell + 1, (rows - 1 - r) * cell + 1, cell - 2, cell - 2);
    }
  }
  $("score-label").textContent = "Lines";
  $("score").textContent = String(f.lines);
  $("episode").textContent = String(f.episode);
  $("action").textContent = f.action;
}

function disc(g, x, y, r, colour) {
  g.fillStyle = colour; g.beginPath(); g.arc(x, y, r, 0, 2 * Math.PI); g.fill();
}

function arrow(g, [x0, y0], [tx, ty]) {
  const a = Math.atan2(ty - y0, tx - x0), h = 10;
  const x1 = tx - 13 * Math.cos(a), y1 = ty - 13 * Math.sin(a);  // stop at the receiver's edge
  g.strokeStyle = "#ffe040"; g.fillStyle = "#ffe040"; g.lineWidth = 2; g.setLineDash([6, 4]);
  g.beginPath(); g.moveTo(x0, y0); g.lineTo(x1, y1); g.stroke(); g.setLineDash([]);
  g.beginPath(); g.moveTo(x1, y1);
  g.lineTo(x1 - h * Math.cos(a - 0.4), y1 - h * Math.sin(a - 0.4));
  g.lineTo(x1 - h * Math.cos(a + 0.4), y1 - h * Math.sin(a + 0.4));
  g.closePath(); g.fill();
}

function drawKeepaway(f) {
  const c = $("view");
  if (c.width !== 400 || c.height !== 400) { c.width = 400; c.height = 400; }
  const g = c.getContext("2d");
  const [len, wid] = f.region;
  const s = 360 / Math.max(len, wid), ox = 20 + (360 - len * s) / 2, oy = 20 + (360 - wid * s) / 2;
  const px = (p) => [ox + (p[0] + len / 2) * s, oy + (wid / 2 - p[1]) * s];
  g.fillStyle = "#22602f"; g.fillRect(0, 0, c.width, c.height);
  g.strokeStyle = "#eee"; g.lineWidth = 2; g.strokeRect(ox, oy, len * s, wid * s);
  if (f.target >= 0) arrow(g, px(f.ball), px(f.keepers[f.target]));
  f.takers.forEach((p) => { const [x, y] = px(p); disc(g, x, y, 8, "#e03030"); });
  g.font = "bold 11px system-ui, sans-serif"; g.textAlign = "center"; g.textBaseline = "middle";
  f.keepers.forEach((p, i) => {
    const [x, y] = px(p);
    if (i === f.holder) disc(g, x, y, 12, "#ffd700");
    disc(g, x, y, 8, "#3070ff");
    g.fillStyle = "#fff"; g.fillText(String(i + 1), x, y + 0.5);
  });
  const [bx, by] = px(f.ball);
  disc(g, bx, by, 5, "#000"); disc(g, bx, by, 4, "#fff");
  $("score-label").textContent = "Hold time";
  $("score").textContent = `${f.time_s.toFixed(1)} s`;
  $("episode").textContent = String(f.episode);
  $("action").textContent = f.action;
  $("mean-hold").textContent = f.mean_hold_s === null ? "-" : `${f.mean_hold_s.toFixed(1)} s`;
  $("trust").textContent = f.weight === null ? "-" : f.weight.toFixed(2);
  $("speed-unit").textContent = `decisions/s (real time: ${f.real_time})`;
}

function showView(view) {
  if (view !== "keepaway") return;
  document.body.classList.add("keepaway");
  $("help").innerHTML = "Watch the keepers (blue, numbered) keep the ball from the takers (red). Press " +
    '<kbd id="key-good">/</kbd> or <b>Good</b> when they keep it well: holding when the takers are far, ' +
    'passing to an open teammate. Press <kbd id="key-bad">z</kbd> or <b>Bad</b> for passes into a taker ' +
    "or holding on while the takers close in. They learn from you and from how long they keep the ball.";
  $("score-label").textContent = "Hold time";
  $("speed-unit").textContent = "decisions/s";
}

function drawCurve() {
  const c = $("curve"), g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  if (curve.length === 0) return;
  const xs = curve.map((p) => p[0]), ys = curve.map((p) => p[1]);
  const x0 = Math.min(...xs), x1 = Math.max(...xs, x0 + 1), y1 = Math.max(...ys, 1);
  g.strokeStyle = "#2a5ab0"; g.lineWidth = 2; g.beginPath();
  curve.forEach(([x, y], i) => {
    const cx = 10 + ((x - x0) / (x1 - x0)) * (c.width - 20);
    const cy = c.height - 10 - (y / y1) * (c.height - 20);
    if (i === 0) g.moveTo(cx, cy); else g.lineTo(cx, cy);
  });
  g.stroke();
  const last = curve[curve.length - 1];
  $("curve-label").textContent = view === "keepaway"
    ? `seconds the keepers kept the ball per episode (mean of each block of episodes): latest ${last[1].toFixed(1)}, best ${y1.toFixed(1)}`
    : `lines per test game after each round of practice: latest ${last[1].toFixed(1)}, best ${y1.toFixed(1)}`;
}

function showSettings(m) {
  paused = m.paused; here = m.here;
  $("speed").value = String(m.actions_per_s);
  $("speed-value").textContent = String(m.actions_per_s);
  $("pause").firstChild.textContent = paused ? "Resume (" : "Pause (";
  $("presence").firstChild.textContent = here ? "I'm away (" : "I'm here (";
  if (m.curve) { curve = m.curve; drawCurve(); }
}

function onMessage(ev) {
  const m = JSON.parse(ev.data);
  if (m.type === "config") {
    keys = m.keys; view = m.view || "tetris";
    showView(view);
    $("key-good").textContent = keys.good; $("key-bad").textContent = keys.bad;
    $("key-pause").textContent = keys.pause; $("key-presence").textContent = keys.presence;
  } else if (m.type === "settings") showSettings(m);
  else if (m.type === "tetris") { drawTetris(m); $("status").textContent = m.text || ""; }
  else if (m.type === "keepaway") { drawKeepaway(m); $("status").textContent = m.text || ""; }
  else if (m.type === "curve") { curve = m.curve; drawCurve(); }
  else if (m.type === "status") $("status").textContent = m.text;
  else if (m.type === "role") $("status").textContent = m.text;
  else if (m.type === "error") console.warn("server rejected a message:", m.message);
}

function connect() {
  ws = new WebSocket(wsUrl);
  ws.onopen = () => { $("status").textContent = "connected"; };
  ws.onmessage = onMessage;
  ws.onclose = () => {
    $("status").textContent = "disconnected: training goes on without you; reconnecting...";
    setTimeout(connect, 2000);
  };
}

document.addEventListener("keydown", (e) => {
  if (e.repeat || e.target.tagName === "INPUT") return;
  if (e.key === keys.good) feedback(1);
  else if (e.key === keys.bad) feedback(-1);
  else if (e.key === keys.pause) send({ type: "pause", paused: !paused });
  else if (e.key === keys.presence) send({ type: "presence", here: !here });
  else return;
  e.preventDefault();
});
$("good").addEventListener("click", () => feedback(1));
$("bad").addEventListener("click", () => feedback(-1));
$("pause").addEventListener("click", () => send({ type: "pause", paused: !paused }));
$("presence").addEventListener("click", () => send({ type: "presence", here: !here }));
$("speed").addEventListener("change", (e) => send({ type: "speed", actions_per_s: Number(e.target.value) }));
connect();

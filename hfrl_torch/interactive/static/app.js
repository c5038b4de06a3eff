// The browser trainer's page: draws what the agent does, sends the person's presses over a WebSocket, and
// says only what the run confirms: a press counts once the server acknowledges it, and the run's own
// messages say when it is practising, finishing, stopping or has ended.
"use strict";

const token = new URLSearchParams(location.search).get("token");
// this tab's name, kept across reloads (sessionStorage is per tab): the run keeps a reloading teacher's
// place for it, so a reload does not hand teaching to another tab
const tab = sessionStorage.getItem("hfrl-tab") ||
  Array.from(crypto.getRandomValues(new Uint8Array(12)), (b) => b.toString(16).padStart(2, "0")).join("");
sessionStorage.setItem("hfrl-tab", tab);
const wsQuery = new URLSearchParams(token ? { token, tab } : { tab });
// relative to the page, so the same page works at / (train.py) and at /p/<code>/teach/ (a study's proxy)
const wsUrl = new URL("ws", location.href);
wsUrl.protocol = location.protocol === "https:" ? "wss:" : "ws:";
wsUrl.search = wsQuery.toString();
wsUrl.hash = "";
// in a study the page sits under the participant's own path: its end offers "Continue" to the study's page
// instead of the run's paths and commands, and the study's proxy says why it closed (WAIT: try again soon)
const STUDY = location.pathname.includes("/teach/");
const WAIT = 4000, OVER = 4001;
const $ = (id) => document.getElementById(id);
const S = {
  ws: null, connected: false, everConnected: false, failures: 0, ended: null,
  keys: { good: "/", bad: "z", pause: "p", presence: "h" }, view: "tetris", info: {},  // info: the run's config message
  role: "teach", paused: false, here: true, live: true, ending: null, progress: {},
  given: 0, pending: new Map(), nextId: 0, curve: [], frame: null, reaction: 0.3, reconnect: 0, clearTimer: null,
  asked: {},
  refusedHere: new Map(),  // presses this page did not send, by reason (since it was opened)
  closeReason: "",  // in a study: why the study's proxy closed the connection, in the participant's words
};

function send(obj) {
  if (S.ws && S.ws.readyState === WebSocket.OPEN) { S.ws.send(JSON.stringify(obj)); return true; }
  return false;
}

function duration(s) {
  if (s === null || s === undefined || !isFinite(s)) return null;
  s = Math.max(0, Math.round(s));
  if (s < 60) return `${s} s`;
  if (s < 3600) return `${Math.floor(s / 60)} min ${s % 60} s`;
  return `${Math.floor(s / 3600)} h ${Math.round((s % 3600) / 60)} min`;
}

// --- what can be pressed, and what the page says ---

function whyNot() {
  if (S.ended) return "the run has ended";
  if (!S.connected) return "the page is not connected to the run";
  if (S.ending === "finishing") return "the run is finishing and saving";
  if (S.ending) return "the run is stopping";
  if (S.role !== "teach") return "another page is teaching";
  if (!S.here) return "you said you are away";
  if (!S.live) return S.frame ? "the agent is practising on its own" : "the run is starting: nothing to judge yet";
  return null;
}

function leftText() {
  const p = S.progress || {};
  if (p.total === undefined) return "";
  let left;
  if (p.unit === "rounds") left = `${p.left} of ${p.total} practice rounds left`;
  else if (p.unit === "episodes") left = `${p.left} of ${p.total} episodes left`;
  else if (p.unit === "steps") left = `${p.left} of ${p.total} steps left`;
  else left = `${(p.left / 60).toFixed(1)} of ${(p.total / 60).toFixed(1)} simulated minutes left`;
  const t = duration(p.left_s);
  return t === null ? left : `${left}, about ${t} at the current pace`;
}

function statusText() {
  if (S.ended) return "The session has ended: see the summary below.";
  if (!S.connected) {
    if (STUDY && S.closeReason) return S.closeReason;
    if (!S.everConnected) return "Connecting to the run...";
    // one reconnection refused: on this machine that means the run's process is gone, not a network blip
    return S.failures > 1
      ? "The run does not answer: it may have stopped (the terminal says). This page reconnects if it comes back."
      : "Connection to the run lost; trying again... Presses are not counted until it is back." +
        (S.reconnect > 0 ? ` If the run is still going, the agent waits up to ${duration(S.reconnect)} for this page, then goes on without you.` : "");
  }
  if (S.ending === "finishing") return "Finishing: the agent ends this round and saves the run. New presses are not counted.";
  if (S.ending) return "The run is stopping (stopped from the terminal): it saves what you taught. New presses are not counted.";
  if (S.role !== "teach") return "Watching only: another page is teaching.";
  if (!S.here) return `You're away: the agent practises on its own; presses are not counted. ${leftText()}.`;
  if (!S.live && !S.frame) return "The run is starting: the game appears here in a moment. Presses count once it is on screen.";
  if (!S.live) return "Practising on its own between your games; presses are not counted until your next game.";
  if (S.paused) return `Paused. A press now counts for the ${S.view === "tetris" ? "placement" : "moment"} on screen. Press Resume (${S.keys.pause}) to go on.`;
  if (S.view === "gym") return "Judge each step: a press counts for the step on screen a moment before it.";
  return S.view === "tetris"
    ? "Your game: judge each placement. A press counts for the placement on screen a moment before it."
    : "Watching you teach: a press counts for what the keepers did in the last half second.";
}

function coverText() {
  if (S.ended) return "The session has ended.";
  if (!S.connected) {
    if (STUDY && S.closeReason) return S.closeReason;
    return S.everConnected ? "Not connected to the run." : "Connecting...";
  }
  if (S.ending) return S.ending === "finishing" ? "Finishing and saving..." : "The run is stopping...";
  if (!S.here) return `You're away. The agent practises on its own: ${leftText()}. Press I'm here (${S.keys.presence}) to teach again before then.`;
  if (!S.live && !S.frame) return "Starting the run...";
  if (S.view === "tetris" && !S.live) {
    const p = S.progress || {};
    const round = p.total === undefined ? "" : ` (round ${Math.min(p.done + 1, p.total)} of ${p.total})`;
    const over = S.over ? `Game over: ${S.over.lines} line${S.over.lines === 1 ? "" : "s"} in game ${S.over.game}. ` : "";
    return `${over}Practising on its own${round}. Your next game starts when this round ends.`;
  }
  return null;
}

function render() {
  $("status").textContent = statusText();
  const cover = coverText();
  $("cover").hidden = cover === null;
  $("cover-text").textContent = cover || "";
  const canPress = whyNot() === null;
  $("good").disabled = !canPress; $("bad").disabled = !canPress;
  const teach = S.connected && !S.ended && !S.ending && S.role === "teach";
  $("pause").disabled = !teach; $("presence").disabled = !teach; $("finish").disabled = !teach;
  $("speed").disabled = !teach;
  $("pause").firstChild.textContent = S.paused ? "Resume (" : "Pause (";
  $("presence").firstChild.textContent = S.here ? "I'm away (" : "I'm here (";
  $("finish").textContent = S.ending === "finishing" ? "Finishing..." : "Finish and save";
  $("given").textContent = String(S.given);
  const p = S.progress || {};
  if (p.total !== undefined) {
    $("progress").textContent = p.unit === "rounds" || p.unit === "steps"
      ? `${p.done} of ${p.total} done`
      : p.unit === "episodes" ? `${p.done} of ${p.total} episodes`
        : `${(p.done / 60).toFixed(1)} of ${(p.total / 60).toFixed(1)} min`;
  }
}

function lastPress(text, refused) {
  const el = $("last-press");
  el.textContent = text;
  el.classList.toggle("refused", !!refused);
}

// --- presses ---

function flash(kind) {
  const f = $("flash");
  f.className = kind;
  setTimeout(() => { f.className = ""; }, 120);
}

function feedback(value) {
  const why = whyNot();
  const word = value > 0 ? "Good" : "Bad";
  if (why !== null) { refusedHere(why); lastPress(`${word} not counted: ${why}.`, true); return; }
  const id = S.nextId;
  S.nextId = (S.nextId + 1) % 1000000;
  if (!send({ type: "feedback", value: value, id: id })) {
    refusedHere("not connected");
    lastPress(`${word} not counted: not connected.`, true);
    return;
  }
  S.pending.set(id, value);
  flash(value > 0 ? "good" : "bad");
}

function refusedHere(why) {
  S.refusedHere.set(why, (S.refusedHere.get(why) || 0) + 1);
}

function notCountedText(byRun) {
  const here = Array.from(S.refusedHere.values()).reduce((a, b) => a + b, 0);
  if (!byRun && !here) return "";
  const parts = [];
  if (byRun) parts.push(`${byRun} refused by the run (made while away, with nothing to judge on screen, or after the stop)`);
  if (here) {
    const why = Array.from(S.refusedHere, ([reason, n]) => `${n} ${reason}`).join("; ");
    parts.push(`${here} kept back by this page since it was opened (${why})`);
  }
  const n = byRun + here;
  return `${n} more ${n === 1 ? "was" : "were"} not counted: ${parts.join(", and ")}.`;
}

function onAck(m) {
  if (m.message !== "feedback") return;
  S.pending.delete(m.id);
  S.given = m.given;
  const word = m.value > 0 ? "Good" : "Bad";
  const what = m.filed ? m.filed : "this moment";
  lastPress(`${word} → ${what}${m.paused ? " (while paused)" : ""}`, false);
  render();
}

function onError(m) {
  if (m.id !== undefined && m.id >= 0 && S.pending.has(m.id)) {
    const word = S.pending.get(m.id) > 0 ? "Good" : "Bad";
    S.pending.delete(m.id);
    lastPress(`${word} not counted: ${m.message.replace(/^not taken: /, "")}.`, true);
  } else {
    S.asked = {};
    console.warn("the run rejected a message:", m.message);
  }
}

// --- drawing ---

function drawBoard(board, marked, rows) {
  const c = $("view");
  const h = board.length, w = board[0].length;
  const cell = Math.floor(Math.min(300 / w, 600 / h));
  if (c.width !== w * cell || c.height !== h * cell) { c.width = w * cell; c.height = h * cell; }
  const cols = $("columns");  // the numbers the page's words use ("T at column 4"), so a press can be checked
  if (cols.hidden || cols.childElementCount !== w) {
    cols.replaceChildren(...Array.from({ length: w }, (_, i) => {
      const span = document.createElement("span"); span.textContent = String(i + 1); return span;
    }));
    cols.hidden = false;
  }
  const g = c.getContext("2d");
  g.fillStyle = "#111"; g.fillRect(0, 0, c.width, c.height);
  const mark = new Set((marked || []).map(([r, col]) => r * w + col));
  const full = new Set(rows || []);
  for (let r = 0; r < h; r++) {
    if (full.has(r)) { g.fillStyle = "#fff6c0"; g.fillRect(0, (h - 1 - r) * cell, c.width, cell); }
    for (let col = 0; col < w; col++) {
      if (!board[r][col]) continue;
      g.fillStyle = full.has(r) ? "#ffb000" : mark.has(r * w + col) ? "#f0c040" : "#5a8fd0";
      g.fillRect(col * cell + 1, (h - 1 - r) * cell + 1, cell - 2, cell - 2);
    }
  }
}

function drawTetris(f) {
  if (S.clearTimer) { clearTimeout(S.clearTimer); S.clearTimer = null; }
  if (f.cleared > 0 && f.before_clear) {  // the full rows glow, then go
    drawBoard(f.before_clear, f.placed_before_clear, f.cleared_rows);
    const b = $("banner");
    b.textContent = f.cleared === 1 ? "1 line!" : `${f.cleared} lines!`;
    b.hidden = false;
    S.clearTimer = setTimeout(() => { b.hidden = true; drawBoard(f.board, [], []); S.clearTimer = null; }, 450);
  } else {
    $("banner").hidden = true;
    drawBoard(f.board, f.placed, []);
  }
  $("game").textContent = `game ${f.game}, placement ${f.placement}`;
  $("score").textContent = `${f.lines} this game`;
  $("action").textContent = f.cleared > 0 ? `${f.action}: cleared ${f.cleared}` : f.action;
  $("steered").textContent = (f.without_you ? `Your teaching changed this move: on its own it would have played ${f.without_you}. ` : "") +
    (f.steered ? `Your teaching changed ${f.steered[0]} of its ${f.steered[1]} moves this game.` : "");
  $("weight").textContent = f.weight === null || f.weight === undefined ? "-" : f.weight.toFixed(2);
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
  $("columns").hidden = true;
  $("steered").textContent = (f.without_you ? `Your teaching changed the last decision: without it, ${f.without_you}. ` : "") +
    (f.steered ? `Your teaching changed ${f.steered[0]} of their ${f.steered[1]} decisions this episode.` : "");
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
  $("game").textContent = String(f.episode);
  $("score").textContent = `${f.time_s.toFixed(1)} s`;
  $("action").textContent = f.action;
  $("mean-hold").textContent = f.mean_hold_s === null ? "-" : `${f.mean_hold_s.toFixed(1)} s`;
  $("weight").textContent = f.weight === null || f.weight === undefined ? "-" : f.weight.toFixed(2);
  $("speed-unit").textContent = `decisions/s (real time: ${f.real_time})`;
}

// any Gymnasium task: the frame the task rendered itself, drawn when it has loaded (frames come in order)
function drawGym(f) {
  $("columns").hidden = true;
  $("steered").textContent = (f.without_you ? `Your teaching changed this move: on its own it would have taken ${f.without_you}. ` : "") +
    (f.steered ? `Your teaching changed ${f.steered[0]} of its ${f.steered[1]} moves this episode.` : "");
  const img = new Image();
  img.onload = () => {
    if (S.frame !== f) return;  // a later frame came first
    const c = $("view");
    if (c.width !== img.width || c.height !== img.height) { c.width = img.width; c.height = img.height; }
    c.getContext("2d").drawImage(img, 0, 0);
  };
  img.src = f.image;
  $("game").textContent = `${f.episode}, step ${f.step}`;
  $("score").textContent = `${nice(f["return"])}${f.ended ? " (episode over)" : ""}`;
  $("action").textContent = f.action;
  $("weight").textContent = f.weight === null || f.weight === undefined ? "-" : f.weight.toFixed(2);
}

function showView(view) {
  if (view === "gym") {
    document.body.classList.add("gym");
    const task = S.info.task ? ` in ${S.info.task}` : "";
    $("help").innerHTML = "";
    $("help").append(`Watch the agent act${task}, one step at a time. Press `);
    $("help").insertAdjacentHTML("beforeend", '<kbd id="key-good">/</kbd> or <b>Good</b> when a step ' +
      'was good, <kbd id="key-bad">z</kbd> or <b>Bad</b> when it was bad. It learns from you and from the ' +
      "task's reward.");
    $("game-label").textContent = "Episode";
    $("score-label").textContent = "Return so far";
    $("action-label").textContent = "Last action";
    $("progress-label").textContent = "Steps";
    $("speed-unit").textContent = "steps/s";
    return;
  }
  if (view !== "keepaway") return;
  document.body.classList.add("keepaway");
  $("help").innerHTML = "Watch the keepers (blue, numbered) keep the ball from the takers (red). Press " +
    '<kbd id="key-good">/</kbd> or <b>Good</b> when they keep it well: holding when the takers are far, ' +
    'passing to an open teammate. Press <kbd id="key-bad">z</kbd> or <b>Bad</b> for passes into a taker ' +
    "or holding on while the takers close in. They learn from you and from how long they keep the ball.";
  $("game-label").textContent = "Episode";
  $("score-label").textContent = "Hold time";
  $("action-label").textContent = "Last decision";
  $("progress-label").textContent = "Simulated time";
  $("speed-unit").textContent = "decisions/s";
}

function nice(x) {
  return Math.abs(x) >= 100 ? x.toFixed(0) : Math.abs(x) >= 10 ? x.toFixed(1).replace(/\.0$/, "") : x.toFixed(2).replace(/\.?0+$/, "");
}

// the learning curve with its axes; each point filled when the person taught it, hollow when it practised alone
function drawCurveOn(c, curve) {
  const g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  const L = 44, R = 10, T = 10, B = 34, W = c.width - L - R, H = c.height - T - B;
  const keep = S.view === "keepaway";
  const xs = curve.map((p) => p[0]), ys = curve.map((p) => p[1]);
  const x0 = curve.length ? Math.min(...xs) : 0, x1 = curve.length ? Math.max(...xs, x0 + 1) : 1;
  // from 0 (or below it: a task's returns may be negative) to a tenth above the highest point
  const lo = Math.min(0, ...ys), hi = Math.max(1, ...ys), span = hi - lo;
  const y0 = lo < 0 ? lo - 0.1 * span : 0, y1 = hi + 0.1 * span;
  const X = (x) => L + (curve.length === 1 ? W / 2 : ((x - x0) / (x1 - x0)) * W);
  const Y = (y) => T + H - ((y - y0) / (y1 - y0)) * H;
  g.strokeStyle = "#555"; g.lineWidth = 1; g.beginPath();
  g.moveTo(L, T); g.lineTo(L, T + H); g.lineTo(L + W, T + H); g.stroke();
  g.fillStyle = "#333"; g.font = "11px system-ui, sans-serif";
  g.textAlign = "right"; g.textBaseline = "middle";
  [y0, (y0 + y1) / 2, y1].forEach((y) => { g.fillText(nice(y), L - 4, Y(y)); g.beginPath(); g.moveTo(L - 3, Y(y)); g.lineTo(L, Y(y)); g.stroke(); });
  g.textAlign = "center"; g.textBaseline = "top";
  if (curve.length) {
    const ticks = curve.length === 1 ? [x0] : [x0, x1];
    ticks.forEach((x) => { g.fillText(nice(x), X(x), T + H + 3); });
  }
  g.fillText(S.info.curve_x || (keep ? "episodes" : "practice round"), L + W / 2, T + H + 18);
  g.save(); g.translate(10, T + H / 2); g.rotate(-Math.PI / 2);
  g.fillText(curveUnit(), 0, -6); g.restore();
  if (!curve.length) {
    g.textBaseline = "middle"; g.fillText("no point yet", L + W / 2, T + H / 2);
    return;
  }
  g.strokeStyle = "#2a5ab0"; g.lineWidth = 1.5; g.beginPath();
  curve.forEach(([x, y], i) => { if (i === 0) g.moveTo(X(x), Y(y)); else g.lineTo(X(x), Y(y)); });
  g.stroke();
  curve.forEach(([x, y, taught]) => {
    g.beginPath(); g.arc(X(x), Y(y), 3.5, 0, 2 * Math.PI);
    if ((taught || 0) >= 0.5) { g.fillStyle = "#2a8a3a"; g.fill(); } else { g.fillStyle = "#fff"; g.fill(); g.strokeStyle = "#777"; g.stroke(); }
  });
}

// what the curve's points measure: the run's own words (info.curve_y), else the domain's
function curveUnit() {
  return S.info.curve_y || (S.view === "keepaway" ? "seconds held" : "lines per test game");
}

function drawCurve() {
  drawCurveOn($("curve"), S.curve);
  if (!S.curve.length) { $("curve-label").textContent = ""; return; }
  const last = S.curve[S.curve.length - 1], best = Math.max(...S.curve.map((p) => p[1]));
  $("curve-label").textContent = (S.info.curve_note
    ? `${S.info.curve_note}: latest ${nice(last[1])}, best ${nice(best)}.`
    : S.view === "keepaway"
    ? `Seconds the keepers kept the ball (mean of each block of episodes): latest ${last[1].toFixed(1)}, best ${best.toFixed(1)}.`
    : `Lines per test game after each practice round: latest ${last[1].toFixed(1)}, best ${best.toFixed(1)}.`) +
    " Filled dots: you taught; hollow: it practised alone.";
}

// --- the end of the session ---

const HEADLINES = {
  finished: "The run finished: it used its whole budget.",
  finished_by_you: "You finished the session. The run is saved.",
  stopped: "The run was stopped from the terminal (Ctrl-C or a stop signal).",
  failed: "The run stopped with an error: the terminal says what went wrong.",
};

function mean(a) { return a.reduce((s, x) => s + x, 0) / a.length; }

function showSummary(m) {
  S.ended = m; S.connected = false;
  render();
  $("teach").hidden = true;
  $("summary").hidden = false;
  $("summary-title").textContent = HEADLINES[m.reason] || "The session has ended.";
  $("summary-why").textContent = m.checkpoint
    ? "Everything you taught is in the saved run."
    : "No checkpoint was written yet; your presses are in the feedback log.";
  const extra = [];
  if (m.paused) extra.push(`${m.paused} while paused`);
  $("summary-presses").textContent =
    `${m.given} presses counted: ${m.good} good, ${m.bad} bad${extra.length ? " (" + extra.join(", ") + ")" : ""}. ` +
    notCountedText(m.not_taken || 0);
  drawCurveOn($("summary-curve"), m.curve);
  const unit = curveUnit();
  const taught = m.curve.filter((p) => p[2] >= 0.5).map((p) => p[1]);
  const alone = m.curve.filter((p) => p[2] < 0.5).map((p) => p[1]);
  let change = S.view === "tetris" ? "No point of the curve yet: the first practice round did not end."
    : "No point of the curve yet.";
  if (m.curve.length) {
    const first = m.curve[0][1], last = m.curve[m.curve.length - 1][1];
    change = `From ${first.toFixed(1)} to ${last.toFixed(1)} ${unit}.`;
    if (taught.length) change += ` With you (filled): ${mean(taught).toFixed(1)} on average over ${taught.length} points.`;
    if (alone.length) change += ` On its own (hollow): ${mean(alone).toFixed(1)} over ${alone.length}.`;
    if (taught.length && alone.length) change += " This is not a controlled comparison: the agent also improves with practice.";
  }
  $("summary-change").textContent = change;
  const saved = $("summary-saved");
  saved.replaceChildren();
  [["Run", m.run_dir], ["Checkpoint", m.checkpoint || "none yet"], ["Your presses", m.feedback_log],
    ["This summary", m.summary_file]].forEach(([k, v]) => {
    if (v === undefined) return;
    const li = document.createElement("li"); li.textContent = `${k}: ${v}`; saved.appendChild(li);
  });
  $("summary-resume").textContent = m.resume || "";
  $("summary-run").hidden = STUDY;
  $("summary-continue").hidden = !STUDY;
  $("summary-keep").textContent = "The run has stopped serving this page: reloading it or opening it again " +
    "will not show this summary. " + (m.summary_file ? "It is saved in the file above; " : "") +
    "Download saves a copy from here.";
  $("summary-download").onclick = () => {
    const a = document.createElement("a");
    a.href = URL.createObjectURL(new Blob([JSON.stringify(m, null, 2)], { type: "application/json" }));
    a.download = "teaching_summary.json";
    a.click();
    URL.revokeObjectURL(a.href);
  };
  const list = $("summary-list");
  list.replaceChildren();
  m.presses.forEach((p) => {
    const li = document.createElement("li");
    li.textContent = `${p.value > 0 ? "Good" : "Bad"} → ${p.filed || "this moment"}${p.paused ? " (while paused)" : ""}`;
    list.appendChild(li);
  });
}

// --- messages from the run ---

// Pause and presence toggle from the last state asked for, not the last one shown: a second press before
// the run has confirmed the first must undo it, not ask for the same state again.
function toggle(type, field, shown) {
  const want = !(field in S.asked ? S.asked[field] : shown);
  if (send({ type: type, [field]: want })) S.asked[field] = want;
}

function showSettings(m) {
  S.paused = m.paused; S.here = m.here; S.live = m.live; S.ending = m.ending;
  for (const field of Object.keys(S.asked)) if (m[field] === S.asked[field]) delete S.asked[field];
  S.progress = m.progress || {}; S.given = m.given;
  if (document.activeElement !== $("speed")) {
    $("speed").value = String(m.actions_per_s);
    $("speed-value").textContent = String(m.actions_per_s);
  }
  if (m.curve) { S.curve = m.curve; drawCurve(); }
  render();
}

function onMessage(ev) {
  const m = JSON.parse(ev.data);
  if (m.type === "config") {
    S.keys = m.keys; S.view = m.view || "tetris"; S.reaction = m.reaction_s; S.reconnect = m.reconnect_s || 0;
    S.info = m;
    showView(S.view);
    $("key-good").textContent = S.keys.good; $("key-bad").textContent = S.keys.bad;
    $("key-pause").textContent = S.keys.pause; $("key-presence").textContent = S.keys.presence;
    if (m.weight_name) $("weight-label").textContent = m.weight_name;
    $("weight-sentence").textContent = m.weight_sentence || "";
  } else if (m.type === "settings") showSettings(m);
  else if (m.type === "status") { S.over = m.game_over || null; render(); }
  else if (m.type === "tetris") { S.frame = m; S.over = null; drawTetris(m); }
  else if (m.type === "keepaway") { S.frame = m; drawKeepaway(m); }
  else if (m.type === "gym") { S.frame = m; drawGym(m); }
  else if (m.type === "curve") { S.curve = m.curve; drawCurve(); }
  else if (m.type === "role") { S.role = m.role; render(); }
  else if (m.type === "ack") onAck(m);
  else if (m.type === "error") onError(m);
  else if (m.type === "end") showSummary(m);
}

// in a study: this participant's teaching is not (or no longer) here; the study's page goes on
function studyOver(reason) {
  S.ended = { reason: "over" };
  render();
  $("teach").hidden = true;
  $("study-over-text").textContent = reason || "The teaching session has ended.";
  $("study-over").hidden = false;
}

function connect() {
  const ws = new WebSocket(wsUrl);
  S.ws = ws;
  const opened = () => { S.connected = true; S.everConnected = true; S.failures = 0; S.closeReason = ""; render(); };
  // in a study the socket opens at the study's proxy: the page is connected once the run itself speaks
  ws.onopen = () => { if (!STUDY) opened(); };
  ws.onmessage = (ev) => { if (STUDY && !S.connected && S.ws === ws) opened(); onMessage(ev); };
  ws.onclose = (ev) => {
    if (S.ws !== ws) return;
    S.connected = false;
    if (STUDY && !S.ended && ev.code === OVER) { studyOver(ev.reason); return; }
    if (STUDY) S.closeReason = ev.code === WAIT || ev.code === 1001 ? ev.reason : "";
    S.asked = {};
    if (S.pending.size) {
      lastPress(`${S.pending.size} press${S.pending.size > 1 ? "es" : ""} not confirmed before the connection was lost; the count shows what the run took.`, true);
      S.pending.clear();
    }
    if (S.ended) return;
    S.failures += 1;
    render();
    setTimeout(connect, 1000);
  };
}

// --- controls: keys work whatever was clicked or dragged last ---

function typing(t) {
  return t && (t.isContentEditable || t.tagName === "TEXTAREA" || t.tagName === "SELECT" ||
    (t.tagName === "INPUT" && t.type !== "range"));
}

document.addEventListener("keydown", (e) => {
  if (e.repeat || e.ctrlKey || e.metaKey || e.altKey || typing(e.target)) return;
  if (e.key === S.keys.good) feedback(1);
  else if (e.key === S.keys.bad) feedback(-1);
  else if (e.key === S.keys.pause) toggle("pause", "paused", S.paused);
  else if (e.key === S.keys.presence) toggle("presence", "here", S.here);
  else return;
  e.preventDefault();
});
function button(id, act) {
  $(id).addEventListener("click", (e) => { e.currentTarget.blur(); act(); });
}
button("good", () => feedback(1));
button("bad", () => feedback(-1));
button("pause", () => toggle("pause", "paused", S.paused));
button("presence", () => toggle("presence", "here", S.here));
button("finish", () => {
  if (confirm("Finish and save now? The agent stops learning and this session ends.")) send({ type: "finish" });
});
const speed = $("speed");
speed.addEventListener("input", () => { $("speed-value").textContent = speed.value; });
speed.addEventListener("change", () => {
  $("speed-value").textContent = speed.value;
  send({ type: "speed", actions_per_s: Number(speed.value) });
  speed.blur();
});
speed.addEventListener("pointerup", () => speed.blur());
if (STUDY) document.body.classList.add("study");  // a study's participant: no weight, which tells the condition
render();
drawCurve();
connect();

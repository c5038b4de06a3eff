// The study's page for a participant: landing (start or enter a code), then the steps the study's server
// says, one at a time: consent, instructions, a practice with a scripted dot that the person's presses
// steer, a reaction-time check, the teaching page, a questionnaire and the end. Every step's answer goes to
// the server, which decides the next step; a reload shows the step the server has.
"use strict";

const $ = (id) => document.getElementById(id);
const CODE = (location.pathname.match(/\/p\/([A-Za-z0-9]+)\/$/) || [])[1] || null;
const SECTIONS = ["landing", "consent", "instructions", "practice", "calibration", "teaching", "questionnaire",
  "done", "declined", "paused"];
const S = { state: null, shown: null, busy: false };

function show(name) {
  SECTIONS.forEach((s) => { $(s).hidden = s !== name; });
  S.shown = name;
}

function error(text) { $("error").textContent = text || ""; }

async function api(path, body) {
  const init = body === undefined ? {} : {
    method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
  };
  const r = await fetch(path, init);
  let data = null;
  try { data = await r.json(); } catch (e) { data = null; }
  return { status: r.status, data };
}

// --- the landing page: a new code, or one the person was given ---

function landing() {
  show("landing");
  $("start").addEventListener("click", async () => {
    $("start").disabled = true;
    const r = await api("api/join", { simulated: false });
    if (r.status === 200 && r.data && r.data.code) { location.href = `p/${r.data.code}/`; return; }
    $("start").disabled = false;
    $("landing-error").textContent = (r.data && r.data.error) || "The study cannot take you now; please try later.";
  });
  $("code-form").addEventListener("submit", (e) => {
    e.preventDefault();
    const code = $("code-input").value.trim().replace(/[^A-Za-z0-9]/g, "");
    if (code) location.href = `p/${code}/`; else $("landing-error").textContent = "Please enter your code.";
  });
}

// --- the steps ---

const STEP_NAMES = {
  consent: "Step 1: taking part", instructions: "Step 2: what you will do", practice: "Step 3: practice",
  calibration: "Step 4: how fast you press", teaching: "Step 5: teaching", questionnaire: "Step 6: questions",
  done: "Finished", declined: "", paused: "Paused",
};

async function advance(step, action, data) {
  if (S.busy) return;
  S.busy = true;
  error("");
  try {
    const r = await api("api/step", { step, action, data: data || {} });
    if (r.status === 200 || r.status === 409) apply(r.data, true);
    else error((r.data && r.data.error) || `The study did not take this (error ${r.status}); please try again.`);
  } catch (e) {
    error("The study's server does not answer; please try again in a moment.");
  } finally {
    S.busy = false;
  }
}

function apply(state, force) {
  if (!state || !state.step) return;
  const first = S.state === null;
  S.state = state;
  if (first) {
    document.title = state.study.title;
    $("title").textContent = state.study.title;
    $("consent-text").textContent = state.study.consent;
    $("instructions-text").textContent = state.study.instructions;
  }
  const view = state.stopped && state.step !== "done" && state.step !== "declined" ? "paused" : state.step;
  $("where").textContent = STEP_NAMES[view] || "";
  if (view === "teaching") teachingReady(state);
  if (view === S.shown && !force) return;  // the same step: keep what the person has typed or pressed
  if (view === S.shown && (view === "practice" || view === "calibration" || view === "questionnaire")) return;
  stopPractice(); stopCalibration();
  show(view);
  if (view === "practice") startPractice(state.study.practice_s);
  else if (view === "calibration") startCalibration(state.study.calibration || {});
  else if (view === "questionnaire") buildQuestions(state.study.questionnaire || []);
  else if (view === "done") doneSummary(state.summary);
}

async function refresh() {
  try {
    const r = await api("api/state");
    if (r.status === 200) apply(r.data, false);
    else if (r.status === 404) { show(null); error("This code is not known to the study: please check the link you were given."); }
  } catch (e) { /* the next refresh tries again */ }
}

// --- practice: a dot that steps left or right; each press makes the step it just took more or less likely ---

const P = { timer: null, clock: null, x: 4, lean: 0, last: 0, presses: 0, steps: 0, left: 0, ends: 0 };
const CELLS = 9;

function chanceRight() { return 1 / (1 + Math.exp(-P.lean)); }

function drawWalk() {
  const c = $("walk"), g = c.getContext("2d");
  const w = c.width / CELLS;
  g.fillStyle = "#111"; g.fillRect(0, 0, c.width, c.height);
  for (let i = 0; i < CELLS; i++) { g.fillStyle = "#333"; g.fillRect(i * w + 2, 55, w - 4, 6); }
  g.fillStyle = "#ffd700"; g.font = "22px system-ui, sans-serif"; g.textAlign = "center";
  g.fillText("★", (CELLS - 0.5) * w, 35); g.fillText("★", 0.5 * w, 35);
  g.fillStyle = "#5a8fd0"; g.beginPath(); g.arc((P.x + 0.5) * w, 58, 13, 0, 2 * Math.PI); g.fill();
  if (P.last) {
    g.fillStyle = "#fff"; g.font = "18px system-ui, sans-serif";
    g.fillText(P.last > 0 ? "→" : "←", (P.x + 0.5) * w, 85);
  }
  const right = chanceRight();
  $("lean-fill").style.width = `${Math.round(right * 100)}%`;
  $("lean").dataset.right = right.toFixed(3);
  $("lean-text").textContent = `It now steps right ${Math.round(right * 100)}% of the time and left ${100 - Math.round(right * 100)}%.`;
}

function step() {
  P.last = Math.random() < chanceRight() ? 1 : -1;
  P.x = Math.max(0, Math.min(CELLS - 1, P.x + P.last));
  P.steps += 1;
  if (P.x === 0 || P.x === CELLS - 1) { P.ends += 1; setTimeout(() => { P.x = 4; drawWalk(); }, 350); }
  drawWalk();
}

function practicePress(value) {
  if (S.shown !== "practice" || !P.last) return;
  P.lean = Math.max(-4, Math.min(4, P.lean + value * P.last * 0.8));
  P.presses += 1;
  const dir = P.last > 0 ? "right" : "left";
  $("practice-last").textContent = `${value > 0 ? "Good" : "Bad"} for stepping ${dir}: it will step ${dir} ${value > 0 ? "more" : "less"} often.`;
  drawWalk();
}

function startPractice(seconds) {
  Object.assign(P, { x: 4, lean: 0, last: 0, presses: 0, steps: 0, left: Math.max(0, seconds || 0), ends: 0 });
  $("practice-last").textContent = "";
  $("practice-next").disabled = P.left > 0;
  const tick = () => {
    $("practice-left").textContent = P.left > 0 ? `${Math.ceil(P.left)} s of practice left` : "Practice done: go on when you are ready.";
    $("practice-next").disabled = P.left > 0;
  };
  tick();
  drawWalk();
  P.timer = setInterval(step, 800);
  P.clock = setInterval(() => { P.left = Math.max(0, P.left - 1); tick(); }, 1000);
}

function stopPractice() {
  clearInterval(P.timer); clearInterval(P.clock); P.timer = null; P.clock = null;
}

// --- calibration: the time from a circle appearing to the person's press ---

const C = { trials: 0, delays: [], shownAt: null, wait: null, miss: null, ready: false, active: false };

function startCalibration(cal) {
  Object.assign(C, { trials: cal.trials || 0, delays: [], shownAt: null, ready: false, active: true });
  $("skip").hidden = !cal.optional;
  $("target").hidden = true;
  $("target-text").textContent = "Press Space or tap here to begin.";
  trialsLeft();
  setTimeout(() => $("target-box").focus(), 0);
}

function stopCalibration() {
  clearTimeout(C.wait); clearTimeout(C.miss); C.active = false;
}

function trialsLeft() {
  $("trials-left").textContent = `${C.delays.length} of ${C.trials} done.`;
}

function nextTrial() {
  C.ready = true; C.shownAt = null;
  $("target").hidden = true;
  $("target-text").textContent = "Wait for the green circle...";
  C.wait = setTimeout(() => {
    C.shownAt = performance.now();
    $("target").hidden = false;
    $("target-text").textContent = "";
    C.miss = setTimeout(() => {
      $("target").hidden = true;
      $("target-text").textContent = "Too slow that time. Press Space or tap to try again.";
      C.ready = false;
    }, 3000);
  }, 1000 + Math.random() * 2000);
}

function calibrationPress() {
  if (!C.active || S.busy) return;
  if (!C.ready) { nextTrial(); return; }
  if (C.shownAt === null) {  // before the circle
    clearTimeout(C.wait);
    C.ready = false;
    $("target-text").textContent = "Too soon: wait until you see the circle. Press Space or tap to try again.";
    return;
  }
  clearTimeout(C.miss);
  const delay = (performance.now() - C.shownAt) / 1000;
  C.ready = false;
  $("target").hidden = true;
  if (delay < 0.05) { $("target-text").textContent = "Too soon. Press Space or tap to try again."; return; }
  C.delays.push(Math.round(delay * 1000) / 1000);
  trialsLeft();
  if (C.delays.length >= C.trials) {
    $("target-text").textContent = "Done, thank you.";
    C.active = false;
    advance("calibration", "next", { delays_s: C.delays });
  } else {
    $("target-text").textContent = `${Math.round(delay * 1000)} ms. Press Space or tap for the next one.`;
  }
}

// --- teaching ---

function teachingReady(state) {
  $("teaching-ready").textContent = state.teaching && state.teaching.ready
    ? "Your session is ready."
    : "Your session is starting: the teaching page says when the game is on screen.";
}

// --- questionnaire ---

function buildQuestions(items) {
  const form = $("answers");
  form.replaceChildren();
  items.forEach((item) => {
    const box = document.createElement("fieldset");
    const legend = document.createElement("legend");
    legend.textContent = item.text;
    box.appendChild(legend);
    box.dataset.id = item.id;
    box.dataset.kind = item.kind;
    if (item.kind === "likert") {
      const row = document.createElement("div");
      row.className = "likert";
      for (let v = 1; v <= item.points; v++) {
        const label = document.createElement("label");
        const input = document.createElement("input");
        input.type = "radio"; input.name = item.id; input.value = String(v);
        label.append(input, document.createTextNode(String(v)));
        row.appendChild(label);
      }
      const ends = document.createElement("div");
      ends.className = "ends";
      const low = document.createElement("span"), high = document.createElement("span");
      low.textContent = `1: ${item.low || ""}`; high.textContent = `${item.points}: ${item.high || ""}`;
      ends.append(low, high);
      box.append(row, ends);
    } else {
      const area = document.createElement("textarea");
      area.name = item.id;
      area.maxLength = item.max_chars || 2000;
      area.setAttribute("aria-label", item.text);
      box.appendChild(area);
      const note = document.createElement("div");
      note.className = "ends";
      note.textContent = "Optional.";
      box.appendChild(note);
    }
    form.appendChild(box);
  });
  const submit = document.createElement("button");
  submit.type = "submit"; submit.className = "primary"; submit.textContent = "Send my answers";
  form.appendChild(submit);
  form.onsubmit = (e) => {
    e.preventDefault();
    const answers = {}, missing = [];
    form.querySelectorAll("fieldset").forEach((box) => {
      const id = box.dataset.id;
      if (box.dataset.kind === "likert") {
        const picked = box.querySelector("input:checked");
        if (picked) answers[id] = Number(picked.value); else missing.push(box.querySelector("legend").textContent);
      } else {
        answers[id] = box.querySelector("textarea").value;
      }
    });
    if (missing.length) { $("answers-error").textContent = `Please answer: ${missing.join("; ")}`; return; }
    $("answers-error").textContent = "";
    advance("questionnaire", "next", { answers });
  };
}

// --- the end ---

function doneSummary(m) {
  if (!m) { $("done-summary").textContent = ""; return; }
  const parts = [];
  if (m.given !== undefined) parts.push(`You gave ${m.given} press${m.given === 1 ? "" : "es"} that counted (${m.good || 0} Good, ${m.bad || 0} Bad).`);
  const curve = m.curve || [];
  if (curve.length > 1) {
    const first = curve[0][1], last = curve[curve.length - 1][1];
    parts.push(`The agent's score went from ${first.toFixed(1)} to ${last.toFixed(1)} while you taught it.`);
  }
  $("done-summary").textContent = parts.join(" ");
}

// --- keys and buttons ---

function typing(t) {
  return t && (t.isContentEditable || t.tagName === "TEXTAREA" || t.tagName === "INPUT" || t.tagName === "SELECT");
}

document.addEventListener("keydown", (e) => {
  if (e.repeat || e.ctrlKey || e.metaKey || e.altKey || typing(e.target)) return;
  if (S.shown === "practice" && (e.key === "/" || e.key === "z")) { practicePress(e.key === "/" ? 1 : -1); e.preventDefault(); }
  else if (S.shown === "calibration" && (e.key === " " || e.key === "Enter") && e.target.tagName !== "BUTTON") {
    calibrationPress(); e.preventDefault();
  }
});

function init() {
  if (!CODE) { landing(); return; }
  $("agree").onclick = () => advance("consent", "agree");
  $("decline").onclick = () => {
    if (confirm("Leave the study? Nothing else will be recorded.")) advance("consent", "decline");
  };
  $("instructions-next").onclick = () => advance("instructions", "next");
  $("p-good").onclick = (e) => { e.currentTarget.blur(); practicePress(1); };
  $("p-bad").onclick = (e) => { e.currentTarget.blur(); practicePress(-1); };
  $("practice-next").onclick = () => advance("practice", "next");
  $("target-box").addEventListener("pointerdown", (e) => { e.preventDefault(); calibrationPress(); });
  $("skip").onclick = () => { stopCalibration(); advance("calibration", "skip"); };
  refresh();
  setInterval(refresh, 2000);
}

init();

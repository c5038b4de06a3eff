// The researcher's page: every participant's step, condition, progress, presses and worker, refreshed
// every 2 s, with Stop and Resume per participant and the study's data as a zip. The token of the link
// study.py printed goes with every request (as a header; in the download's URL, which has no header).
"use strict";

const $ = (id) => document.getElementById(id);
const token = new URLSearchParams(location.search).get("token") || "";
const headers = { Authorization: `Bearer ${token}` };
$("download").href = `admin/data.zip?${new URLSearchParams({ token })}`;

function text(v) {
  if (v === null || v === undefined) return "-";
  if (typeof v === "object") return Object.entries(v).map(([k, x]) => `${k} ${x}`).join(", ");
  return String(v);
}

function cell(row, value) {
  const td = document.createElement("td");
  td.textContent = text(value);
  row.appendChild(td);
  return td;
}

async function act(code, action) {
  const r = await fetch(`admin/api/participants/${encodeURIComponent(code)}/${action}`, { method: "POST", headers });
  if (!r.ok) $("error").textContent = `${action} ${code}: error ${r.status}`;
  refresh();
}

async function refresh() {
  let list;
  try {
    const r = await fetch("admin/api/participants", { headers });
    if (!r.ok) { $("error").textContent = r.status === 403 ? "The researcher token is missing or wrong: use the link study.py printed." : `error ${r.status}`; return; }
    list = await r.json();
  } catch (e) {
    $("error").textContent = "The study's server does not answer.";
    return;
  }
  $("error").textContent = "";
  const steps = {};
  list.forEach((p) => { steps[p.step] = (steps[p.step] || 0) + 1; });
  $("counts").textContent = `${list.length} participants: ` + Object.entries(steps).map(([s, n]) => `${n} ${s}`).join(", ");
  const rows = list.map((p) => {
    const tr = document.createElement("tr");
    if (p.stopped) tr.className = "stopped";
    cell(tr, p.code); cell(tr, p.condition);
    cell(tr, p.stopped ? `${p.step} (stopped)` : p.step);
    cell(tr, p.progress); cell(tr, p.presses); cell(tr, p.worker);
    cell(tr, p.simulated ? "yes" : "no");
    const td = cell(tr, "");
    td.textContent = "";
    const b = document.createElement("button");
    b.textContent = p.stopped ? "Resume" : "Stop";
    b.onclick = () => act(p.code, p.stopped ? "resume" : "stop");
    td.appendChild(b);
    return tr;
  });
  $("rows").replaceChildren(...rows);
}

refresh();
setInterval(refresh, 2000);

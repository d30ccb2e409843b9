// The quality page: boards of the quality log, one board's figures, records and CSV.
"use strict";

function $(id) { return document.getElementById(id); }
function fmt(v, digits) { return v === null || v === undefined ? "-" : (typeof v === "number" ? v.toFixed(digits) : String(v)); }

function when(iso) { return iso ? iso.replace("T", " ").slice(0, 19) : "-"; }

function cells(tr, values) {
  for (const v of values) {
    const td = document.createElement("td");
    td.textContent = v;
    tr.appendChild(td);
  }
  return tr;
}

async function getJson(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${r.status} ${await r.text()}`);
  return r.json();
}

async function loadBoards() {
  const note = $("boards-note");
  let data;
  try {
    data = await getJson("/api/quality/boards");
  } catch (err) {
    note.textContent = `quality log unavailable: ${err.message}`;
    return;
  }
  $("log-name").textContent = data.log;
  const qc = data.quality_class;
  $("class-name").textContent = qc ? `class ${qc.name}: target ${qc.target_pitch_mm} mm ±${(qc.pitch_tolerance * 100).toFixed(1)} %` : "";
  note.textContent = data.boards.length ? "" : "no records yet";
  const body = $("boards").tBodies[0];
  body.replaceChildren(...data.boards.map((b) => {
    const tr = cells(document.createElement("tr"), [b.board_id, b.machine_id || "-", b.records, b.ok,
      b.judged ? `${b.passed}/${b.judged}` : "-", fmt(b.length_mm, 0), fmt(b.mean_pitch_mm, 3),
      fmt(b.mean_uniformity_cv, 3), fmt(b.mean_depth_um, 1), b.grade ?? "-", b.defects ?? "-",
      when(b.first_time), when(b.last_time)]);
    tr.className = "clickable";
    tr.dataset.board = String(b.board_id);
    tr.addEventListener("click", () => showBoard(b.board_id));
    return tr;
  }));
  const wanted = Number(new URLSearchParams(location.search).get("board"));
  const first = data.boards.find((b) => b.board_id === wanted) || data.boards[data.boards.length - 1];
  if (first && $("board-title").textContent === "-") showBoard(first.board_id);
}

async function showBoard(id) {
  for (const tr of $("boards").tBodies[0].rows) tr.classList.toggle("selected", tr.dataset.board === String(id));
  $("board-title").textContent = String(id);
  const csv = $("board-csv");
  csv.href = `/api/quality/boards/${id}.csv`;
  csv.hidden = false;
  const data = await getJson(`/api/quality/boards/${id}`);
  const figs = $("figures");
  figs.replaceChildren(...data.figures.map((name) => {
    const img = document.createElement("img");
    img.alt = `${name} of board ${id}`;
    img.src = `/api/quality/boards/${id}/${name}.png`;
    img.addEventListener("error", () => img.remove());
    return img;
  }));
  $("records").tBodies[0].replaceChildren(...data.records.map((r) => {
    const tr = cells(document.createElement("tr"), [r.id, r.seq, fmt(r.board_position_mm, 1), r.state || "-",
      fmt(r.pitch_mm, 3), fmt(r.uniformity_cv, 3), fmt(r.depth_um, 1), fmt(r.confidence, 2),
      fmt(r.feed_setpoint_mm_s, 0), r.passed === null ? "-" : (r.passed ? "yes" : "no"),
      r.grade ?? "-", r.defects === null ? "-" : (r.defects.join(", ") || "none"), r.error || ""]);
    if (!r.ok || r.passed === false) tr.lastChild.className = "fail";
    return tr;
  }));
}

window.addEventListener("DOMContentLoaded", () => {
  $("reload").addEventListener("click", loadBoards);
  loadBoards();
});

// The operator page: follows /api/live/stream (server-sent events) and draws the snapshot.
"use strict";

const KNIFE_COLOURS = 8; // CSS classes k0..k7
const feedHistories = {}; // head ("" for a single machine) -> [{t, set, act}] from its snapshots
let feedHistory = [];
const FEED_KEEP = 600;
let lastVersion = -1;
let lastSnap = null;
let selectedHead = null; // a moulder's head whose panels are shown (null: the first)

function $(id) { return document.getElementById(id); }
function num(v, digits) { return Plot.finite(v) ? v.toFixed(digits) : "-"; }
function setText(id, text) { const e = $(id); if (e.textContent !== text) e.textContent = text; }

function drawState(status) {
  const badge = $("state");
  if (!status) {
    badge.className = "badge unknown"; badge.textContent = "no service";
    setText("safe-reason", "");
    return;
  }
  const run = status.state === "run";
  badge.className = `badge ${run ? "run" : "safe"}`;
  badge.textContent = run ? "RUN" : "SAFE STATE";
  setText("safe-reason", run ? "" : (status.safe_reason || status.missing.join(", ") || ""));
  setText("feed-set", num(status.feed_setpoint_mm_s, 1));
  setText("feed-act", num(status.feed_actual_mm_s, 1));
  setText("amplifier", status.amplifier_enabled ? "enabled" : "disabled");
  const c = status.counters || {};
  setText("counters", `${c.frames ?? 0} handled, ${c.ok ?? 0} measured, ${c.failed ?? 0} failed, ` +
    `${c.safe_entries ?? 0} safe-state entries` +
    (status.log_problem ? ` - log: ${status.log_problem}` : ""));
  recordFeed(feedHistory, status);
}

function recordFeed(history, status) {
  if (!status || !Plot.finite(status.t_s)) return;
  const last = history[history.length - 1];
  if (!last || status.t_s > last.t) {
    history.push({ t: status.t_s, set: status.feed_setpoint_mm_s, act: status.feed_actual_mm_s });
    if (history.length > FEED_KEEP) history.shift();
  }
}

function drawNow(last, qc) {
  if (!last) return;
  setText("seq", `#${last.seq}${last.ok ? "" : " failed: " + (last.error || "")}`);
  setText("pitch", num(last.pitch_mm, 3));
  setText("cv", num(last.uniformity_cv, 3));
  setText("depth", num(last.depth_um, 2));
  setText("confidence", num(last.confidence, 2));
  setText("roll", num(last.roll_deg, 2));
  setText("roll-conf", Plot.finite(last.roll_confidence) ? `confidence ${last.roll_confidence.toFixed(2)}` : "");
  const cal = last.calibration;
  setText("calibration", cal ? `gain ${num(cal.gain, 3)} (${cal.trusted ? "trusted" : "not trusted"}` +
    `${cal.deblurred ? ", deblurred" : ""})` : "off");
  setText("latency", num(last.latency_ms, 1));
  if (qc) {
    setText("pitch-target", `target ${qc.target_pitch_mm} mm ±${(qc.pitch_tolerance * 100).toFixed(1)} %`);
    setText("cv-limit", Plot.finite(qc.uniformity_max_cv) ? `limit ${qc.uniformity_max_cv}` : "");
    setText("band-name", `class ${qc.name}`);
  }
}

function drawProfile(last) {
  const svg = $("profile");
  if (!last || !last.profile) return;
  const p = last.profile;
  const marks = last.marks || [];
  const spans = marks.map((m) => ({ x0: m.lo_mm, x1: m.hi_mm,
    cls: m.knife === null ? "span" : `knife k${m.knife % KNIFE_COLOURS}` }));
  const hmax = Math.max(...p.height_um.filter(Plot.finite));
  const labels = marks.map((m) => ({ x: (m.lo_mm + m.hi_mm) / 2, y: hmax,
    text: m.knife === null ? "?" : String(m.knife), cls: "mark-label" }));
  Plot.lines(svg, { series: [{ x: p.x_mm, y: p.height_um, cls: "profile" }], spans, labels,
    xlabel: "x along the feed in image A (mm)", ylabel: "height (µm)" });
  setText("profile-info", `pair #${last.seq}, ${marks.length} marks` +
    ({ widths: " (knife of each mark matched by width)",
       "widths-ambiguous": " (knife of each mark matched by width: ambiguous, the knives cut alike)" }[last.knife_source] || ""));
  const knives = new Set(marks.map((m) => m.knife).filter((k) => k !== null));
  const legend = $("knife-legend");
  const text = [...knives].sort((a, b) => a - b).map((k) => `knife ${k}`).join(" ");
  if (legend.dataset.text !== text) {
    legend.dataset.text = text;
    legend.replaceChildren(...[...knives].sort((a, b) => a - b).map((k) => {
      const s = document.createElement("span");
      s.className = `chip k${k % KNIFE_COLOURS}`;
      s.textContent = `knife ${k}`;
      return s;
    }));
  }
}

function drawTraces(trace, qc) {
  const alongBoard = trace.length && trace.every((r) => Plot.finite(r.board_m));
  const x = trace.map((r) => (alongBoard ? r.board_m : r.t_s));
  const xlabel = alongBoard ? "board travel since start (m)" : "service time (s)";
  const col = (k) => trace.map((r) => r[k]);
  const safe = [];
  for (let i = 0; i < trace.length; i++) {
    if (trace[i].state === "safe") safe.push({ x0: x[Math.max(0, i - 1)], x1: x[i], cls: "safe-span" });
  }
  Plot.lines($("pitch-chart"), { series: [{ x, y: col("pitch_mm"), cls: "pitch", points: true }],
    band: qc ? { lo: qc.pitch_lo_mm, hi: qc.pitch_hi_mm } : null,
    hlines: qc ? [{ y: qc.target_pitch_mm, cls: "target" }] : [], spans: safe,
    xlabel, ylabel: "pitch (mm)" });
  Plot.lines($("cv-chart"), { series: [{ x, y: col("uniformity_cv"), cls: "cv", points: true }],
    band: qc && Plot.finite(qc.uniformity_max_cv) ? { lo: 0, hi: qc.uniformity_max_cv } : null,
    spans: safe, xlabel, ylabel: "CV" });
  Plot.lines($("depth-chart"), { series: [{ x, y: col("depth_um"), cls: "depth", points: true }],
    band: qc && Plot.finite(qc.depth_max_um) ? { lo: 0, hi: qc.depth_max_um } : null,
    spans: safe, xlabel, ylabel: "depth (µm)" });
}

function drawKnives(last, status) {
  const widths = last ? last.knife_widths_mm : [];
  const offsets = status ? status.offsets_um : (last ? last.offsets_um : []);
  const labels = (n) => Array.from({ length: n }, (_, i) => `knife ${i}`);
  const cls = (n) => Array.from({ length: n }, (_, i) => `bar k${i % KNIFE_COLOURS}`);
  Plot.bars($("widths-chart"), { values: widths, labels: labels(widths.length),
    cls: cls(widths.length), ylabel: "width (mm)" });
  Plot.bars($("offsets-chart"), { values: offsets, labels: labels(offsets.length),
    cls: cls(offsets.length), ylabel: "offset (µm)" });
}

const JOINTING_WARN_BOARDS = 20; // as the service's JOINTING_DUE (controller/service/loops.py)

function drawKnifeCondition(status) {
  const kc = status ? status.knife_condition : null;
  const chip = status && status.alerts ? status.alerts.knife_chipped : null;
  const sign = (v) => (v >= 0 ? "+" : "");
  setText("kc-chip", !chip ? "" : chip.cause === "nick"
    ? `a knife is nicked (t=${num(chip.t_s, 1)} s): a ridge along the board at ` +
      `${num(chip.y_mm, 1)} mm across the field, ${num(chip.ridge_um, 0)} µm high`
    : `knife ${chip.knife} chipped or moved at t=${num(chip.t_s, 1)} s: ` +
      `runout ${sign(chip.runout_step_um)}${num(chip.runout_step_um, 1)} µm, ` +
      `marks ${sign(chip.width_change_mm)}${num(chip.width_change_mm, 3)} mm`);
  const forecast = $("kc-forecast");
  if (!kc) {
    setText("kc-forecast", "no offset table applied yet");
    forecast.className = "forecast";
    setText("kc-travel", "");
    $("kc-table").tBodies[0].replaceChildren();
    Plot.bars($("reserve-chart"), { values: [], labels: [], cls: [], ylabel: "reserve (µm)" });
    return;
  }
  setText("kc-forecast", kc.text);
  const soon = kc.state === "due" && Plot.finite(kc.due_in_boards) &&
    kc.due_in_boards <= JOINTING_WARN_BOARDS;
  forecast.className = `forecast ${kc.state}${soon ? " soon" : ""}`;
  setText("kc-travel", `(${num(kc.board_travel_m, 1)} m of board)`);
  const knives = kc.knives || [];
  const key = JSON.stringify(knives);
  const body = $("kc-table").tBodies[0];
  if (body.dataset.key !== key) {
    body.dataset.key = key;
    body.replaceChildren(...knives.map((k) => {
      const tr = document.createElement("tr");
      if (kc.state === "due" && kc.knife === k.knife) tr.className = "selected";
      for (const text of [`knife ${k.knife}`, num(k.drift_um_per_m, 3), num(k.reserve_um, 2),
                          num(k.offset_um, 2)]) {
        const td = document.createElement("td");
        td.textContent = text;
        tr.append(td);
      }
      return tr;
    }));
  }
  Plot.bars($("reserve-chart"), { values: knives.map((k) => k.reserve_um),
    labels: knives.map((k) => `knife ${k.knife}`),
    cls: knives.map((k) => `bar k${k.knife % KNIFE_COLOURS}`), ylabel: "reserve (µm)" });
}

const GRADE_WORDS = ["", "defect-free", "good", "fair", "poor", "very poor"]; // ASTM D1666

function countsText(counts) {
  const parts = Object.entries(counts || {}).filter(([, n]) => n > 0)
    .map(([k, n]) => `${k.replace("_", " ")} ${n}`);
  return parts.length ? parts.join(", ") : "no defects";
}

function drawCounts(counts) {
  // the board's defects per kind, each in its kind's colour (the strip's legend)
  const box = $("bs-counts");
  const key = counts ? JSON.stringify(counts) : "";
  if (box.dataset.key === key) return;
  box.dataset.key = key;
  if (!counts) { box.replaceChildren(); return; }
  const parts = Object.entries(counts).filter(([, n]) => n > 0);
  if (!parts.length) { box.replaceChildren("no defects"); return; }
  const nodes = [];
  parts.forEach(([k, n], i) => {
    const span = document.createElement("span");
    span.className = `kind d-${k}`;
    span.textContent = `${k.replace("_", " ")} ${n}`;
    if (i) nodes.push(", ");
    nodes.push(span);
  });
  box.replaceChildren(...nodes);
}

function drawBoardStrip(board) {
  const cur = board ? board.current : null;
  const last = board ? board.last : null;
  const badge = $("bs-grade");
  const svg = $("board-strip");
  setText("bs-last", last ? `; last board ${last.board_id}: grade ${last.grade} ` +
    `(${countsText(last.defect_counts)})` : "");
  if (!cur) {
    badge.className = "grade g0"; setText("bs-grade", "grade -");
    setText("bs-board", ""); drawCounts(null);
    if (svg.dataset.key !== "") { svg.dataset.key = ""; svg.replaceChildren(); }
    return;
  }
  badge.className = `grade g${cur.grade}`;
  setText("bs-grade", `grade ${cur.grade} ${GRADE_WORDS[cur.grade] || ""}`);
  setText("bs-reason", cur.grade_reason || "");
  setText("bs-board", `(board ${cur.board_id}, ${cur.pairs} pairs so far)`);
  drawCounts(cur.defect_counts);
  const key = `${cur.board_id}:${cur.pairs}:${cur.defects.length}`;
  if (svg.dataset.key === key) return;
  svg.dataset.key = key;
  svg.replaceChildren();
  const ns = "http://www.w3.org/2000/svg";
  const add = (name, attrs, text) => {
    const e = document.createElementNS(ns, name);
    for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
    if (text !== undefined) e.textContent = text;
    svg.append(e);
    return e;
  };
  const w = svg.clientWidth || 800, h = svg.clientHeight || 130, pad = 34;
  const xs = cur.defects.map((d) => d.board_x_mm);
  const lo = Math.min(0, cur.from_mm ?? 0, ...xs);
  const hi = Math.max(lo + 500, (cur.to_mm ?? 0) + 50, ...xs);
  const ys = cur.defects.map((d) => d.y_mm + d.width_mm / 2);
  const across = Math.max(40, ...ys);
  const X = (v) => pad + (v - lo) / (hi - lo) * (w - 2 * pad);
  const Y = (v) => 6 + v / across * (h - 30);
  add("rect", { class: "board", x: X(lo), y: Y(0), width: X(hi) - X(lo), height: Y(across) - Y(0) });
  add("line", { class: "pair", x1: X(cur.from_mm ?? lo), x2: X(cur.to_mm ?? lo),
                y1: Y(across) + 4, y2: Y(across) + 4 });
  for (const d of cur.defects) {
    const len = Math.max(3, X(d.board_x_mm + d.length_mm / 2) - X(d.board_x_mm - d.length_mm / 2));
    const hgt = Math.max(3, Y(d.y_mm + d.width_mm / 2) - Y(d.y_mm - d.width_mm / 2));
    const r = add("rect", { class: `defect d-${d.kind}`, x: X(d.board_x_mm) - len / 2,
                            y: Y(d.y_mm) - hgt / 2, width: len, height: hgt,
                            "data-kind": d.kind });
    const depth = Plot.finite(d.depth_um) ? `, ${num(d.depth_um, 0)} µm` : "";
    const title = document.createElementNS(ns, "title");
    title.textContent = `${d.kind.replace("_", " ")} at ${num(d.board_x_mm, 0)} mm: ` +
      `${num(d.length_mm, 1)} x ${num(d.width_mm, 1)} mm${depth} (pair ${d.seq})`;
    r.append(title);
  }
  add("text", { x: X(lo), y: h - 4 }, "0 mm");
  add("text", { x: X(hi), y: h - 4, "text-anchor": "end" }, `${num(hi, 0)} mm along the board`);
}

function drawFeed() {
  const t = feedHistory.map((r) => r.t);
  Plot.lines($("feed-chart"), { series: [
    { x: t, y: feedHistory.map((r) => r.set), cls: "setpoint" },
    { x: t, y: feedHistory.map((r) => r.act), cls: "actual" },
  ], xlabel: "service time (s): setpoint (blue), actual (orange)", ylabel: "feed (mm/s)",
  minspan: 20 });
}

function drawEvents(events) {
  const list = $("events");
  const key = events.length ? `${events.length}:${events[events.length - 1].t_s}:${events[events.length - 1].text}` : "";
  if (list.dataset.key === key) return;
  list.dataset.key = key;
  list.replaceChildren(...events.slice().reverse().map((e) => {
    const li = document.createElement("li");
    li.className = `ev ${e.kind}`;
    li.textContent = `t=${num(e.t_s, 3)} s  ${e.head ? e.head + ": " : ""}${e.text}`;
    return li;
  }));
}

function headRow(h, machine) {
  // one row of the heads' table: what the head does now
  const s = h.status, last = h.last;
  const setpoints = (machine && machine.spindle_setpoints_rpm) || {};
  const rpm = h.plc && Plot.finite(h.plc.spindle_rpm) ? h.plc.spindle_rpm : h.rpm;
  const sp = Plot.finite(setpoints[h.name]) ? ` (set ${num(setpoints[h.name], 0)})` : "";
  const knives = h.plc && Plot.finite(h.plc.knives) ? h.plc.knives : h.knives;
  const offsets = s ? s.offsets_um.map((v) => num(v, 1)).join(" ") : "-";
  const grade = h.board && h.board.current ? String(h.board.current.grade) : "-";
  const state = !s ? "no service" : s.state === "run" ? "RUN"
    : `SAFE ${s.safe_reason || s.missing.join(", ")}`;
  const limiting = machine && (machine.limiting || []).includes(h.name) ? " (sets the feed)" : "";
  return { cls: `head ${s ? s.state : "unknown"}`, cells: [
    [`${h.name}${limiting}`, "name"], [h.face || "-", "face"], [state, "state"],
    [last ? num(last.pitch_mm, 3) : "-", "pitch"], [num(h.target_pitch_mm, 2), "target"],
    [last ? num(last.uniformity_cv, 3) : "-", "cv"], [`${num(rpm, 0)}${sp}`, "rpm"],
    [knives ?? "-", "knives"], [offsets, "offsets"], [grade, "board-grade"]] };
}

function drawHeads(heads, machine) {
  const box = $("heads");
  box.hidden = !heads;
  if (!heads) return;
  if (!heads.some((h) => h.name === selectedHead)) selectedHead = heads[0].name;
  setText("machine-feed", machine && Plot.finite(machine.feed_mm_s)
    ? `feed ${num(machine.feed_mm_s, 1)} mm/s` : "");
  const body = $("heads-table").tBodies[0];
  body.replaceChildren(...heads.map((h) => {
    const row = headRow(h, machine);
    const tr = document.createElement("tr");
    tr.className = row.cls + (h.name === selectedHead ? " selected" : "");
    tr.dataset.head = h.name;
    for (const [text, cls] of row.cells) {
      const td = document.createElement("td");
      td.className = cls;
      td.textContent = String(text);
      tr.append(td);
    }
    return tr;
  }));
  const tabs = $("head-tabs");
  const key = heads.map((h) => h.name).join(",") + ":" + selectedHead;
  if (tabs.dataset.key === key) return;
  tabs.dataset.key = key;
  tabs.replaceChildren(...heads.map((h) => {
    const b = document.createElement("button");
    b.type = "button";
    b.dataset.head = h.name;
    b.className = h.name === selectedHead ? "selected" : "";
    b.textContent = `${h.name} (${h.face || "-"})`;
    b.addEventListener("click", () => {
      selectedHead = h.name;
      if (lastSnap) { lastVersion = -1; draw(lastSnap); }
    });
    return b;
  }));
}

function draw(full) {
  if (full.version === lastVersion) return;
  lastVersion = full.version;
  lastSnap = full;
  drawHeads(full.heads, full.machine);
  // a moulder: the panels below show the selected head (its status, pairs, board strip)
  const head = full.heads ? full.heads.find((h) => h.name === selectedHead) : null;
  const snap = head ? { ...full, status: head.status, last: head.last, trace: head.trace,
    quality_class: head.quality_class, board: head.board } : full;
  for (const h of full.heads || []) {
    if (h !== head) recordFeed(feedHistories[h.name] ||= [], h.status);
  }
  feedHistory = feedHistories[head ? head.name : ""] ||= [];
  document.body.dataset.head = head ? head.name : "";
  const qc = snap.quality_class;
  drawState(snap.status);
  drawNow(snap.last, qc);
  drawProfile(snap.last);
  drawTraces(snap.trace || [], qc);
  drawKnives(snap.last, snap.status);
  drawKnifeCondition(snap.status);
  drawBoardStrip(snap.board);
  drawFeed();
  drawEvents(snap.events || []);
  document.body.dataset.version = String(full.version);
}

function connect() {
  const link = $("link");
  const source = new EventSource("/api/live/stream");
  source.onopen = () => { link.className = "link up"; link.textContent = "live"; };
  source.onerror = () => { link.className = "link down"; link.textContent = "reconnecting"; };
  source.onmessage = (msg) => {
    try {
      draw(JSON.parse(msg.data));
    } catch (err) {
      link.textContent = `display error: ${err}`;
    }
  };
}

window.addEventListener("DOMContentLoaded", connect);

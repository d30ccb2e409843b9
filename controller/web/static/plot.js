// Small SVG charts for the smart-planer pages (no library, no network).
// Plot.lines(svg, opts) draws line/point series with an optional band and limit lines;
// Plot.bars(svg, opts) draws one bar per value around zero. Both redraw the whole SVG.
"use strict";

const Plot = (() => {
  const NS = "http://www.w3.org/2000/svg";
  const PAD = { l: 52, r: 10, t: 8, b: 30 };

  function el(name, attrs, parent) {
    const e = document.createElementNS(NS, name);
    for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
    if (parent) parent.appendChild(e);
    return e;
  }

  function clear(svg) {
    while (svg.firstChild) svg.removeChild(svg.firstChild);
    const w = svg.clientWidth || Number(svg.getAttribute("width")) || 400;
    const h = svg.clientHeight || Number(svg.getAttribute("height")) || 160;
    svg.setAttribute("viewBox", `0 0 ${w} ${h}`);
    return { w, h };
  }

  function finite(v) { return v !== null && v !== undefined && Number.isFinite(v); }

  function niceTicks(lo, hi, n) {
    const span = hi - lo || Math.abs(hi) || 1;
    const step0 = span / Math.max(1, n);
    const mag = Math.pow(10, Math.floor(Math.log10(step0)));
    const step = [1, 2, 2.5, 5, 10].map((m) => m * mag).find((s) => s >= step0) || step0;
    const out = [];
    for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) out.push(v);
    return out;
  }

  function stepFmt(lo, hi, n) {
    // labels with just enough decimals for the tick step
    const ticks = niceTicks(lo, hi, n);
    const step = ticks.length > 1 ? ticks[1] - ticks[0] : Math.abs(hi - lo) || 1;
    const digits = Math.min(6, Math.max(0, -Math.floor(Math.log10(step) + 1e-9)));
    return { ticks, label: (v) => (Math.abs(v) < step * 1e-6 ? "0" : v.toFixed(digits)) };
  }

  function fmt(v) {
    const a = Math.abs(v);
    if (a === 0) return "0";
    if (a >= 100) return v.toFixed(0);
    if (a >= 10) return v.toFixed(1);
    if (a >= 1) return v.toFixed(2);
    return v.toPrecision(2);
  }

  function frame(svg, xr, yr, opts) {
    const { w, h } = clear(svg);
    const X = (x) => PAD.l + ((x - xr[0]) / (xr[1] - xr[0] || 1)) * (w - PAD.l - PAD.r);
    const Y = (y) => h - PAD.b - ((y - yr[0]) / (yr[1] - yr[0] || 1)) * (h - PAD.t - PAD.b);
    const axes = el("g", { class: "axes" }, svg);
    const yt = stepFmt(yr[0], yr[1], 4);
    for (const t of yt.ticks) {
      el("line", { x1: PAD.l, x2: w - PAD.r, y1: Y(t), y2: Y(t), class: "grid" }, axes);
      el("text", { x: PAD.l - 4, y: Y(t) + 4, "text-anchor": "end" }, axes).textContent = yt.label(t);
    }
    const xt = stepFmt(xr[0], xr[1], 6);
    for (const t of opts.noxticks ? [] : xt.ticks) {
      el("text", { x: X(t), y: h - PAD.b + 14, "text-anchor": "middle" }, axes).textContent = xt.label(t);
    }
    el("rect", { x: PAD.l, y: PAD.t, width: w - PAD.l - PAD.r, height: h - PAD.t - PAD.b,
      class: "plotarea" }, axes);
    if (opts.xlabel) {
      el("text", { x: (PAD.l + w - PAD.r) / 2, y: h - 3, "text-anchor": "middle", class: "label" },
        axes).textContent = opts.xlabel;
    }
    if (opts.ylabel) {
      el("text", { x: 12, y: (PAD.t + h - PAD.b) / 2, "text-anchor": "middle", class: "label",
        transform: `rotate(-90 12 ${(PAD.t + h - PAD.b) / 2})` }, axes).textContent = opts.ylabel;
    }
    return { X, Y, w, h };
  }

  function range(values, extra, minspan) {
    const v = values.filter(finite).concat((extra || []).filter(finite));
    if (!v.length) return [0, 1];
    let lo = Math.min(...v), hi = Math.max(...v);
    if (minspan && hi - lo < minspan) {
      const mid = (lo + hi) / 2;
      lo = mid - minspan / 2; hi = mid + minspan / 2;
    }
    if (lo === hi) { lo -= Math.abs(lo) * 0.1 || 1; hi += Math.abs(hi) * 0.1 || 1; }
    const m = (hi - lo) * 0.05;
    return [lo - m, hi + m];
  }

  // opts: {series: [{x, y, cls, points}], band: {lo, hi, cls}, hlines: [{y, cls}],
  //        spans: [{x0, x1, cls}], labels: [{x, y, text, cls}], xlabel, ylabel, xrange, yrange,
  //        minspan (smallest y range drawn)}
  function lines(svg, opts) {
    const xs = [], ys = [];
    for (const s of opts.series) { xs.push(...s.x); ys.push(...s.y); }
    const lim = [];
    if (opts.band) lim.push(opts.band.lo, opts.band.hi);
    for (const l of opts.hlines || []) lim.push(l.y);
    const xr = opts.xrange || range(xs);
    const yr = opts.yrange || range(ys, lim, opts.minspan);
    const { X, Y } = frame(svg, xr, yr, opts);
    const clip = (y) => Math.min(Math.max(y, yr[0]), yr[1]);
    for (const s of opts.spans || []) {
      el("rect", { x: X(s.x0), y: Y(yr[1]), width: Math.max(1, X(s.x1) - X(s.x0)),
        height: Y(yr[0]) - Y(yr[1]), class: s.cls || "span" }, svg);
    }
    if (opts.band && finite(opts.band.lo) && finite(opts.band.hi)) {
      el("rect", { x: X(xr[0]), width: X(xr[1]) - X(xr[0]), y: Y(clip(opts.band.hi)),
        height: Math.max(0, Y(clip(opts.band.lo)) - Y(clip(opts.band.hi))),
        class: opts.band.cls || "band" }, svg);
    }
    for (const l of opts.hlines || []) {
      if (finite(l.y)) {
        el("line", { x1: X(xr[0]), x2: X(xr[1]), y1: Y(l.y), y2: Y(l.y), class: l.cls || "limit" },
          svg);
      }
    }
    for (const s of opts.series) {
      let d = "", pen = false;
      for (let i = 0; i < s.x.length; i++) {
        if (!finite(s.x[i]) || !finite(s.y[i])) { pen = false; continue; }
        d += `${pen ? "L" : "M"}${X(s.x[i]).toFixed(1)},${Y(s.y[i]).toFixed(1)}`;
        pen = true;
      }
      el("path", { d, class: `line ${s.cls || ""}` }, svg);
      if (s.points) {
        for (let i = 0; i < s.x.length; i++) {
          if (finite(s.x[i]) && finite(s.y[i])) {
            el("circle", { cx: X(s.x[i]), cy: Y(s.y[i]), r: 2.5, class: `pt ${s.cls || ""}` }, svg);
          }
        }
      }
    }
    for (const l of opts.labels || []) {
      if (finite(l.x) && finite(l.y)) {
        el("text", { x: X(l.x), y: Y(l.y), "text-anchor": "middle", class: l.cls || "mark-label" },
          svg).textContent = l.text;
      }
    }
  }

  // opts: {values: [...], labels: [...], cls: [...] or string, ylabel, yrange}
  function bars(svg, opts) {
    const n = opts.values.length;
    const yr = opts.yrange || range(opts.values, [0]);
    const { X, Y } = frame(svg, [0, Math.max(1, n)], yr, { ylabel: opts.ylabel, noxticks: true });
    const y0 = Y(Math.min(Math.max(0, yr[0]), yr[1]));
    for (let i = 0; i < n; i++) {
      const v = opts.values[i];
      const x = X(i + 0.15), bw = X(i + 0.85) - X(i + 0.15);
      const cls = Array.isArray(opts.cls) ? opts.cls[i] : (opts.cls || "bar");
      if (finite(v)) {
        const y = Y(v);
        el("rect", { x, width: bw, y: Math.min(y, y0), height: Math.max(1, Math.abs(y0 - y)),
          class: cls }, svg);
      }
      el("text", { x: x + bw / 2, y: Y(yr[0]) + 14, "text-anchor": "middle" }, svg).textContent =
        opts.labels ? opts.labels[i] : String(i);
    }
  }

  return { lines, bars, fmt, finite };
})();

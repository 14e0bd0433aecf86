// Small canvas plots: line plot, bar chart, top-down map. Each also sets an aria-label with
// the key numbers so the plot is not only visual.

function setup(canvas, cssW, cssH) {
  const dpr = window.devicePixelRatio || 1;
  canvas.width = Math.round(cssW * dpr);
  canvas.height = Math.round(cssH * dpr);
  canvas.style.width = `${cssW}px`;
  canvas.style.height = `${cssH}px`;
  const ctx = canvas.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.clearRect(0, 0, cssW, cssH);
  ctx.font = "12px system-ui, sans-serif";
  return ctx;
}

function niceTicks(lo, hi, n = 5) {
  const span = hi - lo || 1;
  const step0 = span / n;
  const mag = 10 ** Math.floor(Math.log10(step0));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => span / s <= n) || 10 * mag;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9; v += step) out.push(+v.toFixed(10));
  return out;
}

/**
 * points: [[x, y], ...]; opts: {xLabel, yLabel, yMin, yMax, marker: [x, y]}; `label`: the
 * main curve's legend entry; `series`: more curves on the same axes, [{points, color, label,
 * dash: [on, off], dots}] (drawn under the main curve; a legend row above the plot).
 */
export function linePlot(canvas, points, { xLabel = "", yLabel = "", xMin = null, yMin = null, yMax = null, marker = null, markerLabel = "", dots = false, width = 460, height = 260, yFmt = (v) => v, label = "", series = [], xInteger = false } = {}) {
  const ctx = setup(canvas, width, height);
  const legend = [{ label, color: "#0a66c2", dash: [] }, ...series].filter((e) => e.label && (label || series.length));
  // a legend takes one row above the plot area, so it never hides a curve
  const m = { l: 52, r: 12, t: legend.length ? 28 : 12, b: 40 };
  const W = width - m.l - m.r;
  const H = height - m.t - m.b;
  if (!points.length) {
    ctx.fillText("no data", m.l + 10, m.t + 20);
    return;
  }
  const all = points.concat(...series.map((s) => s.points || []));
  const xs = all.map((p) => p[0]);
  const ys = all.map((p) => p[1]);
  // x axis from xMin (or the data) to a tick at or beyond the last point, so the curve and
  // its end marker stay inside the plot
  const x0 = Math.min(xMin ?? Infinity, ...xs, ...(marker ? [marker[0]] : []));
  const xTop = Math.max(...xs, ...(marker ? [marker[0]] : []));
  const xt = niceTicks(x0, xTop > x0 ? xTop : x0 + 1);
  const x1 = xt.length && xt[xt.length - 1] >= xTop ? xt[xt.length - 1] : xTop + (xt.length > 1 ? xt[1] - xt[0] : 1);
  const y0 = yMin ?? Math.min(...ys), y1 = yMax ?? Math.max(...ys);
  const X = (x) => m.l + ((x - x0) / (x1 - x0 || 1)) * W;
  const Y = (y) => m.t + H - ((y - y0) / (y1 - y0 || 1)) * H;
  ctx.strokeStyle = "#bbb";
  ctx.fillStyle = "#333";
  ctx.lineWidth = 1;
  for (const t of niceTicks(y0, y1)) {
    ctx.beginPath();
    ctx.moveTo(m.l, Y(t));
    ctx.lineTo(m.l + W, Y(t));
    ctx.stroke();
    ctx.textAlign = "right";
    ctx.fillText(String(yFmt(t)), m.l - 4, Y(t) + 4);
  }
  ctx.textAlign = "center";
  for (const t of niceTicks(x0, x1)) if (t <= x1 + 1e-9 && (!xInteger || Number.isInteger(t))) ctx.fillText(String(t), X(t), m.t + H + 14);
  ctx.fillText(xLabel, m.l + W / 2, height - 6);
  ctx.save();
  ctx.translate(12, m.t + H / 2);
  ctx.rotate(-Math.PI / 2);
  ctx.fillText(yLabel, 0, 0);
  ctx.restore();
  for (const s of series) {
    if (!s.points || !s.points.length) continue;
    ctx.strokeStyle = s.color || "#888";
    ctx.lineWidth = 2;
    ctx.setLineDash(s.dash || []);
    ctx.beginPath();
    s.points.forEach(([x, y], i) => (i ? ctx.lineTo(X(x), Y(y)) : ctx.moveTo(X(x), Y(y))));
    ctx.stroke();
    ctx.setLineDash([]);
    if (s.dots) {
      ctx.fillStyle = s.color || "#888";
      for (const [x, y] of s.points) {
        ctx.beginPath();
        ctx.arc(X(x), Y(y), 2.5, 0, Math.PI * 2);
        ctx.fill();
      }
    }
  }
  ctx.strokeStyle = "#0a66c2";
  ctx.lineWidth = 2;
  ctx.beginPath();
  points.forEach(([x, y], i) => (i ? ctx.lineTo(X(x), Y(y)) : ctx.moveTo(X(x), Y(y))));
  ctx.stroke();
  let lx = m.l;
  ctx.textAlign = "left";
  for (const e of legend) {
    ctx.strokeStyle = e.color || "#888";
    ctx.setLineDash(e.dash || []);
    ctx.beginPath();
    ctx.moveTo(lx, 10);
    ctx.lineTo(lx + 22, 10);
    ctx.stroke();
    ctx.setLineDash([]);
    ctx.fillStyle = "#333";
    ctx.fillText(e.label, lx + 28, 14);
    lx += 28 + ctx.measureText(e.label).width + 18;
  }
  if (dots) {
    ctx.fillStyle = "#0a66c2";
    for (const [x, y] of points) {
      ctx.beginPath();
      ctx.arc(X(x), Y(y), 3, 0, Math.PI * 2);
      ctx.fill();
    }
  }
  canvas.dataset.x0 = String(x0);
  canvas.dataset.x1 = String(x1);
  canvas.dataset.first = JSON.stringify(points[0]);
  if (marker) {
    ctx.fillStyle = "#d93025";
    ctx.beginPath();
    ctx.arc(X(marker[0]), Y(marker[1]), 5, 0, Math.PI * 2);
    ctx.fill();
    if (markerLabel) {
      ctx.textAlign = X(marker[0]) > m.l + W / 2 ? "right" : "left";
      ctx.fillText(markerLabel, X(marker[0]) + (ctx.textAlign === "left" ? 8 : -8), Y(marker[1]) + 16);
    }
  }
  canvas.setAttribute("role", "img");
  const ends = (p) => `from ${yFmt(p[0][1])} at ${p[0][0]} to ${yFmt(p[p.length - 1][1])} at ${p[p.length - 1][0]}`;
  const more = series.filter((s) => s.points && s.points.length).map((s) => `; ${s.label || "other"}: ${ends(s.points)}`).join("");
  canvas.setAttribute("aria-label", `${yLabel} vs ${xLabel}: ${label ? `${label}: ` : ""}${ends(points)}${more}`);
}

/** bars: [{label, value, color}] (horizontal bars, log-free, sorted as given). */
export function barPlot(canvas, bars, { width = 460, valueFmt = (v) => v.toLocaleString(), title = "" } = {}) {
  const rowH = 18;
  const height = Math.max(40, bars.length * rowH + 24);
  const ctx = setup(canvas, width, height);
  const labelW = 120;
  const max = Math.max(1, ...bars.map((b) => b.value));
  const W = width - labelW - 80;
  bars.forEach((b, i) => {
    const y = 8 + i * rowH;
    ctx.fillStyle = "#333";
    ctx.textAlign = "right";
    ctx.fillText(b.label, labelW - 6, y + 12);
    ctx.fillStyle = b.color || "#0a66c2";
    ctx.fillRect(labelW, y + 2, Math.max(1, (b.value / max) * W), rowH - 5);
    ctx.strokeStyle = "#666";
    ctx.strokeRect(labelW, y + 2, Math.max(1, (b.value / max) * W), rowH - 5);
    ctx.fillStyle = "#333";
    ctx.textAlign = "left";
    ctx.fillText(valueFmt(b.value), labelW + Math.max(1, (b.value / max) * W) + 4, y + 12);
  });
  canvas.setAttribute("role", "img");
  canvas.setAttribute("aria-label", `${title}: ` + bars.map((b) => `${b.label} ${valueFmt(b.value)}`).join(", "));
}

/** Normalise a selection "cell" entry into {x0, y0, x1, y1} (or null). */
export function cellRect(c, edge = null) {
  if (Array.isArray(c)) {
    if (c.length >= 4) return { x0: Math.min(c[0], c[2]), y0: Math.min(c[1], c[3]), x1: Math.max(c[0], c[2]), y1: Math.max(c[1], c[3]) };
    if (c.length === 2 && edge) return { x0: c[0] - edge / 2, y0: c[1] - edge / 2, x1: c[0] + edge / 2, y1: c[1] + edge / 2 };
    return null;
  }
  if (c && typeof c === "object") {
    if ("x0" in c) return { x0: c.x0, y0: c.y0, x1: c.x1, y1: c.y1 };
    if ("xmin" in c) return { x0: c.xmin, y0: c.ymin, x1: c.xmax, y1: c.ymax };
    if (c.bounds) return cellRect(c.bounds, edge);
    const ctr = c.center || c.centre;
    const e = c.size ?? c.edge ?? edge;
    if (ctr && e) return { x0: ctr[0] - e / 2, y0: ctr[1] - e / 2, x1: ctr[0] + e / 2, y1: ctr[1] + e / 2 };
  }
  return null;
}

/**
 * Top-down map: cameras [[x, y]], selected: Set of indices into cameras, cells: rects.
 * Equal axis scale, +y up.
 */
export function mapPlot(canvas, { cameras = [], selected = new Set(), cells = [], lattice = null, width = 460, height = 400 } = {}) {
  const ctx = setup(canvas, width, height);
  const pts = cameras.filter((p) => Array.isArray(p) && p.length >= 2);
  const xs = pts.map((p) => p[0]).concat(cells.flatMap((c) => [c.x0, c.x1]));
  const ys = pts.map((p) => p[1]).concat(cells.flatMap((c) => [c.y0, c.y1]));
  if (!xs.length) {
    ctx.fillText("no cameras", 10, 20);
    return;
  }
  const x0 = Math.min(...xs), x1 = Math.max(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
  const pad = 16;
  const s = Math.min((width - 2 * pad) / (x1 - x0 || 1), (height - 2 * pad) / (y1 - y0 || 1));
  const X = (x) => pad + (x - x0) * s;
  const Y = (y) => height - pad - (y - y0) * s;
  ctx.strokeStyle = "rgba(0,0,0,0.35)";
  ctx.lineWidth = 1;
  for (const c of cells) ctx.strokeRect(X(c.x0), Y(c.y1), (c.x1 - c.x0) * s, (c.y1 - c.y0) * s);
  if (lattice && lattice.edge > 0) {
    // grid lines every `edge` metres across the extent (cell geometry not sent by the API)
    ctx.setLineDash([4, 4]);
    ctx.beginPath();
    for (let x = x0; x <= x1 + 1e-6; x += lattice.edge) {
      ctx.moveTo(X(x), Y(y0));
      ctx.lineTo(X(x), Y(y1));
    }
    for (let y = y0; y <= y1 + 1e-6; y += lattice.edge) {
      ctx.moveTo(X(x0), Y(y));
      ctx.lineTo(X(x1), Y(y));
    }
    ctx.stroke();
    ctx.setLineDash([]);
  }
  cameras.forEach((p, i) => {
    if (!Array.isArray(p)) return;
    const sel = selected.has(i);
    ctx.fillStyle = sel ? "#d93025" : "rgba(10,102,194,0.45)";
    const r = sel ? 4 : 2;
    ctx.beginPath();
    ctx.arc(X(p[0]), Y(p[1]), r, 0, Math.PI * 2);
    ctx.fill();
  });
  ctx.fillStyle = "#333";
  ctx.fillText(`${cameras.length} cameras, ${selected.size} selected, ${cells.length || (lattice ? lattice.count : 0)} cells; ${(x1 - x0).toFixed(0)}×${(y1 - y0).toFixed(0)} m`, 6, 12);
  canvas.setAttribute("role", "img");
  canvas.setAttribute("aria-label", `Top-down map: ${cameras.length} camera positions, ${selected.size} selected frames (red), ${cells.length} grid cells`);
}

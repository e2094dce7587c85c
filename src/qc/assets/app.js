// fwlidar QC page. Plain JS, no external resources: polls the read-only API of the QC server
// (/api/status and /api/history every second, /api/waveform every 2 s) and draws the charts,
// the coverage map and the waveform on <canvas> itself.
"use strict";
(function () {
  const STATUS_MS = 1000;
  const WAVE_MS = 2000;
  const NAV_OLD_S = 1; // navigation age shown amber above this, seconds
  const NAV_STALE_S = 5; // and red above this, seconds
  const DATA_STALE_MS = 3500; // no new snapshot for this long: connection shown down

  const COLORS = ["#58a6ff", "#3fb950", "#f85149", "#d29922", "#bc8cff", "#39c5cf",
    "#ff7b72", "#e3b341", "#7ee787", "#a5d6ff", "#ffa657", "#d2a8ff"];
  const AXIS = "#8b949e";
  const GRID = "#21262d";

  const $ = (id) => document.getElementById(id);

  let status = null; // last snapshot
  let history = []; // history points, oldest first
  let wave = null; // last waveform view or null
  let lastSeq = -1;
  let lastSeqChange = 0; // Date.now() when the sequence last changed
  let lastOk = 0; // Date.now() of the last successful status fetch

  // ---- helpers -------------------------------------------------------------------------------

  function setText(id, text) {
    const el = $(id);
    if (el && el.textContent !== String(text)) el.textContent = String(text);
  }

  function el(tag, cls, text) {
    const e = document.createElement(tag);
    if (cls) e.className = cls;
    if (text !== undefined && text !== null) e.textContent = String(text);
    return e;
  }

  function replaceChildren(parent, children) {
    parent.replaceChildren(...children);
  }

  /** Integer as plain digits (the live numbers must parse as numbers). */
  function int(v) {
    return Number.isFinite(v) ? String(Math.round(v)) : "0";
  }

  /** A count with thin grouping for reading, not for ids. */
  function group(v) {
    if (!Number.isFinite(v)) return "–";
    return Math.round(v).toLocaleString("en-US").replace(/,/g, "\u2009");
  }

  function bytes(v) {
    if (!Number.isFinite(v)) return "–";
    const units = ["B", "kB", "MB", "GB", "TB", "PB"];
    let i = 0;
    while (v >= 1000 && i < units.length - 1) { v /= 1000; i++; }
    return (i === 0 ? v.toFixed(0) : v.toFixed(v < 10 ? 2 : 1)) + " " + units[i];
  }

  function duration(s) {
    if (!Number.isFinite(s)) return "–";
    s = Math.max(0, Math.floor(s));
    const d = Math.floor(s / 86400), h = Math.floor(s % 86400 / 3600);
    const m = Math.floor(s % 3600 / 60), sec = s % 60;
    const p2 = (x) => String(x).padStart(2, "0");
    return (d > 0 ? d + " d " : "") + p2(h) + ":" + p2(m) + ":" + p2(sec);
  }

  function latency(us) {
    if (!Number.isFinite(us)) return "–";
    if (us >= 1e6) return (us / 1e6).toFixed(2) + " s";
    if (us >= 1e3) return (us / 1e3).toFixed(us >= 1e4 ? 0 : 1) + " ms";
    return us.toFixed(us >= 10 ? 0 : 1) + " µs";
  }

  async function getJSON(url) {
    const r = await fetch(url, { cache: "no-store" });
    if (r.status === 204) return null;
    if (!r.ok) throw new Error(url + ": HTTP " + r.status);
    return r.json();
  }

  /** Sizes a canvas to its CSS box at the device pixel ratio; returns [ctx, width, height] in CSS px. */
  function prepare(canvas) {
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(50, canvas.clientWidth), h = Math.max(50, canvas.clientHeight);
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    ctx.font = "12px system-ui, sans-serif";
    ctx.textBaseline = "middle";
    return [ctx, w, h];
  }

  /** A "nice" step (1, 2, 5 × 10^k) near range / n. */
  function niceStep(range, n) {
    const raw = range / Math.max(1, n);
    const p = Math.pow(10, Math.floor(Math.log10(raw)));
    const f = raw / p;
    return (f < 1.5 ? 1 : f < 3.5 ? 2 : f < 7.5 ? 5 : 10) * p;
  }

  function tickLabel(v) {
    const a = Math.abs(v);
    if (a >= 1e6) return (v / 1e6).toFixed(a >= 1e7 ? 0 : 1) + "M";
    if (a >= 1e3) {
      // "12k" or "2.5k" when that is the exact tick; otherwise the whole number (6420, 6440).
      const k = v / 1e3;
      if (Math.abs(k * 10 - Math.round(k * 10)) < 1e-9) {
        return (Number.isInteger(k) ? String(k) : k.toFixed(1)) + "k";
      }
      return String(Math.round(v));
    }
    if (a === 0) return "0";
    if (a < 0.01) return v.toExponential(0);
    return String(Number(v.toPrecision(3)));
  }

  /** Lays the legend out in rows from (x0, 10) within maxX; returns the rows' height. */
  function legend(ctx, items, x0, maxX, draw) {
    let x = x0, y = 10;
    ctx.textAlign = "left";
    for (const it of items) {
      const wi = 24 + ctx.measureText(it.label).width;
      if (x > x0 && x + wi > maxX) { x = x0; y += 15; }
      if (draw) {
        ctx.fillStyle = it.color;
        ctx.fillRect(x, y - (it.dash ? 1 : 5), 12, it.dash ? 3 : 10);
        ctx.fillStyle = "#e6edf3";
        ctx.fillText(it.label, x + 16, y);
      }
      x += wi;
    }
    return y + 8;
  }

  // ---- time-series chart ---------------------------------------------------------------------

  /**
   * Draws series over time. opts: {t: [unix s], series: [{label, color, values}], unit,
   * log: bool, min0: bool, fmt: value → label}.
   */
  function lineChart(canvas, opts) {
    const [ctx, w, h] = prepare(canvas);
    const L = 54, R = 10, B = 22;
    const T = legend(ctx, opts.series, L + 40, w - R, false) + 6;
    const pw = w - L - R, ph = h - T - B;
    const t = opts.t;
    legend(ctx, opts.series, L + 40, w - R, true);
    if (t.length < 2) {
      ctx.fillStyle = AXIS;
      ctx.textAlign = "center";
      ctx.fillText("collecting history…", w / 2, h / 2);
      return;
    }
    const t1 = t[t.length - 1];
    const t0 = Math.min(t[0], t1 - 60);
    const tx = (v) => L + (v - t0) / (t1 - t0) * pw;

    let lo = Infinity, hi = -Infinity;
    for (const s of opts.series) {
      for (const v of s.values) {
        if (!Number.isFinite(v) || (opts.log && v <= 0)) continue;
        lo = Math.min(lo, v);
        hi = Math.max(hi, v);
      }
    }
    if (!Number.isFinite(lo)) { lo = opts.log ? 1 : 0; hi = opts.log ? 1000 : 1; }
    let ty, ticks = [];
    if (opts.log) {
      const a = Math.floor(Math.log10(lo)), b = Math.max(a + 1, Math.ceil(Math.log10(hi)));
      ty = (v) => T + ph - (Math.log10(Math.max(v, Math.pow(10, a))) - a) / (b - a) * ph;
      for (let k = a; k <= b; k++) ticks.push(Math.pow(10, k));
    } else {
      if (opts.min0) lo = Math.min(0, lo);
      if (opts.max !== undefined) hi = Math.max(hi, opts.max);
      if (hi - lo < 1e-9) hi = lo + 1;
      const step = niceStep(hi - lo, 4);
      lo = Math.floor(lo / step) * step;
      hi = Math.ceil(hi / step) * step;
      ty = (v) => T + ph - (v - lo) / (hi - lo) * ph;
      for (let v = lo; v <= hi + step / 2; v += step) ticks.push(v);
    }
    // Grid and axes.
    ctx.strokeStyle = GRID;
    ctx.lineWidth = 1;
    ctx.fillStyle = AXIS;
    ctx.textAlign = "right";
    for (const v of ticks) {
      const y = Math.round(ty(v)) + 0.5;
      ctx.beginPath(); ctx.moveTo(L, y); ctx.lineTo(L + pw, y); ctx.stroke();
      ctx.fillText((opts.fmt || tickLabel)(v), L - 6, y);
    }
    ctx.textAlign = "center";
    const span = t1 - t0;
    const tstep = niceStep(span, 5);
    for (let a = 0; a <= span + 1e-6; a += tstep) {
      const x = tx(t1 - a);
      ctx.beginPath(); ctx.moveTo(x, T); ctx.lineTo(x, T + ph); ctx.stroke();
      const label = a === 0 ? "now" : (a >= 60 ? "−" + Number((a / 60).toFixed(1)) + " min" : "−" + Math.round(a) + " s");
      ctx.fillText(label, Math.min(Math.max(x, L + 14), L + pw - 14), T + ph + 12);
    }
    if (opts.unit) {
      ctx.textAlign = "left";
      ctx.fillStyle = AXIS;
      ctx.fillText(opts.unit, 4, 10);
    }
    // Lines.
    ctx.save();
    ctx.beginPath(); ctx.rect(L, T, pw, ph); ctx.clip();
    for (const s of opts.series) {
      ctx.strokeStyle = s.color;
      ctx.lineWidth = s.width || 1.8;
      ctx.setLineDash(s.dash ? [5, 4] : []);
      ctx.beginPath();
      let pen = false;
      for (let i = 0; i < t.length; i++) {
        const v = s.values[i];
        if (!Number.isFinite(v) || (opts.log && v <= 0)) { pen = false; continue; }
        const x = tx(t[i]), y = ty(v);
        if (pen) ctx.lineTo(x, y); else ctx.moveTo(x, y);
        pen = true;
      }
      ctx.stroke();
    }
    ctx.restore();
    ctx.setLineDash([]);
  }

  function drawCharts() {
    const t = history.map((p) => p.t);
    lineChart($("chart-rates"), {
      t, unit: "/s", min0: true,
      series: [
        { label: "in", color: COLORS[0], values: history.map((p) => p.rate_in_hz) },
        { label: "processed", color: COLORS[1], values: history.map((p) => p.rate_processed_hz) },
        { label: "dropped", color: COLORS[2], values: history.map((p) => p.rate_dropped_hz) },
      ],
    });
    lineChart($("chart-queue"), {
      t, unit: "%", min0: true, max: 100,
      series: [{ label: "fullest queue", color: COLORS[3], values: history.map((p) => 100 * p.queue_fill) }],
    });
    const stages = status ? status.stages.map((s) => s.name) : [];
    const series = [
      { label: "e2e p50", color: COLORS[0], values: history.map((p) => p.e2e_p50_us), width: 2.5 },
      { label: "e2e p99", color: COLORS[2], values: history.map((p) => p.e2e_p99_us), width: 2.5 },
    ];
    stages.forEach((name, i) => series.push({
      label: name + " p99", color: COLORS[(i + 4) % COLORS.length], dash: true, width: 1.3,
      values: history.map((p) => (p.stage_p99_us || [])[i]),
    }));
    lineChart($("chart-latency"), { t, unit: "latency", log: true, series, fmt: latency });
  }

  // ---- status panels -------------------------------------------------------------------------

  function renderHeader(s) {
    setText("survey", s.survey || "–");
    setText("version", s.version || "–");
    setText("uptime", Math.floor(s.uptime_s || 0));
    setText("uptime-text", "(" + duration(s.uptime_s) + ")");
    setText("snapshot-seq", s.sequence);
    document.title = "fwlidar QC" + (s.survey ? " – " + s.survey : "");
  }

  function renderBig(s) {
    const p = s.pulses;
    setText("rate-in", int(p.rate_in_hz));
    setText("rate-processed", int(p.rate_processed_hz));
    setText("pulses-processed", int(p.pulses_processed));
    setText("pulses-in", group(p.pulses_in));
    setText("frames-lost", group(p.frames_lost));
    setText("frames-bad", group(p.frames_bad));
    setText("dropped-total", int(p.dropped_total));
    setText("rate-dropped", int(p.rate_dropped_hz));
    $("drops-box").classList.toggle("warn", p.dropped_total > 0 && p.rate_dropped_hz === 0);
    $("drops-box").classList.toggle("bad", p.rate_dropped_hz > 0);
    const reasons = Object.entries(s.drops || {}).sort((a, b) => b[1] - a[1]);
    replaceChildren($("drops"), reasons.map(([r, n]) => {
      const li = el("li");
      li.append(el("span", "", r), el("span", "", group(n)));
      return li;
    }));

    let fullest = 0;
    const rows = [];
    for (const q of s.queues || []) {
      const f = q.capacity > 0 ? q.len / q.capacity : 0;
      fullest = Math.max(fullest, f);
      const row = el("div", "qrow");
      const bar = el("div", "qbar" + (f > 0.9 ? " crit" : f > 0.5 ? " warn" : ""));
      const fill = el("div");
      fill.style.width = (100 * Math.min(1, f)).toFixed(1) + "%";
      bar.append(fill);
      row.append(el("span", "", q.name), bar, el("span", "", q.len + " / " + q.capacity));
      rows.push(row);
    }
    setText("queue-fill", int(100 * fullest));
    $("queue-box").classList.toggle("bad", fullest > 0.9);
    $("queue-box").classList.toggle("warn", fullest > 0.5 && fullest <= 0.9);
    replaceChildren($("queues"), rows);
  }

  function renderAlerts(s) {
    const alerts = s.alerts || [];
    const box = $("alerts");
    const count = $("alert-count");
    count.textContent = String(alerts.length);
    const crit = alerts.some((a) => a.severity === "critical");
    count.className = "count" + (crit ? " critical" : alerts.length ? " warning" : "");
    if (alerts.length === 0) {
      replaceChildren(box, [el("div", "ok", "No alerts")]);
      return;
    }
    const sorted = alerts.slice().sort((a, b) =>
      (a.severity === "critical" ? 0 : 1) - (b.severity === "critical" ? 0 : 1));
    replaceChildren(box, sorted.map((a) => {
      const sev = a.severity === "critical" ? "critical" : "warning";
      const row = el("div", "alert " + sev);
      row.dataset.kind = a.kind;
      row.append(el("span", "sev", a.severity), el("span", "kind", a.kind), el("span", "msg", a.message));
      return row;
    }));
  }

  function renderInputs(s) {
    replaceChildren($("inputs"), (s.inputs || []).map((i) => {
      const tr = el("tr");
      const name = el("td");
      name.append(el("div", "strong", i.name), el("div", "dim", i.detail));
      const age = i.last_data_age_s;
      tr.append(
        name,
        el("td", i.up ? "up" : "down", i.up ? "UP" : "DOWN"),
        el("td", "", age === null || age === undefined ? "never" : age.toFixed(1) + " s ago"),
        el("td", "", bytes(i.bytes)),
        el("td", "", group(i.connects)),
        el("td", i.failed_attempts > 0 ? "err" : "", group(i.failed_attempts)),
        el("td", i.last_error ? "err" : "dim", i.last_error || "–"),
      );
      return tr;
    }));
  }

  function renderNav(s) {
    const navs = s.nav || [];
    if (navs.length === 0) {
      replaceChildren($("nav"), [el("div", "none", "No navigation port")]);
      return;
    }
    replaceChildren($("nav"), navs.map((n) => {
      const age = n.last_packet_age_s;
      const has = age !== null && age !== undefined;
      const card = el("div", "navcard" + (!has || age > NAV_STALE_S ? " stale" : age > NAV_OLD_S ? " old" : ""));
      card.append(el("h3", "", "Port " + n.port));
      const ageLine = el("div");
      const ageNum = el("span", "age", has ? age.toFixed(1) : "");
      ageNum.id = "nav-age-" + n.port;
      ageLine.append(ageNum, el("span", "unit", has ? "s since last packet" : "no packet yet"));
      card.append(ageLine);
      const dl = el("dl", "kv");
      const kv = (k, v, cls) => { dl.append(el("dt", "", k), el("dd", cls || "", v)); };
      kv("Fix", (n.fix_name || "–") + (n.fix !== null && n.fix !== undefined ? " (" + n.fix + ")" : ""),
        n.fix === 0 ? "crit" : "");
      kv("Satellites", n.satellites === null || n.satellites === undefined ? "–" : n.satellites,
        n.satellites !== null && n.satellites < 6 ? "warn" : "");
      kv("INS", (n.ins_name || "–") + (n.ins_status !== null && n.ins_status !== undefined ? " (" + n.ins_status + ")" : ""));
      if (n.position) {
        kv("Position", n.position[0].toFixed(6) + "°, " + n.position[1].toFixed(6) + "°, " + n.position[2].toFixed(1) + " m");
      }
      if (n.last_gps_sow !== null && n.last_gps_sow !== undefined) kv("GPS SOW", n.last_gps_sow.toFixed(2) + " s");
      kv("Samples", group(n.samples));
      kv("Rejected", group(n.rejected), n.rejected > 0 ? "warn" : "");
      card.append(dl);
      return card;
    }));
  }

  function renderKv(id, rows) {
    replaceChildren($(id), rows.flatMap(([k, v, cls]) => [el("dt", "", k), el("dd", cls || "", v)]));
  }

  function renderSystem(s) {
    const r = s.recording || {}, d = s.disk || {};
    const pct = d.total_bytes > 0 ? 100 * d.free_bytes / d.total_bytes : NaN;
    renderKv("recording", [
      ["Segment", r.segment || "–"],
      ["Written", bytes(r.bytes) + ", " + group(r.records) + " records, " + group(r.nav_records) + " nav records"],
      ["Recording error", r.error || "none", r.error ? "crit" : ""],
      ["Frames", "received " + group(s.pulses.frames_received) + ", recorded " + group(s.pulses.frames_recorded)],
      ["Disk", d.path || "–"],
      ["Free", bytes(d.free_bytes) + " of " + bytes(d.total_bytes) + (Number.isFinite(pct) ? " (" + pct.toFixed(1) + " %)" : ""),
        d.alarm ? "crit" : ""],
      ["Time left", d.seconds_left === null || d.seconds_left === undefined ? "–" : duration(d.seconds_left),
        d.alarm ? "crit" : ""],
    ]);
    const g = s.georeference || {}, sat = s.saturation || {};
    const missed = Object.entries(g.missed || {}).map(([k, v]) => k + " " + group(v)).join(", ");
    renderKv("georef", [
      ["Georeferencing", g.enabled ? "on" : "off"],
      ["CRS", g.crs || "–"],
      ["Placed", group(g.placed)],
      ["Missed", missed || "none", missed ? "warn" : ""],
      ["Saturated pulses", group(sat.pulses)],
      ["Saturated now", Number.isFinite(sat.recent_fraction) ? (100 * sat.recent_fraction).toFixed(2) + " %" : "–",
        sat.recent_fraction > 0.01 ? "crit" : sat.recent_fraction > 0 ? "warn" : ""],
      ["End-to-end latency", "p50 " + latency(s.end_to_end.p50_us) + ", p99 " + latency(s.end_to_end.p99_us) +
        ", max " + latency(s.end_to_end.max_us)],
    ]);
  }

  // ---- coverage map --------------------------------------------------------------------------

  function drawCoverage(s) {
    const canvas = $("coverage");
    const [ctx, w, h] = prepare(canvas);
    const tiles = s.tiles || { cells: [] };
    const cells = tiles.cells || [];
    setText("tiles-open", tiles.open || 0);
    setText("tiles-closed", tiles.closed || 0);
    const tm = tiles.tile_m || [0, 0];
    setText("tile-size", tm[0] > 0 ? tm[0] + " × " + tm[1] : "–");
    canvas.dataset.cells = String(cells.length);
    let dmax = 0;
    for (const c of cells) dmax = Math.max(dmax, c.density_per_m2 || 0);
    setText("density-max", dmax >= 10 ? dmax.toFixed(0) : dmax > 0 ? dmax.toPrecision(2) : "0");
    let hmax = null;
    for (const c of cells) {
      if (typeof c.canopy_height_m === "number") hmax = hmax === null ? c.canopy_height_m : Math.max(hmax, c.canopy_height_m);
    }
    setText("canopy-max", hmax === null ? "–" : hmax.toFixed(1));
    if (cells.length === 0) {
      ctx.fillStyle = AXIS;
      ctx.textAlign = "center";
      ctx.fillText("no tiles yet", w / 2, h / 2);
      return;
    }
    let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
    for (const c of cells) {
      x0 = Math.min(x0, c.tx); x1 = Math.max(x1, c.tx);
      y0 = Math.min(y0, c.ty); y1 = Math.max(y1, c.ty);
    }
    const pad = 28;
    const nx = x1 - x0 + 1, ny = y1 - y0 + 1;
    const aspect = tm[0] > 0 && tm[1] > 0 ? tm[1] / tm[0] : 1; // tile height / width
    const cw = Math.min(60, (w - 2 * pad) / nx, (h - 2 * pad) / (ny * aspect));
    const ch = cw * aspect;
    const ox = (w - cw * nx) / 2, oy = (h - ch * ny) / 2;
    for (const c of cells) {
      const x = ox + (c.tx - x0) * cw;
      const y = oy + (y1 - c.ty) * ch; // north up
      const shade = dmax > 0 ? 0.2 + 0.8 * Math.min(1, (c.density_per_m2 || 0) / dmax) : 0.6;
      const open = c.state === "open";
      ctx.globalAlpha = shade;
      ctx.fillStyle = open ? "#58a6ff" : "#3fb950";
      ctx.fillRect(x + 1, y + 1, cw - 2, ch - 2);
      ctx.globalAlpha = 1;
      if (open && cw > 6) {
        ctx.strokeStyle = "#a5d6ff";
        ctx.lineWidth = 1.5;
        ctx.strokeRect(x + 1.5, y + 1.5, cw - 3, ch - 3);
      }
      // The tile's highest canopy (m), where the chain computes forest metrics.
      if (typeof c.canopy_height_m === "number" && cw >= 24 && ch >= 14) {
        ctx.fillStyle = "#e6edf3";
        ctx.textAlign = "center";
        ctx.fillText(c.canopy_height_m.toFixed(0), x + cw / 2, y + ch / 2 + 4);
      }
    }
    // Tile index range.
    ctx.fillStyle = AXIS;
    ctx.textAlign = "left";
    ctx.fillText("tx " + x0 + "…" + x1 + ", ty " + y0 + "…" + y1, 6, 12);
    // North arrow.
    ctx.textAlign = "center";
    ctx.fillStyle = "#e6edf3";
    ctx.fillText("N", w - 16, 12);
    ctx.beginPath(); ctx.moveTo(w - 16, 20); ctx.lineTo(w - 21, 32); ctx.lineTo(w - 11, 32); ctx.closePath(); ctx.fill();
    // Scale bar in metres.
    if (tm[0] > 0) {
      const pxPerM = cw / tm[0];
      const metres = niceStep(w * 0.25 / pxPerM, 1);
      const len = metres * pxPerM;
      const bx = 10, by = h - 12;
      ctx.strokeStyle = "#e6edf3";
      ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.moveTo(bx, by - 4); ctx.lineTo(bx, by); ctx.lineTo(bx + len, by); ctx.lineTo(bx + len, by - 4);
      ctx.stroke();
      ctx.textAlign = "left";
      ctx.fillText(metres >= 1000 ? metres / 1000 + " km" : metres + " m", bx + len + 6, by - 2);
    }
  }

  // ---- waveform ------------------------------------------------------------------------------

  function drawWaveform() {
    const canvas = $("waveform");
    const [ctx, w, h] = prepare(canvas);
    if (!wave || !wave.steps || wave.steps.length === 0) {
      ctx.fillStyle = AXIS;
      ctx.textAlign = "center";
      ctx.fillText("no waveform sampled yet", w / 2, h / 2);
      setText("wave-info", "No waveform yet");
      canvas.dataset.pulseId = "";
      return;
    }
    canvas.dataset.pulseId = String(wave.pulse_id);
    const norm = $("wave-normalise").checked;
    const dt = wave.sample_ns || 1;
    const n = Math.max(...wave.steps.map((s) => s.values.length));
    const ta = wave.start_ns, tb = wave.start_ns + Math.max(1, n - 1) * dt;
    const peak = (vals) => vals.reduce((m, v) => Math.max(m, Math.abs(v)), 0) || 1;
    const gauss = (t) => wave.returns.reduce((acc, r) =>
      acc + r.amplitude * Math.exp(-0.5 * Math.pow((t - r.time_ns) / (r.sigma_ns || 1), 2)), 0);
    // The Gaussians were fitted to the last step's signal; normalised, they share its scale.
    const lastScale = norm ? 1 / peak(wave.steps[wave.steps.length - 1].values) : 1;
    const series = wave.steps.map((s, i) => ({
      label: s.name, color: COLORS[i % COLORS.length],
      scale: norm ? 1 / peak(s.values) : 1, values: s.values,
    }));
    let lo = 0, hi = 0;
    for (const s of series) for (const v of s.values) { lo = Math.min(lo, v * s.scale); hi = Math.max(hi, v * s.scale); }
    const fine = 400;
    const model = [];
    for (let k = 0; k <= fine; k++) {
      const t = ta + (tb - ta) * k / fine;
      const v = gauss(t) * lastScale;
      model.push([t, v]);
      lo = Math.min(lo, v); hi = Math.max(hi, v);
    }
    if (hi - lo < 1e-12) hi = lo + 1;
    const legendItems = series.slice();
    if (wave.returns.length > 0) {
      legendItems.push({ label: "fitted Gaussians (" + wave.returns.length + ")", color: "#ffffff", dash: true });
    }
    const L = 54, R = 10, B = 30;
    const T = legend(ctx, legendItems, L + 70, w - R, true) + 6;
    const pw = w - L - R, ph = h - T - B;
    const step = niceStep(hi - lo, 5);
    lo = Math.floor(lo / step) * step; hi = Math.ceil(hi / step) * step;
    const X = (t) => L + (t - ta) / (tb - ta) * pw;
    const Y = (v) => T + ph - (v - lo) / (hi - lo) * ph;
    ctx.strokeStyle = GRID; ctx.lineWidth = 1; ctx.fillStyle = AXIS; ctx.textAlign = "right";
    for (let v = lo; v <= hi + step / 2; v += step) {
      const y = Math.round(Y(v)) + 0.5;
      ctx.beginPath(); ctx.moveTo(L, y); ctx.lineTo(L + pw, y); ctx.stroke();
      ctx.fillText(tickLabel(v), L - 6, y);
    }
    const xs = niceStep(tb - ta, 8);
    ctx.textAlign = "center";
    for (let t = Math.ceil(ta / xs) * xs; t <= tb + 1e-9; t += xs) {
      const x = Math.round(X(t)) + 0.5;
      ctx.beginPath(); ctx.moveTo(x, T); ctx.lineTo(x, T + ph); ctx.stroke();
      ctx.fillText(tickLabel(t), x, T + ph + 10);
    }
    ctx.fillText("time after the pulse reference, ns", L + pw / 2, T + ph + 23);
    ctx.textAlign = "left";
    ctx.fillText(norm ? "normalised" : "V / step unit", 4, 10);
    ctx.save();
    ctx.beginPath(); ctx.rect(L, T, pw, ph); ctx.clip();
    for (const s of series) {
      ctx.strokeStyle = s.color; ctx.lineWidth = 1.6; ctx.setLineDash([]);
      ctx.beginPath();
      s.values.forEach((v, i) => {
        const x = X(ta + i * dt), y = Y(v * s.scale);
        if (i) ctx.lineTo(x, y); else ctx.moveTo(x, y);
      });
      ctx.stroke();
    }
    if (wave.returns.length > 0) {
      ctx.strokeStyle = "#ffffff"; ctx.lineWidth = 1.4; ctx.setLineDash([5, 4]);
      ctx.beginPath();
      model.forEach(([t, v], i) => { if (i) ctx.lineTo(X(t), Y(v)); else ctx.moveTo(X(t), Y(v)); });
      ctx.stroke();
      ctx.setLineDash([2, 3]);
      ctx.strokeStyle = "#e3b341";
      for (const r of wave.returns) {
        const x = X(r.time_ns);
        ctx.beginPath(); ctx.moveTo(x, Y(r.amplitude * lastScale)); ctx.lineTo(x, Y(0)); ctx.stroke();
      }
    }
    ctx.restore();
    ctx.setLineDash([]);
    setText("wave-info", "pulse " + wave.pulse_id + " · GPS " + wave.gps_time.toFixed(6) + " s · " +
      dt + " ns/sample · " + wave.returns.length + " returns");
  }

  // ---- connection state and polling ----------------------------------------------------------

  function renderConn() {
    const c = $("conn");
    const now = Date.now();
    if (lastOk === 0) {
      c.className = "conn wait"; c.textContent = "waiting for data";
    } else if (now - lastOk > DATA_STALE_MS) {
      c.className = "conn down"; c.textContent = "NO CONNECTION " + Math.round((now - lastOk) / 1000) + " s";
    } else if (now - lastSeqChange > DATA_STALE_MS) {
      c.className = "conn down"; c.textContent = "NO NEW DATA " + Math.round((now - lastSeqChange) / 1000) + " s";
    } else {
      c.className = "conn live"; c.textContent = "LIVE";
    }
  }

  function renderStatus(s) {
    renderHeader(s);
    renderBig(s);
    renderAlerts(s);
    renderInputs(s);
    renderNav(s);
    renderSystem(s);
    drawCoverage(s);
  }

  async function pollStatus() {
    try {
      const [s, h] = await Promise.all([getJSON("/api/status"), getJSON("/api/history")]);
      lastOk = Date.now();
      if (s) {
        if (s.sequence !== lastSeq) { lastSeq = s.sequence; lastSeqChange = lastOk; }
        status = s;
        renderStatus(s);
      }
      history = Array.isArray(h) ? h : [];
      drawCharts();
      if (s && document.body.dataset.ready !== "1") document.body.dataset.ready = "1";
    } catch (e) {
      console.warn("status:", e);
    }
    renderConn();
    setTimeout(pollStatus, STATUS_MS);
  }

  async function pollWave() {
    try {
      wave = await getJSON("/api/waveform");
      drawWaveform();
    } catch (e) {
      console.warn("waveform:", e);
    }
    setTimeout(pollWave, WAVE_MS);
  }

  $("wave-normalise").addEventListener("change", drawWaveform);
  window.addEventListener("resize", () => {
    drawCharts();
    drawWaveform();
    if (status) drawCoverage(status);
  });
  pollStatus();
  pollWave();
})();

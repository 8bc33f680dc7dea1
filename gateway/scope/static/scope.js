// can-drive-hil live scope: the run's signals from /events (server-sent events), drawn on
// canvases like an oscilloscope: signals chosen per panel, pause, zoom, time base, trigger.
// No library, no network beyond the page's own server.
"use strict";

const GROUPS = [  // panel, unit, which columns belong to it, which are shown at first
  {name: "speed", unit: "rad/s", match: /^(w_|w$|theta_target)/,
   shown: ["w_ref", "w_m", "w_hat", "w_target"]},
  {name: "flux", unit: "Wb", match: /^psi/, shown: ["psi_ref", "psi_r_mod", "psi_hat_mod"]},
  {name: "currents", unit: "A", match: /^i_s/, shown: ["i_sa", "i_sb", "i_sd_ref", "i_sq_ref"]},
  {name: "voltages", unit: "V", match: /^u_/, shown: ["u_sa", "u_sb", "u_sd_ref", "u_sq_ref"]},
  {name: "torque", unit: "N·m", match: /^(T_|T$)/, shown: ["T_L", "T_e", "T_ref"]},
  {name: "timing and state", unit: "", match: /^(sync_|reaction|missed|withheld|statusword|i_limited|u_limit|fault)/,
   shown: ["missed"]},
  {name: "other", unit: "", match: /./, shown: []},
];
const COLORS = ["#4af", "#fa4", "#6d6", "#f66", "#c8f", "#ff6", "#6ff", "#f8c", "#aaa"];
const MAX_POINTS = 400000;

const scope = window.scope = {
  columns: [], data: {}, length: 0, samples: 0, lastT: NaN, running: false, stop: null,
  paused: false, window: 0.5, viewEnd: null, traces: {}, batches: 0,
  trigger: {armed: false, at: null},
};
const groupOf = {};
const shown = new Set();
let panels = [];

function grow(n) {
  for (const name of scope.columns) {
    const old = scope.data[name];
    if (scope.length + n > old.length) {
      const bigger = new Float64Array(Math.max(1024, 2 * (scope.length + n)));
      bigger.set(old.subarray(0, scope.length));
      scope.data[name] = bigger;
    }
  }
}

function dropOldest() {
  if (scope.length <= MAX_POINTS) return;
  const cut = scope.length - MAX_POINTS;
  for (const name of scope.columns) {
    const a = scope.data[name];
    a.copyWithin(0, cut, scope.length);
  }
  scope.length -= cut;
}

function onMeta(meta) {
  scope.columns = meta.columns;
  scope.data = {};
  scope.length = 0;
  for (const name of meta.columns) scope.data[name] = new Float64Array(1024);
  document.getElementById("title").textContent = "can-drive-hil scope" +
    (meta.title ? " — " + meta.title : "");
  for (const name of meta.columns) {
    if (name === "t") continue;
    const g = GROUPS.find((g) => g.match.test(name));
    groupOf[name] = g;
    if (g.shown.includes(name)) shown.add(name);
  }
  buildSignalList();
  buildPanels();
  const sel = document.getElementById("trig-signal");
  sel.innerHTML = "";
  for (const name of meta.columns) {
    if (name === "t") continue;
    const o = document.createElement("option");
    o.value = o.textContent = name;
    if (name === "w_m") o.selected = true;
    sel.appendChild(o);
  }
}

function onRows(batch) {
  const n = batch.n;
  if (!n) return;
  grow(n);
  for (const name of scope.columns) {
    const src = batch.columns[name], dst = scope.data[name];
    for (let i = 0; i < n; i++) dst[scope.length + i] = src[i] === null ? NaN : src[i];
  }
  const first = scope.length;
  scope.length += n;
  scope.samples += n;
  scope.batches += 1;
  scope.cycles = batch.cycles;
  scope.lastT = scope.data.t[scope.length - 1];
  checkTrigger(first);
  dropOldest();
}

function onState(state) {
  scope.running = state.running;
  scope.stop = state.stop || null;
  scope.state = state;
}

function checkTrigger(first) {
  const tr = scope.trigger;
  if (!tr.armed) return;
  const name = document.getElementById("trig-signal").value;
  const level = parseFloat(document.getElementById("trig-level").value);
  const rising = document.getElementById("trig-edge").value === "rising";
  const y = scope.data[name], t = scope.data.t;
  if (!y) return;
  for (let i = Math.max(1, first); i < scope.length; i++) {
    const a = y[i - 1], b = y[i];
    if (rising ? (a < level && b >= level) : (a > level && b <= level)) {
      tr.armed = false;
      tr.at = t[i];
      scope.paused = true;
      scope.viewEnd = t[i] + scope.window / 2;
      document.getElementById("pause").textContent = "Run";
      document.getElementById("trig-state").textContent =
        `triggered at t = ${t[i].toFixed(4)} s`;
      return;
    }
  }
}

function buildSignalList() {
  const list = document.getElementById("signal-list");
  list.innerHTML = "";
  for (const g of GROUPS) {
    const names = scope.columns.filter((n) => groupOf[n] === g);
    if (!names.length) continue;
    const head = document.createElement("div");
    head.className = "group";
    head.textContent = g.name + (g.unit ? ` (${g.unit})` : "");
    list.appendChild(head);
    for (const name of names) {
      const label = document.createElement("label");
      const box = document.createElement("input");
      box.type = "checkbox";
      box.checked = shown.has(name);
      box.dataset.signal = name;
      box.addEventListener("change", () => {
        box.checked ? shown.add(name) : shown.delete(name);
        buildPanels();
      });
      label.appendChild(box);
      label.appendChild(document.createTextNode(" " + name));
      list.appendChild(label);
    }
  }
}

function buildPanels() {
  const main = document.getElementById("panels");
  main.innerHTML = "";
  panels = [];
  for (const g of GROUPS) {
    const names = scope.columns.filter((n) => groupOf[n] === g && shown.has(n));
    if (!names.length) continue;
    const div = document.createElement("div");
    div.className = "panel";
    const canvas = document.createElement("canvas");
    canvas.dataset.panel = g.name;
    const label = document.createElement("div");
    label.className = "label";
    label.innerHTML = names.map((n, k) =>
      `<span class="swatch" style="background:${COLORS[k % COLORS.length]}"></span>${n}`)
      .join(" &nbsp; ") + (g.unit ? ` &nbsp; [${g.unit}]` : "");
    div.appendChild(canvas);
    div.appendChild(label);
    main.appendChild(div);
    addPanZoom(canvas);
    panels.push({group: g, names, canvas});
  }
}

function addPanZoom(canvas) {
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const w = scope.window || spanOfRun();
    scope.window = Math.max(1e-3, w * (e.deltaY > 0 ? 1.25 : 0.8));
    document.getElementById("timebase").value = "";
  }, {passive: false});
  let dragX = null;
  canvas.addEventListener("mousedown", (e) => { if (scope.paused) dragX = e.clientX; });
  window.addEventListener("mouseup", () => { dragX = null; });
  canvas.addEventListener("mousemove", (e) => {
    if (dragX === null) return;
    const w = scope.window || spanOfRun();
    scope.viewEnd = (scope.viewEnd ?? scope.lastT) - (e.clientX - dragX) / canvas.clientWidth * w;
    dragX = e.clientX;
  });
}

function spanOfRun() {
  return scope.length ? scope.lastT - scope.data.t[0] : 1;
}

function lowerBound(a, n, x) {
  let lo = 0, hi = n;
  while (lo < hi) { const m = (lo + hi) >> 1; if (a[m] < x) lo = m + 1; else hi = m; }
  return lo;
}

function draw() {
  const t = scope.data.t;
  for (const p of panels) {
    const c = p.canvas, ctx = c.getContext("2d");
    const W = c.width = c.clientWidth * devicePixelRatio;
    const H = c.height = c.clientHeight * devicePixelRatio;
    ctx.clearRect(0, 0, W, H);
    if (!scope.length) continue;
    const end = scope.paused && scope.viewEnd !== null ? scope.viewEnd : scope.lastT;
    const win = scope.window || spanOfRun();
    const start = scope.window ? end - win : t[0];
    const i0 = Math.max(0, lowerBound(t, scope.length, start) - 1);
    const i1 = Math.min(scope.length, lowerBound(t, scope.length, end) + 1);
    let lo = Infinity, hi = -Infinity;
    for (const name of p.names) {
      const y = scope.data[name];
      for (let i = i0; i < i1; i++) { const v = y[i]; if (v < lo) lo = v; if (v > hi) hi = v; }
    }
    if (!isFinite(lo)) { lo = -1; hi = 1; }
    if (hi - lo < 1e-12) { lo -= 1; hi += 1; }
    const pad = 0.08 * (hi - lo); lo -= pad; hi += pad;
    const L = 72 * devicePixelRatio, X = (x) => L + (x - start) / (end - start) * (W - L);
    const Y = (v) => H - (v - lo) / (hi - lo) * H;
    ctx.strokeStyle = "#333"; ctx.fillStyle = "#888";
    ctx.font = `${11 * devicePixelRatio}px monospace`;
    const digits = Math.min(9, Math.max(0, 1 - Math.floor(Math.log10((hi - lo) / 4))));
    for (let k = 0; k <= 4; k++) {
      const v = lo + k * (hi - lo) / 4, y = Y(v);
      ctx.beginPath(); ctx.moveTo(L, y); ctx.lineTo(W, y); ctx.stroke();
      ctx.fillText(v.toFixed(digits), 2, Math.min(H - 2, Math.max(10, y)));
    }
    ctx.fillText(`${start.toFixed(3)} s`, L + 2, H - 3);
    ctx.fillText(`${end.toFixed(3)} s`, W - 70 * devicePixelRatio, H - 3);
    if (scope.trigger.at !== null && scope.trigger.at >= start && scope.trigger.at <= end) {
      ctx.strokeStyle = "#f44";
      ctx.beginPath(); ctx.moveTo(X(scope.trigger.at), 0); ctx.lineTo(X(scope.trigger.at), H);
      ctx.stroke();
    }
    p.names.forEach((name, k) => {
      const y = scope.data[name];
      ctx.strokeStyle = COLORS[k % COLORS.length];
      ctx.lineWidth = devicePixelRatio;
      ctx.beginPath();
      let pen = false, drawn = 0;
      const stride = Math.max(1, Math.floor((i1 - i0) / (2 * (W - L))));
      for (let i = i0; i < i1; i += stride) {
        const v = y[i];
        if (!isFinite(v)) { pen = false; continue; }
        pen ? ctx.lineTo(X(t[i]), Y(v)) : ctx.moveTo(X(t[i]), Y(v));
        pen = true; drawn++;
      }
      ctx.stroke();
      scope.traces[name] = drawn;
    });
  }
  const st = document.getElementById("status");
  const missed = scope.data.missed && scope.length
    ? scope.data.missed.subarray(0, scope.length).reduce((a, b) => a + (b > 0 ? 1 : 0), 0) : 0;
  const where = `cycle ${scope.cycles ?? 0} · t = ${isFinite(scope.lastT) ? scope.lastT.toFixed(3) : "—"} s` +
    ` · missed (rows shown) ${missed} · ${scope.samples} points`;
  if (scope.running) { st.textContent = "running · " + where; st.className = ""; }
  else if (scope.stop) {
    const s = scope.state || {};
    st.textContent = `stopped: ${scope.stop}` + (s.stop_reason ? ` (${s.stop_reason})` : "") +
      (s.speed_error_rms != null ? ` · speed error rms ${s.speed_error_rms.toPrecision(3)} rad/s` : "") +
      " · " + where;
    st.className = "stopped";
  } else { st.textContent = "waiting for the run · " + where; }
  requestAnimationFrame(draw);
}

function connect() {
  const es = new EventSource("events");
  es.addEventListener("meta", (e) => onMeta(JSON.parse(e.data)));
  es.addEventListener("rows", (e) => onRows(JSON.parse(e.data)));
  es.addEventListener("state", (e) => onState(JSON.parse(e.data)));
  es.onerror = () => {
    if (!scope.running) { es.close(); return; }  // the run is over and so is its server
  };
}

document.getElementById("pause").addEventListener("click", (e) => {
  scope.paused = !scope.paused;
  scope.viewEnd = scope.paused ? scope.lastT : null;
  e.target.textContent = scope.paused ? "Run" : "Pause";
});
document.getElementById("timebase").addEventListener("change", (e) => {
  scope.window = parseFloat(e.target.value) || 0;
});
document.getElementById("trig-arm").addEventListener("click", () => {
  scope.trigger.armed = true;
  scope.trigger.at = null;
  scope.paused = false;
  scope.viewEnd = null;
  document.getElementById("pause").textContent = "Pause";
  document.getElementById("trig-state").textContent = "armed";
});

connect();
requestAnimationFrame(draw);

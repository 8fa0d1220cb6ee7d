// The live page of `campaign watch` (docs/watch.md): polls /api/status every POLL_MS, fetches the
// poses stored since the last poll, and draws its plots on <canvas> by hand (no library, no CDN).
"use strict";

const POLL_MS = 500;
const DETAILS_MS = 3000;
const COLOURS = { ink: "#1d2733", nominal: "#1f77b4", calibrated: "#ff7f0e", bad: "#d62728", grid: "#e3e8ee", axis: "#5f6b7a" };
const S = { poses: [], status: null, details: null, detailsAt: 0, stage: undefined, calibration: undefined,
            view: { yaw: -0.6, pitch: 0.35 } };

const $ = (id) => document.getElementById(id);

async function getJSON(url) {
  const r = await fetch(url, { cache: "no-store", credentials: "same-origin" });
  if (r.status === 401) throw new Error("the watcher refuses this page: its token changed or it restarted with another; open the page again as http://HOST:PORT/?token=<the token file's text>");
  if (!r.ok) throw new Error(`no answer from the watcher (${url}: HTTP ${r.status}); retrying`);
  return r.json();
}

async function tick() {
  try {
    const st = await getJSON("api/status");
    const total = st.measured + st.failed;
    const now = Date.now();
    const drifted = S.status && st.drift.checks !== S.status.drift.checks;  // the drift plot's points come with details
    if (!S.details || st.state !== S.status.state || drifted || now - S.detailsAt > DETAILS_MS) {
      S.details = await getJSON("api/details");
      S.detailsAt = now;
      // another calibration (even of the same stage): every pose's calibrated residual is new
      if (S.details.calibration_id !== S.calibration) {
        S.calibration = S.details.calibration_id; S.stage = S.details.calibration_stage; S.poses = [];
      }
    }
    if (total < S.poses.length) S.poses = [];  // failed poses forgotten (--retry-failed): read them all again
    if (total > S.poses.length) S.poses = S.poses.concat(await getJSON(`api/poses?from=${S.poses.length}`));
    S.status = st;
    render();
    $("conn").textContent = "";
  } catch (e) {
    $("conn").textContent = e instanceof TypeError ? `no answer from the watcher (${e.message}); retrying` : e.message;
  }
  setTimeout(tick, POLL_MS);
}

// -- numbers ----------------------------------------------------------------------------------------
function fmtDuration(s) {
  if (s === null || s === undefined) return "–";
  if (s < 90) return `${s.toFixed(0)} s`;
  if (s < 5400) return `${(s / 60).toFixed(0)} min`;
  if (s < 172800) return `${(s / 3600).toFixed(1)} h`;
  return `${(s / 86400).toFixed(1)} days`;
}
const fmt = (v, d = 3) => (v === null || v === undefined ? "–" : v.toFixed(d));
const median = (a) => { if (!a.length) return null; const b = [...a].sort((x, y) => x - y); return b[b.length >> 1]; };

// -- the page ----------------------------------------------------------------------------------------
function render() {
  const st = S.status, d = S.details || {};
  $("run").textContent = d.run ? `${d.run}${d.robot ? " · " + d.robot : ""}` : "";
  $("measured").textContent = st.measured;
  $("failed").textContent = st.failed;
  $("planned").textContent = st.planned;
  const badge = $("state");
  badge.textContent = st.state;
  badge.className = `state ${st.state}`;
  $("clock").textContent = st.campaign_h === null ? "–" : `${st.campaign_h.toFixed(2)} h`;
  const rate = d.rate_poses_per_campaign_h;
  $("rate").textContent = rate ? `${rate.toFixed(0)} poses/h` : "–";
  $("eta").textContent = st.state === "finished" ? "done" : fmtDuration(st.eta_s);
  $("last").textContent = st.last_pose === null ? "–" : st.last_pose;
  const planned = Math.max(st.planned, 1);
  $("bar-measured").style.width = `${(100 * st.measured) / planned}%`;
  $("bar-failed").style.width = `${(100 * st.failed) / planned}%`;
  const holder = d.holder && d.holder.command ? `; being written by campaign ${d.holder.command} (pid ${d.holder.pid})` : "";
  const next = st.state === "running" && d.next_pose !== null && d.next_pose !== undefined ? `; next pose ${d.next_pose}` : "";
  const wall = d.rate_poses_per_wall_h ? `; ${(d.rate_poses_per_wall_h / 60).toFixed(1)} poses per wall-clock minute` : "";
  $("where").textContent = `${d.path || ""}${holder}${next}${wall}`;
  const cost = d.watcher ? `; the server answered ${d.watcher.requests} requests in ${d.watcher.cpu_s.toFixed(1)} s of CPU` : "";
  $("updated").textContent = `last update ${new Date().toLocaleTimeString()}${cost}`;
  renderResiduals();
  renderSpace();
  renderDrift(d);
  renderFailures();
  renderEvents(d);
  renderAuto(d);
}

function renderResiduals() {
  const nom = [], cal = [];
  for (const p of S.poses) {
    if (p.time_s === null) continue;
    if (p.error_nominal_mm !== null) nom.push([p.time_s / 3600, p.error_nominal_mm]);
    if (p.error_calibrated_mm !== null) cal.push([p.time_s / 3600, p.error_calibrated_mm]);
  }
  const series = [{ pts: nom, color: COLOURS.nominal, label: nom.length ? `nominal model (median ${fmt(median(nom.map((q) => q[1])))} mm)` : "nominal model" }];
  if (cal.length) series.push({ pts: cal, color: COLOURS.calibrated, label: `calibrated: ${S.stage} (median ${fmt(median(cal.map((q) => q[1])))} mm)` });
  // the calibrated errors are often a hundredth of the nominal ones: on one linear axis they would
  // all sit on its zero, so the axis turns logarithmic when the medians are a decade apart
  const mNom = median(nom.map((q) => q[1])), mCal = median(cal.map((q) => q[1]));
  const log = mNom !== null && mCal !== null && mCal > 0 && mNom / mCal > 10;
  const inTracker = S.details && S.details.frame === "tracker";
  const empty = inTracker && S.poses.some((p) => p.status === "measured") ? "no error before a calibration found the tracker" : "nothing yet";
  plot($("residuals"), { series, xlabel: "campaign clock (h)", ylabel: log ? "‖Δt‖ (mm, log scale)" : "‖Δt‖ (mm)", ymin: 0, log, empty });
  $("residuals-note").textContent = cal.length
    ? `‖Δt‖: the distance between the measured point and the model's; calibrated: RUN/calibration's current model (${S.stage}), for every pose measured, those measured after it too` +
      (inTracker ? "; both in the tracker's frame, where the calibration found the tracker" : "")
    : inTracker ? "measured in the tracker's frame: the errors against the nominal and the calibrated model appear once `campaign calibrate` has found where the tracker stands"
    : "‖Δt‖: the distance between the measured point and the nominal model's; against the calibrated model too once `campaign calibrate` has run";
}

function renderDrift(d) {
  const checks = (d.events || []).filter((e) => e.kind === "drift_check" && e.detail.drift_mm !== null && e.time_s !== null);
  // what the driver compared with the threshold: the move against the reference's earlier readings
  // (moved_mm) where it stored one, else the distance from the first reading
  const judged = (e) => [e.time_s / 3600, typeof e.detail.moved_mm === "number" ? e.detail.moved_mm : e.detail.drift_mm];
  const ok = checks.filter((e) => !e.detail.over_threshold).map(judged);
  const over = checks.filter((e) => e.detail.over_threshold).map(judged);
  const fromFirst = checks.map((e) => [e.time_s / 3600, e.detail.drift_mm]);
  // each check's own threshold when the driver stored it (run.drift_threshold_mm: auto follows the
  // noise floor), else the configured one
  const own = checks.filter((e) => typeof e.detail.threshold_mm === "number").map((e) => [e.time_s / 3600, e.detail.threshold_mm]);
  const thr = d.drift_threshold_mm;
  const series = [{ pts: fromFirst, color: "#9aa8b6", label: "from the 1st reading", line: true, marks: false },
                  { pts: ok, color: COLOURS.nominal, label: "moved" },
                  { pts: over, color: COLOURS.bad, label: "over" }];
  if (own.length) series.push({ pts: own, color: COLOURS.bad, label: "threshold", line: true, dashed: true, marks: false });
  plot($("drift"), {
    series,
    hline: own.length || thr === null || thr === undefined ? null : { y: thr, label: `threshold ${thr} mm` },
    xlabel: "campaign clock (h)", ylabel: "drift (mm)", ymin: 0,
  });
  const dr = S.status.drift || {};
  $("drift-note").textContent = dr.checks ? `${dr.checks} checks; from the first reading: last ${fmt(dr.last_mm)} mm, largest ${fmt(dr.max_mm)} mm; ${dr.over_threshold} moved over the threshold` +
                                            (dr.threshold_mm !== null ? ` (now ${fmt(dr.threshold_mm)} mm)` : "")
                                          : "no drift check yet (run.drift_check_every in campaign.yaml)";
}

// a failure's reason with its numbers folded (one reason with varying values counts once), names
// such as a reflector's m1 or a joint's q3 kept: they say where it fails
function reasonKey(reason) {
  return (reason || "no reason stored").replace(/(?<![\w.])[-+]?\d+(\.\d+)?(e[-+]?\d+)?(?![\w])/gi, "#");
}

function renderFailures() {
  const failed = S.poses.filter((p) => p.status === "failed");
  const byReason = new Map();
  for (const p of failed) {
    const key = reasonKey(p.reason);
    byReason.set(key, (byReason.get(key) || 0) + 1);
  }
  const box = $("failure-reasons");
  box.replaceChildren();
  if (!failed.length) { box.textContent = "none so far"; box.className = "small"; }
  for (const [reason, n] of [...byReason.entries()].sort((a, b) => b[1] - a[1]).slice(0, 8)) {
    const row = document.createElement("div");
    row.className = "reason";
    const b = document.createElement("b"); b.textContent = n;
    const s = document.createElement("span"); s.textContent = reason;
    row.append(b, s);
    box.append(row);
  }
  const body = $("failures").tBodies[0];
  body.replaceChildren();
  // a pose refused before it moved has no time of its own: the campaign clock of the pose stored before it
  const when = new Map();
  let last = null;
  for (const p of S.poses) {
    if (p.status === "failed") when.set(p.pose_id, p.time_s !== null ? (p.time_s / 3600).toFixed(2) : last === null ? "–" : `~${(last / 3600).toFixed(2)}`);
    if (p.time_s !== null) last = p.time_s;
  }
  for (const p of failed.slice(-12).reverse()) {
    const tr = body.insertRow();
    const pos = p.nominal_xyz_m ? p.nominal_xyz_m.map((v) => (v * 1e3).toFixed(0)).join(", ") : "–";
    for (const [text, cls] of [[p.pose_id, "num"], [when.get(p.pose_id), "num"],
                               [p.reason || "", ""], [pos, "num"]]) {
      const td = tr.insertCell(); td.textContent = text; td.className = cls;
    }
  }
}

function renderEvents(d) {
  const ul = $("reports");
  ul.replaceChildren();
  for (const r of d.reports || []) {
    const li = document.createElement("li");
    const a = document.createElement("a");
    a.href = r.href; a.textContent = r.label; a.target = "_blank"; a.rel = "noopener";
    li.append(a); ul.append(li);
  }
  if (!(d.reports || []).length) { const li = document.createElement("li"); li.className = "small"; li.textContent = "no report yet (calibrate, diagnose, iso9283 write them)"; ul.append(li); }
  const ev = $("events");
  ev.replaceChildren();
  const shown = (d.events || []).filter((e) => e.kind !== "drift_check").slice(-10).reverse();
  for (const e of shown) {
    const li = document.createElement("li");
    const h = e.time_s === null ? "" : `${(e.time_s / 3600).toFixed(2)} h: `;
    const text = e.detail.message || e.detail.reason || e.detail.why || (e.kind === "session_end" ? `measured ${e.detail.measured}, failed ${e.detail.failed}` : "");
    li.textContent = e.kind === "warning" ? `${h}${text}` : `${h}${e.kind.replace(/_/g, " ")}${text ? " — " + text : ""}`;
    if (e.kind === "warning" || e.kind === "stop") li.className = "warn";
    ev.append(li);
  }
  for (const n of d.notes || []) { const li = document.createElement("li"); li.textContent = n; li.className = "small"; ev.append(li); }
}

function renderAuto(d) {
  const panel = $("auto-panel");
  panel.hidden = !d.auto;
  if (!d.auto) return;
  panel.style.order = "-1";  // auto's story first: the rounds are what an auto run is about
  const body = $("rounds").tBodies[0];
  body.replaceChildren();
  for (const r of d.auto.rounds) {
    const tr = body.insertRow();
    const ratio = r.floor_mm ? (r.heldout_mm / r.floor_mm).toFixed(2) : "–";
    for (const [text, cls] of [[r.number, "num"], [r.poses, "num"], [fmt(r.hours, 2), "num"], [r.model, ""],
                               [fmt(r.heldout_mm, 4), "num"], [ratio, "num"], [r.decision || "", ""]]) {
      const td = tr.insertCell(); td.textContent = text; td.className = cls;
    }
  }
  const next = d.auto.rounds.length + 1;
  // why it finished: the last round's decision when it was to stop, else the reason's code
  const last = d.auto.rounds[d.auto.rounds.length - 1];
  const why = last && last.kind === "stop" && last.decision ? last.decision
            : d.auto.finished ? (d.auto.finished.reason || "").replace(/_/g, " ") : "";
  $("auto-note").textContent = d.auto.finished ? `finished; ${why}`
                             : d.auto.pending ? `now: ${d.auto.pending}`
                             : d.auto.rounds.length ? `round ${next} under way: measuring, calibrating and diagnosing after round ${next - 1}'s decision`
                             : "no round yet: the first measurement is under way";
}

// -- a 2-D plot on a canvas ----------------------------------------------------------------------
function setup(canvas, minHeight = 0) {
  if (!canvas.dataset.aspect) canvas.dataset.aspect = canvas.height / canvas.width;  // from the HTML's size
  const ratio = window.devicePixelRatio || 1;
  // the HTML's proportions, but never so flat that the axis labels run into each other (a phone)
  const w = canvas.clientWidth || canvas.width, h = Math.max(w * Number(canvas.dataset.aspect), minHeight);
  canvas.width = Math.round(w * ratio);
  canvas.height = Math.round(h * ratio);
  const ctx = canvas.getContext("2d");
  ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
  return [ctx, w, h];
}

function niceTicks(lo, hi, n = 5) {
  if (!(hi > lo)) hi = lo + 1;
  const step0 = (hi - lo) / n, mag = 10 ** Math.floor(Math.log10(step0));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= step0);
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) out.push(Number(v.toPrecision(12)));
  return out;
}

// log10 positions between lo and hi (log10 values) as far apart as the axis's height allows
// (pxPerDecade): 1, 2, 5 × each decade, 1 and 3 ×, the decades, every other decade
function logTicks(lo, hi, pxPerDecade) {
  const out = [];
  const every = pxPerDecade < 14 ? 2 : 1;
  for (let d = Math.floor(lo); d <= Math.ceil(hi); d++) {
    if (d % every) continue;
    for (const m of pxPerDecade >= 70 ? [1, 2, 5] : pxPerDecade >= 36 ? [1, 3] : [1]) {
      const v = d + Math.log10(m);
      if (v >= lo - 1e-9 && v <= hi + 1e-9) out.push(v);
    }
  }
  return out;
}

function plot(canvas, { series, hline = null, xlabel, ylabel, ymin = null, log = false, empty = "nothing yet" }) {
  const [ctx, W, H] = setup(canvas, 200);
  canvas.dataset.yscale = log ? "log" : "linear";
  if (log) {  // plotted as log10 of the values (all positive: distances; a zero at a micrometre's thousandth)
    series = series.map((s) => ({ ...s, pts: s.pts.map((p) => [p[0], Math.log10(Math.max(p[1], 1e-6))]) }));
    ymin = null;
  }
  const m = { l: 56, r: 12, t: 26, b: 38 };
  ctx.clearRect(0, 0, W, H);
  ctx.font = "11px system-ui, sans-serif";
  // the legend's entries, on as many lines above the plot as the width needs
  const legend = [];
  let lx = m.l + 6, line = 0;
  for (const s of series) {
    const text = `${s.label} (${s.pts.length})`, width = ctx.measureText(text).width + 12;
    if (lx > m.l + 6 && lx + width > W - m.r) { line += 1; lx = m.l + 6; }
    legend.push({ s, text, x: lx, y: 14 + 15 * line });
    lx += width + 18;
  }
  m.t += 15 * line;
  const all = series.flatMap((s) => s.pts);
  let x0 = Math.min(...all.map((p) => p[0])), x1 = Math.max(...all.map((p) => p[0]));
  let y0 = Math.min(...all.map((p) => p[1])), y1 = Math.max(...all.map((p) => p[1]));
  if (hline) { y0 = Math.min(y0, hline.y); y1 = Math.max(y1, hline.y * 1.15); }
  if (!all.length) { x0 = 0; x1 = 1; y0 = 0; y1 = hline ? hline.y * 1.5 : 1; }
  if (ymin !== null) y0 = Math.min(ymin, y0);
  if (x1 - x0 < 1e-9) { x0 -= 0.5; x1 += 0.5; }
  const pad = (x1 - x0) * 0.02;  // no point on the frame
  x0 -= pad; x1 += pad;
  if (y1 - y0 < 1e-12) y1 = y0 + 1;
  y1 += (y1 - y0) * 0.05;
  if (log) y0 -= (y1 - y0) * 0.05;  // no point on the bottom of the frame either
  const X = (v) => m.l + ((v - x0) / (x1 - x0)) * (W - m.l - m.r);
  const Y = (v) => H - m.b - ((v - y0) / (y1 - y0)) * (H - m.t - m.b);
  ctx.strokeStyle = COLOURS.grid; ctx.fillStyle = COLOURS.axis; ctx.lineWidth = 1;
  ctx.textAlign = "right"; ctx.textBaseline = "middle";
  for (const v of log ? logTicks(y0, y1, (H - m.t - m.b) / (y1 - y0)) : niceTicks(y0, y1)) {
    ctx.beginPath(); ctx.moveTo(m.l, Y(v)); ctx.lineTo(W - m.r, Y(v)); ctx.stroke();
    ctx.fillText(log ? Number((10 ** v).toPrecision(1)) : Number(v.toPrecision(4)), m.l - 5, Y(v));
  }
  ctx.textAlign = "center"; ctx.textBaseline = "top";
  for (const v of niceTicks(x0, x1, 6)) {
    ctx.beginPath(); ctx.moveTo(X(v), m.t); ctx.lineTo(X(v), H - m.b); ctx.stroke();
    ctx.fillText(Number(v.toPrecision(4)), X(v), H - m.b + 4);
  }
  ctx.fillText(xlabel, (m.l + W - m.r) / 2, H - 15);
  ctx.save(); ctx.translate(12, (m.t + H - m.b) / 2); ctx.rotate(-Math.PI / 2); ctx.fillText(ylabel, 0, -6); ctx.restore();
  ctx.strokeStyle = COLOURS.axis; ctx.strokeRect(m.l, m.t, W - m.l - m.r, H - m.t - m.b);
  if (hline) {
    ctx.save(); ctx.setLineDash([6, 4]); ctx.strokeStyle = COLOURS.bad;
    ctx.beginPath(); ctx.moveTo(m.l, Y(hline.y)); ctx.lineTo(W - m.r, Y(hline.y)); ctx.stroke(); ctx.restore();
    ctx.fillStyle = COLOURS.bad; ctx.textAlign = "right"; ctx.textBaseline = "bottom";
    ctx.fillText(hline.label, W - m.r - 4, Y(hline.y) - 2);
  }
  const r = all.length > 2000 ? 1.5 : 2.5;
  for (const s of series) {
    ctx.fillStyle = s.color; ctx.strokeStyle = s.color;
    if (s.line && s.pts.length > 1) {
      ctx.save(); if (s.dashed) ctx.setLineDash([6, 4]);
      ctx.beginPath(); s.pts.forEach((p, i) => (i ? ctx.lineTo(X(p[0]), Y(p[1])) : ctx.moveTo(X(p[0]), Y(p[1])))); ctx.stroke();
      ctx.restore();
    }
    if (s.marks !== false) for (const p of s.pts) { ctx.beginPath(); ctx.arc(X(p[0]), Y(p[1]), r, 0, 2 * Math.PI); ctx.fill(); }
  }
  ctx.textAlign = "left"; ctx.textBaseline = "middle";
  for (const { s, text, x, y } of legend) {
    if (s.marks === false) {  // a line in the legend for a line, a dot for points
      ctx.save(); ctx.strokeStyle = s.color; ctx.lineWidth = 2; if (s.dashed) ctx.setLineDash([4, 2]);
      ctx.beginPath(); ctx.moveTo(x - 2, y); ctx.lineTo(x + 10, y); ctx.stroke(); ctx.restore();
    } else { ctx.fillStyle = s.color; ctx.beginPath(); ctx.arc(x + 4, y, 4, 0, 2 * Math.PI); ctx.fill(); }
    ctx.fillStyle = COLOURS.axis; ctx.fillText(text, x + 12, y);
  }
  if (!all.length) { ctx.textAlign = "center"; ctx.fillText(empty, (m.l + W) / 2, (m.t + H) / 2); }
}

// -- the 3-D view of the tool positions ---------------------------------------------------------------
const VIRIDIS = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];
function colourMap(t) {
  t = Math.min(Math.max(t, 0), 1) * (VIRIDIS.length - 1);
  const i = Math.min(Math.floor(t), VIRIDIS.length - 2), f = t - i;
  const c = VIRIDIS[i].map((v, k) => Math.round(v + f * (VIRIDIS[i + 1][k] - v)));
  return `rgb(${c[0]},${c[1]},${c[2]})`;
}

function basis(up) {
  const u = up && up.length === 3 ? up : [0, 0, 1];
  const ref = Math.abs(u[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
  const dot = ref[0] * u[0] + ref[1] * u[1] + ref[2] * u[2];
  let a = ref.map((v, k) => v - dot * u[k]);
  const n = Math.hypot(...a); a = a.map((v) => v / n);
  const b = [u[1] * a[2] - u[2] * a[1], u[2] * a[0] - u[0] * a[2], u[0] * a[1] - u[1] * a[0]];
  return [a, b, u];
}

function renderSpace() {
  const canvas = $("space");
  const [ctx, W, H] = setup(canvas);
  ctx.clearRect(0, 0, W, H);
  const which = $("colour").value;
  const key = which === "calibrated" ? "error_calibrated_mm" : "error_nominal_mm";
  // measured in the tracker's frame: the points are the tracker's, the nominal ones (where failures
  // are placed) the robot's, so failures are not drawn among them
  const inTracker = S.details && S.details.frame === "tracker";
  const pts = [];
  for (const p of S.poses) {
    if (p.status === "measured" && p.xyz_m) pts.push({ x: p.xyz_m, e: p[key], failed: false });
    else if (p.status === "failed" && p.nominal_xyz_m && !inTracker) pts.push({ x: p.nominal_xyz_m, e: null, failed: true });
  }
  ctx.font = "11px system-ui, sans-serif"; ctx.fillStyle = COLOURS.axis;
  if (!pts.length) { ctx.textAlign = "center"; ctx.fillText("nothing yet", W / 2, H / 2); return; }
  const [a, b, u] = basis(inTracker ? null : S.details && S.details.up);
  const { yaw, pitch } = S.view;
  const c = [0, 1, 2].map((k) => pts.reduce((s, p) => s + p.x[k], 0) / pts.length);
  const proj = (x) => {
    const d = [x[0] - c[0], x[1] - c[1], x[2] - c[2]];
    const pa = d[0] * a[0] + d[1] * a[1] + d[2] * a[2], pb = d[0] * b[0] + d[1] * b[1] + d[2] * b[2];
    const pu = d[0] * u[0] + d[1] * u[1] + d[2] * u[2];
    const sx = Math.cos(yaw) * pa + Math.sin(yaw) * pb, depth0 = -Math.sin(yaw) * pa + Math.cos(yaw) * pb;
    return [sx, Math.cos(pitch) * pu - Math.sin(pitch) * depth0, Math.sin(pitch) * pu + Math.cos(pitch) * depth0];
  };
  const P = pts.map((p) => ({ ...p, s: proj(p.x) }));
  const R = Math.max(...P.map((p) => Math.hypot(p.s[0], p.s[1])), 1e-3);
  const scale = (Math.min(W - 70, H - 30) / 2) / R, cx = (W - 60) / 2, cy = H / 2;
  const errs = P.filter((p) => p.e !== null).map((p) => p.e).sort((x, y) => x - y);
  const lo = errs.length ? errs[0] : 0, hi = errs.length ? errs[Math.floor(0.98 * (errs.length - 1))] : 1;
  P.sort((p, q) => p.s[2] - q.s[2]);
  const dot = P.length > 2000 ? 1.6 : 3;  // thousands of poses: smaller dots, the shape shows through
  for (const p of P) {
    const x = cx + p.s[0] * scale, y = cy - p.s[1] * scale;
    if (p.failed) {
      ctx.strokeStyle = COLOURS.bad; ctx.lineWidth = 1.5; ctx.beginPath();
      ctx.moveTo(x - 4, y - 4); ctx.lineTo(x + 4, y + 4); ctx.moveTo(x + 4, y - 4); ctx.lineTo(x - 4, y + 4); ctx.stroke();
      ctx.lineWidth = 1;
    } else {
      ctx.fillStyle = p.e === null ? "#aab4bf" : colourMap((p.e - lo) / Math.max(hi - lo, 1e-12));
      ctx.beginPath(); ctx.arc(x, y, dot, 0, 2 * Math.PI); ctx.fill();
    }
  }
  // the axes of the frame from the centre of the points, 20 % of their spread, over the points
  // (under thousands of them they were hidden)
  const L = 0.4 * R;
  ctx.lineWidth = 1.5; ctx.font = "bold 12px system-ui, sans-serif"; ctx.textAlign = "left"; ctx.textBaseline = "middle";
  [["x", [1, 0, 0]], ["y", [0, 1, 0]], ["z", [0, 0, 1]]].forEach(([name, e]) => {
    const o = proj(c), t = proj(c.map((v, k) => v + L * e[k]));
    const ox = cx + o[0] * scale, oy = cy - o[1] * scale, tx = cx + t[0] * scale, ty = cy - t[1] * scale;
    for (const [colour, width] of [["#fff", 4], [COLOURS.ink, 1.5]]) {  // a white halo under each
      ctx.strokeStyle = colour; ctx.lineWidth = width;
      ctx.beginPath(); ctx.moveTo(ox, oy); ctx.lineTo(tx, ty); ctx.stroke();
      ctx.strokeText(name, tx + 4, ty);
    }
    ctx.fillStyle = COLOURS.ink; ctx.fillText(name, tx + 4, ty);
  });
  ctx.lineWidth = 1; ctx.font = "11px system-ui, sans-serif";
  // colour bar, when there is an error to colour by
  const bx = W - 46, by0 = 20, by1 = H - 40;
  if (errs.length) {
    for (let i = 0; i <= 40; i++) { ctx.fillStyle = colourMap(i / 40); ctx.fillRect(bx, by1 - ((by1 - by0) * (i + 1)) / 41, 10, (by1 - by0) / 40 + 1); }
    ctx.fillStyle = COLOURS.axis; ctx.textAlign = "left"; ctx.textBaseline = "middle";
    ctx.fillText(fmt(hi, 2), bx + 13, by0); ctx.fillText(fmt(lo, 2), bx + 13, by1); ctx.fillText("mm", bx - 2, by1 + 14);
  }
  const nFailed = P.filter((p) => p.failed).length;
  $("space-note").textContent = `${P.length - nFailed} measured${inTracker ? ", in the tracker's frame" : ""} (colour: ‖Δt‖ against the ${which} model)` +
    (nFailed ? `; × ${nFailed} failed, at their nominal positions` : "") + (errs.length ? "" : "; no error to colour by yet");
}

function dragToTurn() {
  const canvas = $("space");
  let last = null;
  canvas.addEventListener("pointerdown", (e) => { last = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
  canvas.addEventListener("pointermove", (e) => {
    if (!last) return;
    S.view.yaw += (e.clientX - last[0]) * 0.01;
    S.view.pitch = Math.max(-1.5, Math.min(1.5, S.view.pitch + (e.clientY - last[1]) * 0.01));
    last = [e.clientX, e.clientY];
    renderSpace();
  });
  canvas.addEventListener("pointerup", () => { last = null; });
  $("colour").addEventListener("change", renderSpace);
}

window.addEventListener("DOMContentLoaded", () => {
  // opened once as ?token=...: the server answered with a cookie; the token leaves the address bar
  if (new URLSearchParams(location.search).has("token")) history.replaceState(null, "", location.pathname);
  dragToTurn();
  tick();
});
window.addEventListener("resize", () => { if (S.status) render(); });

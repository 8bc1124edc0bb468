// The driftwatch dashboard: a client of the public JSON API under /api/v1 and nothing else.
// Hash routes: #/ (the fleet) and #/machine/ID (one machine). Every 5 s the current page's
// data is read again and the page redrawn when it changed. Charts are plain SVG.
'use strict';

const API = '/api/v1';
const SVG = 'http://www.w3.org/2000/svg';
const POLL_MS = 5000;
const NS_PER_MIN = 60e9;
const NS_PER_H = 3600e9;
// The window of the machine page's charts: the last shift before the service clock.
const WINDOW_NS = 8 * NS_PER_H;
// Bars and bands: this many standard uncertainties.
const K = 2;
const TOKEN_KEY = 'driftwatch.token';

// ---- the API ----

function token() {
  return sessionStorage.getItem(TOKEN_KEY) || '';
}

class ApiError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }
}

async function api(path, method = 'GET') {
  const headers = { Accept: 'application/json' };
  if (token()) headers.Authorization = 'Bearer ' + token();
  const r = await fetch(API + path, { method, headers, cache: 'no-store' });
  let body = null;
  try {
    body = await r.json();
  } catch (_) {
    // not JSON
  }
  if (!r.ok) {
    const message = body && body.message ? body.message : `${r.status} ${r.statusText}`;
    throw new ApiError(r.status, body && body.code, message);
  }
  return body;
}

// A read whose 404 with this code is a state, not a failure (no set yet, no model yet).
async function maybe(path, code) {
  try {
    return await api(path);
  } catch (e) {
    if (e.status === 404 && e.code === code) return null;
    throw e;
  }
}

const enc = encodeURIComponent;

// ---- formatting ----

// EX0B, EY0C, EZ0B... are positions (um); EA0B, EB0C, EC0A... angles (urad).
function unit(name) {
  return /^E[XYZ]/.test(name) ? 'um' : 'urad';
}

function num(v, digits = 1) {
  return v == null || !isFinite(v) ? '-' : Number(v).toFixed(digits);
}

function utc(ns) {
  if (ns == null) return '-';
  return new Date(ns / 1e6).toISOString().replace('T', ' ').slice(0, 19) + ' UTC';
}

function hhmm(ns) {
  return new Date(ns / 1e6).toISOString().slice(11, 16);
}

function age(ns) {
  if (ns == null) return '-';
  const s = ns / 1e9;
  if (s < 120) return `${Math.round(s)} s`;
  if (s < 7200) return `${Math.round(s / 60)} min`;
  return `${(s / 3600).toFixed(1)} h`;
}

// How old something stamped at t_ns is on the service clock `clock`, both from one answer of
// the API (never the browser's clock): a negative age is said as "ahead", never printed.
function ageOf(clock, t_ns) {
  if (clock == null || t_ns == null) return { ns: null, text: 'age unknown (the answer carries no clock)' };
  const d = clock - t_ns;
  if (d < 0) return { ns: d, text: `${age(-d)} ahead of the service clock` };
  return { ns: d, text: `${age(d)} old` };
}

// The clock of an answer about a machine: the service clock when it was made, else (an API
// not told its clock) the loop's last step.
function clockOf(m) {
  return m.service_clock_ns ?? m.clock_ns;
}

// What moves the service clock, in words (from /service).
function clockKind(svc) {
  if (!svc || !svc.clock) return null;
  if (svc.clock === 'manual') return 'simulated clock, moved by hand: not the time of day';
  if (svc.clock === 'scaled') {
    const k = svc.time_scale;
    const rate = k >= 1 ? `${num(k, k < 10 ? 1 : 0)}\u00d7 faster than` : `${num(1 / k, 1)}\u00d7 slower than`;
    return `simulated clock, ${rate} the wall clock: not the time of day`;
  }
  return null;
}

// The header: the service clock of the answer and, when it is not the wall clock, what it is.
function showClock(clock, svc) {
  document.getElementById('clock').textContent = clock != null ? `service clock ${utc(clock)}` : '';
  const kind = clockKind(svc);
  const k = document.getElementById('clock-kind');
  k.textContent = kind || '';
  k.hidden = !kind;
}

// ---- the DOM ----

function el(tag, attrs, ...children) {
  const e = document.createElement(tag);
  return fill(e, attrs, children);
}

function svg(tag, attrs, ...children) {
  return fill(document.createElementNS(SVG, tag), attrs, children);
}

function fill(e, attrs, children) {
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v == null || v === false) continue;
    if (k.startsWith('on')) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v === true ? '' : v);
  }
  for (const c of children.flat()) {
    if (c == null || c === false) continue;
    e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return e;
}

function table(head, rows, empty) {
  if (!rows.length) return el('p', { class: 'muted' }, empty);
  return el('table', {},
    el('thead', {}, el('tr', {}, head.map((h) => el('th', {}, h)))),
    el('tbody', {}, rows));
}

// ---- the fleet ----

async function loadFleet() {
  // The machines' served sets come in their summaries with the clock of that answer, so
  // that a set's age is measured on the clock that stamped it.
  const [machines, svc] = await Promise.all([api('/machines'), api('/service')]);
  const more = await Promise.all(machines.map(async (m) => {
    const alerts = await api(`/machines/${enc(m.id)}/alerts?limit=1`);
    return { m, open: alerts.open, thresholds: alerts.thresholds || [] };
  }));
  return { svc, tiles: more };
}

// The served error largest in size, of one unit.
function largest(set, u) {
  if (!set) return null;
  let best = null;
  for (const [name, value] of Object.entries(set.errors)) {
    if (unit(name) !== u) continue;
    if (!best || Math.abs(value) > Math.abs(best.value)) {
      best = { name, value, sigma: set.sigma[name] };
    }
  }
  return best;
}

// What a served value is: the compensation set it belongs to.
function servedWhat(set) {
  return set.source === 'measured' && set.cycle != null
    ? `served v${set.version}, measured in cycle ${set.cycle}`
    : `served v${set.version}, ${set.source}`;
}

// A threshold rule in words: where it raises and clears, about which reference.
function thresholdText(t, u) {
  if (t.reference == null) return `limit \u00b1${num(t.limit)} ${u} from the first validated value (none yet)`;
  return `limit \u00b1${num(t.limit)} ${u} (clear \u00b1${num(t.clear)}) from ${num(t.reference)} ${u}`;
}

function largestLine(set, thresholds, u) {
  const b = largest(set, u);
  if (!b) return null;
  const t = thresholds.find((r) => r.error === b.name);
  return el('div', { class: 'largest', 'data-unit': u },
    el('span', { class: 'label' }, `largest (${u})`),
    `${b.name} ${num(b.value)} \u00b1 ${num(K * b.sigma)} ${u}`,
    el('div', { class: 'rule-note' }, `the ${servedWhat(set)}; `,
      t ? `alert ${thresholdText(t, u)}` : `no threshold rule on ${b.name}`));
}

// An open alert with the cycle its message describes: its value is that cycle's, not the
// served set's.
function alertLine(a) {
  const when = a.last_cycle === a.raised_cycle
    ? `at cycle ${a.last_cycle}, which raised it`
    : `at cycle ${a.last_cycle} (raised at cycle ${a.raised_cycle})`;
  return el('div', { class: `alert-line ${a.severity}`, 'data-rule': a.rule },
    el('span', { class: 'rule' }, a.rule), ` ${when}: ${a.message}`,
    a.acknowledged ? el('span', { class: 'acked' }, ` (acknowledged by ${a.acknowledged.by})`) : null);
}

function servedLine(m, set) {
  if (!set) {
    return el('div', { class: 'served' }, el('span', { class: 'label' }, 'served set'),
      'none yet: the NC keeps its own values');
  }
  const a = ageOf(clockOf(m), set.valid_from_ns);
  return el('div', { class: 'served', 'data-age-ns': a.ns, 'data-version': set.version },
    el('span', { class: 'label' }, 'served set'),
    `v${set.version}, ${set.source}`, set.cycle != null ? ` (cycle ${set.cycle})` : '',
    `, ${a.text}`,
    el('div', { class: 'reason' }, `why: ${set.reason}`));
}

function fleetTile({ m, open, thresholds }, simulated) {
  const phase = m.phase ? m.phase.phase : 'starting';
  const phaseText = phase.replace(/_/g, ' ');
  const set = m.compensation;
  const unacked = open.filter((a) => !a.acknowledged).length;
  const elsewhere = m.fleet && !m.fleet.here;
  return el('a', { class: `tile ${m.failing ? 'failing' : ''}`, href: `#/machine/${enc(m.id)}`, 'data-machine': m.id },
    el('h2', {}, m.id, el('span', { class: 'muted' }, ` ${m.kinematics}`),
      simulated ? el('span', { class: 'badge sim' }, 'simulated machine') : null),
    el('div', { class: `phase ${phase}` }, phaseText),
    servedLine(m, set),
    largestLine(set, thresholds, 'um'),
    largestLine(set, thresholds, 'urad'),
    elsewhere
      ? el('div', {}, el('span', { class: 'label' }, 'open alerts'), 'shown by the process that runs it')
      : el('div', { class: open.length ? 'alerts-open' : '' },
        el('span', { class: 'label' }, 'open alerts'),
        open.length ? `${open.length} (${unacked} not acknowledged)` : 'none'),
    elsewhere ? null : open.slice(0, 3).map(alertLine),
    !elsewhere && open.length > 3 ? el('div', { class: 'muted' }, `and ${open.length - 3} more`) : null,
    m.fleet
      ? el('div', {}, el('span', { class: 'label' }, 'run by'),
        m.fleet.holder ? `${m.fleet.holder}${m.fleet.here ? ' (this process)' : ''}` : 'no process just now')
      : null,
    m.failing && m.last_fault ? el('div', { class: 'fault' }, `failing: ${m.last_fault.message}`) : null);
}

function drawFleet(view, { svc, tiles }) {
  const clocks = tiles.map((t) => clockOf(t.m)).filter((c) => c != null);
  showClock(clocks.length ? Math.max(...clocks) : null, svc);
  const simulated = new Set(svc.simulated || []);
  view.replaceChildren(
    el('h1', {}, 'Fleet'),
    el('div', { class: 'tiles' }, tiles.map((t) => fleetTile(t, simulated.has(t.m.id)))));
}

// ---- one machine ----

async function loadMachine(id) {
  const p = `/machines/${enc(id)}`;
  const [m, svc] = await Promise.all([api(p), api('/service')]);
  // The window ends at the clock of the machine's answer; the set shown is the one in it.
  const to = clockOf(m) || 0;
  const from = to - WINDOW_NS;
  const [nc, measured, predicted, cycles, alerts, diagnoses, verifications, geometry] =
    await Promise.all([
      m.compensation ? ncVariables(p) : null,
      api(`${p}/errors?source=measured&from=${from}&to=${to}`),
      api(`${p}/errors?source=predicted&from=${from}&to=${to}`),
      api(`${p}/cycles?limit=20`),
      api(`${p}/alerts?limit=10`),
      api(`${p}/diagnoses?limit=10`),
      api(`${p}/verifications?limit=5`),
      api(`${p}/geometry`),
    ]);
  return { m, svc, from, to, set: m.compensation, nc, measured, predicted, cycles, alerts, diagnoses, verifications, geometry };
}

// The served set in driftwatch's own NC form (its variables with units and steps), or why
// the API would not give it.
async function ncVariables(p) {
  try {
    return { body: await api(`${p}/compensation?format=json`) };
  } catch (e) {
    return { refused: e.message };
  }
}

// One error over the window: measured points with their bars, the predicted line and band.
function chart(name, from, to, measured, predicted, threshold, clockName) {
  const W = 640, H = 200, L = 56, R = 12, T = 22, B = 28;
  const asked = { from, to };
  // Drawn from a little before the first value (a machine that started an hour ago has no
  // empty seven hours); the window asked for stays in data-from and data-to.
  const first = Math.min(...measured.concat(predicted).map((s) => s.t_ns));
  from = Math.max(from, Math.min(first, to - NS_PER_H) - 10 * NS_PER_MIN);
  const u = unit(name);
  const all = measured.concat(predicted);
  // The alert rule's lines: reference +- limit (raises) and +- clear (resolves). The range
  // takes the limits in, so that how far a value is from them shows at a glance.
  const ref = threshold && threshold.reference != null ? threshold.reference : null;
  const lines = ref == null ? [] : [
    { kind: 'limit', v: ref + threshold.limit }, { kind: 'clear', v: ref + threshold.clear },
    { kind: 'clear', v: ref - threshold.clear }, { kind: 'limit', v: ref - threshold.limit },
  ];
  let lo = Math.min(...all.map((s) => s.value - K * s.sigma), ...lines.map((l) => l.v));
  let hi = Math.max(...all.map((s) => s.value + K * s.sigma), ...lines.map((l) => l.v));
  if (!(hi > lo)) { lo -= 1; hi += 1; }
  const pad = (hi - lo) * 0.05;
  lo -= pad; hi += pad;
  const x = (t) => L + ((t - from) / (to - from)) * (W - L - R);
  const y = (v) => T + ((hi - v) / (hi - lo)) * (H - T - B);
  const parts = [];
  // Axes and ticks: five values, the hours of the window.
  for (let i = 0; i <= 4; i++) {
    const v = lo + ((hi - lo) * i) / 4;
    parts.push(svg('line', { class: 'grid', x1: L, x2: W - R, y1: y(v), y2: y(v) }));
    parts.push(svg('text', { class: 'tick', x: L - 4, y: y(v) + 4, 'text-anchor': 'end' }, num(v)));
  }
  for (let t = Math.ceil(from / NS_PER_H) * NS_PER_H; t <= to; t += NS_PER_H) {
    parts.push(svg('line', { class: 'grid', x1: x(t), x2: x(t), y1: T, y2: H - B }));
    parts.push(svg('text', { class: 'tick', x: x(t), y: H - B + 14, 'text-anchor': 'middle' }, hhmm(t)));
  }
  parts.push(svg('text', { class: 'title', x: L, y: 14 }, `${name} (${u})`));
  parts.push(svg('text', { class: 'tick', x: W - R, y: 14, 'text-anchor': 'end' }, `UTC, ${clockName}`));
  if (ref != null) {
    parts.push(svg('line', { class: 'reference', x1: L, x2: W - R, y1: y(ref), y2: y(ref), 'data-value': ref },
      svg('title', {}, `reference ${num(ref, 2)} ${u}`)));
  }
  for (const l of lines) {
    const word = l.kind === 'limit' ? 'alert limit' : 'clears within';
    parts.push(svg('line', { class: l.kind, x1: L, x2: W - R, y1: y(l.v), y2: y(l.v), 'data-value': l.v },
      svg('title', {}, `${threshold.rule}: ${word} ${num(l.v, 2)} ${u} (${l.v >= ref ? '+' : '\u2212'}${num(Math.abs(l.v - ref), 1)} from ${num(ref, 1)})`)));
    if (l.kind === 'limit') {
      parts.push(svg('text', { class: 'limit-label', x: W - R - 2, y: y(l.v) - 3, 'text-anchor': 'end' },
        `alert ${l.v >= ref ? '+' : '\u2212'}${num(threshold.limit, 0)} ${u}`));
    }
  }
  // The predicted band and line through the served predictions (each held until the next).
  if (predicted.length) {
    const upper = predicted.map((s) => `${x(s.t_ns)},${y(s.value + K * s.sigma)}`);
    const lower = predicted.slice().reverse().map((s) => `${x(s.t_ns)},${y(s.value - K * s.sigma)}`);
    parts.push(svg('polygon', { class: 'band', points: upper.concat(lower).join(' ') }));
    parts.push(svg('polyline', { class: 'predicted', points: predicted.map((s) => `${x(s.t_ns)},${y(s.value)}`).join(' ') }));
  }
  for (const s of measured) {
    const cx = x(s.t_ns);
    parts.push(svg('line', { class: 'bar', x1: cx, x2: cx, y1: y(s.value - K * s.sigma), y2: y(s.value + K * s.sigma) }));
    parts.push(svg('circle', { class: 'measured', cx, cy: y(s.value), r: 3 },
      svg('title', {}, `cycle ${s.cycle}, ${hhmm(s.t_ns)}: ${num(s.value, 2)} \u00b1 ${num(K * s.sigma, 2)} ${u}`)));
  }
  return svg('svg', {
    class: 'chart', viewBox: `0 0 ${W} ${H}`, role: 'img',
    'aria-label': `${name} over the window, ${u}`,
    'data-error': name, 'data-from': asked.from, 'data-to': asked.to, 'data-measured': measured.length,
    'data-limits': lines.length,
  }, parts);
}

function charts(d) {
  const names = [...new Set(d.measured.concat(d.predicted).map((s) => s.name))].sort();
  if (!names.length) return el('p', { class: 'muted' }, 'No validated cycle in the window yet.');
  const of = (list, n) => list.filter((s) => s.name === n).sort((a, b) => a.t_ns - b.t_ns);
  const rule = (n) => (d.alerts.thresholds || []).find((t) => t.error === n);
  const clockName = d.svc.clock === 'manual' || d.svc.clock === 'scaled' ? 'simulated service clock' : 'service clock';
  return el('div', { class: 'charts' },
    names.map((n) => chart(n, d.from, d.to, of(d.measured, n), of(d.predicted, n), rule(n), clockName)));
}

// The served sets of the window, newest first: one row per time and source.
function servedHistory(d) {
  const sets = new Map();
  for (const s of d.measured.concat(d.predicted)) {
    const key = `${s.t_ns} ${s.source}`;
    if (!sets.has(key)) sets.set(key, { t_ns: s.t_ns, source: s.source, cycle: s.cycle, n: 0 });
    sets.get(key).n += 1;
  }
  const rows = [...sets.values()].sort((a, b) => b.t_ns - a.t_ns).slice(0, 12);
  return table(['time', 'source', 'cycle', 'errors'],
    rows.map((r) => el('tr', {}, el('td', {}, utc(r.t_ns)), el('td', { class: r.source }, r.source),
      el('td', {}, r.cycle), el('td', {}, r.n))),
    'No served set in the window.');
}

function servedNow(set, clock) {
  if (!set) return el('p', { class: 'muted' }, 'No validated set yet: the NC keeps its own values.');
  const a = ageOf(clock, set.valid_from_ns);
  return el('div', {},
    el('p', { class: 'served-now', 'data-age-ns': a.ns }, `Version ${set.version}, ${set.source}`, set.cycle != null ? ` (cycle ${set.cycle})` : '',
      `, valid from ${utc(set.valid_from_ns)} (${a.text}): ${set.reason}`),
    table(['error', 'value', `\u00b1${K}\u03c3`, 'unit'],
      Object.keys(set.errors).sort().map((n) => el('tr', {}, el('td', {}, n),
        el('td', { class: 'num' }, num(set.errors[n], 2)), el('td', { class: 'num' }, num(K * set.sigma[n], 2)),
        el('td', {}, unit(n)))), ''));
}

// An offset's unit from its name (`B_pivot_z_um`, `C_tilt_a_urad`).
function offsetUnit(name) {
  const m = name.match(/_(um|urad|mm|deg)$/);
  return m ? m[1] : '';
}

// The NC offsets of the served set (what the NC applies), with the variables of the NC form
// (meaning, step from the previous served set) where the API gave them for this version.
function offsetsTable(id, set, nc) {
  if (!set) return el('p', { class: 'muted' }, 'No validated set yet: no offsets are served.');
  const vars = new Map();
  const body = nc && nc.body && nc.body.version === set.version ? nc.body : null;
  for (const v of (body && body.variables) || []) vars.set(v.name, v);
  const names = Object.keys(set.offsets).sort();
  const prev = body && body.previous_version != null ? `step from v${body.previous_version}` : 'step';
  return el('div', {},
    el('p', {}, `The offsets of version ${set.version}, as the NC applies them (each a sum of the errors above).`),
    names.length
      ? el('table', { class: 'offsets' },
        el('thead', {}, el('tr', {}, ['offset', 'value', 'unit', prev, 'meaning'].map((h) => el('th', {}, h)))),
        el('tbody', {}, names.map((n) => {
          const v = vars.get(n);
          return el('tr', { 'data-offset': n }, el('td', {}, n),
            el('td', { class: 'num' }, num(set.offsets[n], 2)), el('td', { class: 'unit' }, v ? v.unit : offsetUnit(n)),
            el('td', { class: 'num' }, v && v.step != null ? num(v.step, 2) : '-'), el('td', {}, v ? v.meaning : ''));
        })))
      : el('p', { class: 'muted' }, 'This set has no offsets.'),
    nc && nc.refused ? el('p', { class: 'muted' }, `The NC form was refused: ${nc.refused}`) : null,
    el('p', { class: 'muted' }, 'A control\u2019s own variables: ',
      el('a', { href: `${API}/machines/${enc(id)}/compensation?format=json` }, 'format=json'),
      ' (fanuc, siemens, heidenhain and linuxcnc programs: docs/nc.md).'));
}

function verificationLine(v) {
  return `Latest verification: ${v.instrument} at ${utc(v.t_ns)}, ` +
    (v.exceeds_any ? `an error exceeds ${v.k} combined \u03c3` : `within ${v.k} combined \u03c3`) +
    ` (largest |z|: ${v.worst_error}, z = ${num(v.worst_z, 2)}).`;
}

// What the acknowledge buttons answered, by alert id (kept across redraws).
const ackNotes = new Map();

async function acknowledge(id, alert) {
  try {
    const r = await api(`/machines/${enc(id)}/alerts/${alert}/ack`, 'POST');
    ackNotes.set(alert, {
      ok: true,
      text: r.already ? `already acknowledged by ${r.by}` : `acknowledgement by ${r.by} taken: the loop applies it at its next step`,
    });
  } catch (e) {
    ackNotes.set(alert, { ok: false, text: `refused: ${e.message}` });
  }
  refresh(true);
}

function alertRows(id, open) {
  return open.map((a) => {
    const note = ackNotes.get(a.id);
    return el('tr', { 'data-alert': a.id },
      el('td', {}, a.id), el('td', {}, a.rule), el('td', { class: a.severity }, a.severity),
      el('td', {}, utc(a.raised_t_ns), el('div', { class: 'muted' }, `cycle ${a.raised_cycle}`)),
      el('td', { class: 'alert-message' }, el('span', { class: 'what' }, `at cycle ${a.last_cycle}: `), a.message),
      el('td', {},
        a.acknowledged
          ? el('span', { class: 'acked' }, `acknowledged by ${a.acknowledged.by}`)
          : el('button', { class: 'ack', type: 'button', onclick: () => acknowledge(id, a.id) }, 'Acknowledge'),
        note && !(note.ok && a.acknowledged)
          ? el('div', { class: `ack-note ${note.ok ? 'ok' : 'refused'}` }, note.text)
          : null));
  });
}

function thresholdList(thresholds) {
  if (!thresholds || !thresholds.length) return null;
  return el('p', { class: 'muted thresholds' }, 'Threshold rules (the dashed lines on the charts): ',
    thresholds.map((t) => `${t.error} ${thresholdText(t, unit(t.error))}` +
      (t.reference != null && !t.reference_configured ? ' (the first validated value the alert rules saw)' : ''))
      .join('; '),
    '.');
}

function drawMachine(view, d) {
  const m = d.m;
  const id = m.id;
  const clock = clockOf(m);
  showClock(clock, d.svc);
  const simulated = (d.svc.simulated || []).includes(id);
  const phase = m.phase ? m.phase.phase : 'starting';
  const phaseText = phase.replace(/_/g, ' ');
  view.replaceChildren(
    el('p', {}, el('a', { href: '#/' }, '\u2190 fleet')),
    el('h1', {}, id, el('span', { class: 'muted' }, ` ${m.kinematics}`),
      simulated ? el('span', { class: 'badge sim' }, 'simulated machine') : null),
    el('p', { class: 'summary' },
      el('span', { class: `phase ${phase}` }, phaseText),
      m.phase ? ` spindle ${num(m.phase.spindle_rpm, 0)} min\u207b\u00b9, since ${utc(m.phase.since_ns)}. ` : ' ',
      `Last cycle ${m.last_cycle ?? '-'}`, m.open_cycle != null ? `, cycle ${m.open_cycle} running` : '',
      `. Scheduler: ${m.schedule}`,
      m.failing && m.last_fault ? el('span', { class: 'fault' }, ` Failing: ${m.last_fault.message}`) : null),
    el('h2', {}, `Errors over the last ${WINDOW_NS / NS_PER_H} h of the service clock, to ${utc(d.to)}`),
    el('p', { class: 'legend' },
      el('span', { class: 'key measured' }, '\u25cf measured (validated cycles, \u00b12\u03c3)'),
      el('span', { class: 'key predicted' }, '\u2014 predicted by the thermal model (band \u00b12\u03c3)'),
      el('span', { class: 'key limit' }, '- - alert limit'),
      el('span', { class: 'key clear' }, '\u00b7\u00b7\u00b7 clears within'),
      el('span', { class: 'key reference' }, '\u2014 reference')),
    charts(d),
    thresholdList(d.alerts.thresholds),
    el('div', { class: 'columns' },
      el('section', {}, el('h2', {}, 'Served set'), servedNow(d.set, clock)),
      el('section', {}, el('h2', {}, 'Served set history'), servedHistory(d))),
    el('h2', {}, 'NC offsets'),
    offsetsTable(id, d.set, d.nc),
    el('h2', {}, 'Alerts'),
    el('p', { class: 'muted' }, 'Each message describes the cycle it names, not the served set.'),
    table(['id', 'rule', 'severity', 'raised', 'message (at its cycle)', ''], alertRows(id, d.alerts.open), 'No open alert.'),
    el('details', {}, el('summary', {}, 'Latest alert events'),
      table(['time', 'alert', 'kind', 'message'],
        d.alerts.events.map((e) => el('tr', {}, el('td', {}, utc(e.t_ns)), el('td', {}, `${e.alert} ${e.rule}`),
          el('td', {}, e.kind), el('td', {}, e.message))), 'None.')),
    el('h2', {}, 'Cycles'),
    table(['cycle', 'started', 'trigger', 'status', 'reason'],
      d.cycles.map((c) => el('tr', { 'data-cycle': c.cycle }, el('td', {}, c.cycle), el('td', {}, utc(c.started_ns)),
        el('td', {}, c.trigger), el('td', { class: `status ${c.status}` }, c.status), el('td', {}, c.reason || ''))),
      'No cycle yet.'),
    el('h2', {}, 'Diagnoses'),
    table(['id', 'window', 'status', 'summary', 'report'],
      d.diagnoses.map((g) => el('tr', {}, el('td', {}, g.id),
        el('td', {}, `${utc(g.from_ns)} to ${utc(g.to_ns)}`), el('td', {}, g.status), el('td', {}, g.summary),
        el('td', {}, el('a', { href: `${API}/machines/${enc(id)}/diagnoses/${g.id}` }, 'JSON')))),
      'No diagnosis yet (POST /api/v1/machines/{id}/diagnoses runs one).'),
    el('h2', {}, 'Verifications and geometry'),
    el('p', {},
      d.verifications.length
        ? verificationLine(d.verifications[0])
        : 'No verification against a reference instrument yet.',
      ' ',
      d.geometry.length
        ? `Linear-axis geometry version ${d.geometry[0].version} (${d.geometry[0].source}).`
        : 'No linear-axis geometry posted (the machine file\u2019s is used).'));
}

// ---- routing and polling ----

let last = '';
let timer = null;
let generation = 0;

function route() {
  const m = location.hash.match(/^#\/machine\/(.+)$/);
  return m ? { page: 'machine', id: decodeURIComponent(m[1]) } : { page: 'fleet' };
}

async function refresh(force) {
  clearTimeout(timer);
  const gen = ++generation;
  const view = document.getElementById('view');
  const r = route();
  try {
    const data = r.page === 'machine' ? await loadMachine(r.id) : await loadFleet();
    if (gen !== generation) return;
    // Redraw only on a change: an unchanged page keeps its elements (and what is focused).
    const key = JSON.stringify([r, data, [...ackNotes]]);
    if (force || key !== last) {
      last = key;
      if (r.page === 'machine') drawMachine(view, data);
      else drawFleet(view, data);
    }
  } catch (e) {
    if (gen !== generation) return;
    last = '';
    const hint = e.status === 401 ? ' Reads need a token here: enter one above.' : '';
    view.replaceChildren(el('p', { class: 'error' }, `The API answered: ${e.message}.${hint}`));
  }
  timer = setTimeout(() => refresh(false), POLL_MS);
}

function showTokenState() {
  document.getElementById('token-state').textContent = token() ? 'token set for this tab' : 'no token';
}

document.addEventListener('DOMContentLoaded', () => {
  document.getElementById('token-form').addEventListener('submit', (ev) => {
    ev.preventDefault();
    const input = document.getElementById('token');
    sessionStorage.setItem(TOKEN_KEY, input.value.trim());
    input.value = '';
    ackNotes.clear();
    showTokenState();
    refresh(true);
  });
  document.getElementById('token-forget').addEventListener('click', () => {
    sessionStorage.removeItem(TOKEN_KEY);
    ackNotes.clear();
    showTokenState();
    refresh(true);
  });
  window.addEventListener('hashchange', () => refresh(true));
  showTokenState();
  refresh(true);
});

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
  const machines = await api('/machines');
  const more = await Promise.all(machines.map(async (m) => {
    const id = enc(m.id);
    const [set, alerts] = await Promise.all([
      maybe(`/machines/${id}/compensation`, 'no_compensation'),
      api(`/machines/${id}/alerts?limit=1`),
    ]);
    return { m, set, open: alerts.open };
  }));
  return more;
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

function largestLine(set, open, u) {
  const b = largest(set, u);
  if (!b) return null;
  // The limits are the alert rules' (config [[alerts]]); the API tells them through the
  // threshold alert an error has open.
  const alert = open.find((a) => a.rule === `threshold:${b.name}`);
  return el('div', {},
    el('span', { class: 'label' }, `largest (${u})`),
    `${b.name} ${num(b.value)} \u00b1 ${num(K * b.sigma)} ${u}`,
    alert
      ? el('div', { class: `limit ${alert.severity}` }, alert.message)
      : el('div', { class: 'limit ok' }, 'no threshold alert open'));
}

function drawFleet(view, tiles) {
  const clock = Math.max(0, ...tiles.map((t) => t.m.clock_ns || 0));
  document.getElementById('clock').textContent = clock ? utc(clock) : '';
  view.replaceChildren(
    el('h1', {}, 'Fleet'),
    el('div', { class: 'tiles' }, tiles.map(({ m, set, open }) => {
      const phase = m.phase ? m.phase.phase : 'starting';
  const phaseText = phase.replace(/_/g, ' ');
      const unacked = open.filter((a) => !a.acknowledged).length;
      return el('a', { class: `tile ${m.failing ? 'failing' : ''}`, href: `#/machine/${enc(m.id)}`, 'data-machine': m.id },
        el('h2', {}, m.id, el('span', { class: 'muted' }, ` ${m.kinematics}`)),
        el('div', { class: `phase ${phase}` }, phaseText),
        el('div', {},
          el('span', { class: 'label' }, 'served set'),
          set
            ? `v${set.version}, ${set.source}, ${age((m.clock_ns || set.valid_from_ns) - set.valid_from_ns)} old`
            : 'none yet: the NC keeps its own values'),
        largestLine(set, open, 'um'),
        largestLine(set, open, 'urad'),
        m.fleet && !m.fleet.here
          ? el('div', {}, el('span', { class: 'label' }, 'open alerts'),
            'shown by the process that runs it')
          : el('div', { class: open.length ? 'alerts-open' : '' },
            el('span', { class: 'label' }, 'open alerts'),
            open.length ? `${open.length} (${unacked} not acknowledged)` : 'none'),
        m.fleet
          ? el('div', {}, el('span', { class: 'label' }, 'run by'),
            m.fleet.holder ? `${m.fleet.holder}${m.fleet.here ? ' (this process)' : ''}` : 'no process just now')
          : null,
        m.failing && m.last_fault ? el('div', { class: 'fault' }, `failing: ${m.last_fault.message}`) : null);
    })));
}

// ---- one machine ----

async function loadMachine(id) {
  const p = `/machines/${enc(id)}`;
  const m = await api(p);
  const to = m.clock_ns || 0;
  const from = to - WINDOW_NS;
  const [set, measured, predicted, cycles, alerts, diagnoses, verifications, geometry] =
    await Promise.all([
      maybe(`${p}/compensation`, 'no_compensation'),
      api(`${p}/errors?source=measured&from=${from}&to=${to}`),
      api(`${p}/errors?source=predicted&from=${from}&to=${to}`),
      api(`${p}/cycles?limit=20`),
      api(`${p}/alerts?limit=10`),
      api(`${p}/diagnoses?limit=10`),
      api(`${p}/verifications?limit=5`),
      api(`${p}/geometry`),
    ]);
  return { m, from, to, set, measured, predicted, cycles, alerts, diagnoses, verifications, geometry };
}

// One error over the window: measured points with their bars, the predicted line and band.
function chart(name, from, to, measured, predicted) {
  const W = 640, H = 200, L = 56, R = 12, T = 22, B = 28;
  const asked = { from, to };
  // Drawn from a little before the first value (a machine that started an hour ago has no
  // empty seven hours); the window asked for stays in data-from and data-to.
  const first = Math.min(...measured.concat(predicted).map((s) => s.t_ns));
  from = Math.max(from, Math.min(first, to - NS_PER_H) - 10 * NS_PER_MIN);
  const u = unit(name);
  const all = measured.concat(predicted);
  let lo = Math.min(...all.map((s) => s.value - K * s.sigma));
  let hi = Math.max(...all.map((s) => s.value + K * s.sigma));
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
  parts.push(svg('text', { class: 'tick', x: W - R, y: 14, 'text-anchor': 'end' }, 'UTC, service clock'));
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
  }, parts);
}

function charts(d) {
  const names = [...new Set(d.measured.concat(d.predicted).map((s) => s.name))].sort();
  if (!names.length) return el('p', { class: 'muted' }, 'No validated cycle in the window yet.');
  const of = (list, n) => list.filter((s) => s.name === n).sort((a, b) => a.t_ns - b.t_ns);
  return el('div', { class: 'charts' },
    names.map((n) => chart(n, d.from, d.to, of(d.measured, n), of(d.predicted, n))));
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
  return el('div', {},
    el('p', {}, `Version ${set.version}, ${set.source}`, set.cycle != null ? ` (cycle ${set.cycle})` : '',
      `, valid from ${utc(set.valid_from_ns)} (${age(clock - set.valid_from_ns)} ago): ${set.reason}`),
    table(['error', 'value', `\u00b1${K}\u03c3`, 'unit'],
      Object.keys(set.errors).sort().map((n) => el('tr', {}, el('td', {}, n),
        el('td', { class: 'num' }, num(set.errors[n], 2)), el('td', { class: 'num' }, num(K * set.sigma[n], 2)),
        el('td', {}, unit(n)))), ''));
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
      el('td', {}, utc(a.raised_t_ns)), el('td', {}, a.message),
      el('td', {},
        a.acknowledged
          ? el('span', { class: 'acked' }, `acknowledged by ${a.acknowledged.by}`)
          : el('button', { class: 'ack', type: 'button', onclick: () => acknowledge(id, a.id) }, 'Acknowledge'),
        note && !(note.ok && a.acknowledged)
          ? el('div', { class: `ack-note ${note.ok ? 'ok' : 'refused'}` }, note.text)
          : null));
  });
}

function drawMachine(view, d) {
  const m = d.m;
  const id = m.id;
  document.getElementById('clock').textContent = utc(m.clock_ns);
  const phase = m.phase ? m.phase.phase : 'starting';
  const phaseText = phase.replace(/_/g, ' ');
  view.replaceChildren(
    el('p', {}, el('a', { href: '#/' }, '\u2190 fleet')),
    el('h1', {}, id, el('span', { class: 'muted' }, ` ${m.kinematics}`)),
    el('p', { class: 'summary' },
      el('span', { class: `phase ${phase}` }, phaseText),
      m.phase ? ` spindle ${num(m.phase.spindle_rpm, 0)} min\u207b\u00b9, since ${utc(m.phase.since_ns)}. ` : ' ',
      `Last cycle ${m.last_cycle ?? '-'}`, m.open_cycle != null ? `, cycle ${m.open_cycle} running` : '',
      `. Scheduler: ${m.schedule}`,
      m.failing && m.last_fault ? el('span', { class: 'fault' }, ` Failing: ${m.last_fault.message}`) : null),
    el('h2', {}, `Errors over the last ${WINDOW_NS / NS_PER_H} h of the service clock, to ${utc(d.to)}`),
    el('p', { class: 'legend' },
      el('span', { class: 'key measured' }, '\u25cf measured (validated cycles, \u00b12\u03c3)'),
      el('span', { class: 'key predicted' }, '\u2014 predicted by the thermal model (band \u00b12\u03c3)')),
    charts(d),
    el('div', { class: 'columns' },
      el('section', {}, el('h2', {}, 'Served set'), servedNow(d.set, m.clock_ns)),
      el('section', {}, el('h2', {}, 'Served set history'), servedHistory(d))),
    el('h2', {}, 'Alerts'),
    table(['id', 'rule', 'severity', 'raised', 'message', ''], alertRows(id, d.alerts.open), 'No open alert.'),
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

// Fleet overview: every robot live, in a table that renders only the rows on screen.
//
// Frames change a plain model (robots by id) and mark robots dirty; one requestAnimationFrame
// pass then rewrites only the cells of visible rows whose text changed. Hundreds of robots
// sending metrics four times a second cost a few dozen cell writes per frame.

import { get, seg } from "./api.js";
import { labelChips, labelText } from "./labels.js";
import { startLive } from "./live.js";
import {
  ROBOT_METRICS,
  debounce,
  el,
  errorText,
  fmtAgo,
  fmtMetric,
  fmtTime,
  frameBatcher,
  isoSeconds,
  pageData,
  setClass,
  setText,
} from "./util.js";

const METRIC_NAMES = Object.keys(ROBOT_METRICS);
const ACTIVE = new Set(["running", "starting", "migrating", "stopping"]);
const OVERSCAN = 8;
// Sorting by a live metric reorders rows at most this often, so rows do not jump under the pointer.
const METRIC_RESORT_MS = 3000;

const table = document.getElementById("fleet");
const tbody = document.getElementById("fleet-rows");
const summary = document.getElementById("fleet-summary");
const emptyNote = document.getElementById("fleet-empty");
const noMatch = document.getElementById("fleet-no-match");
const filterInput = document.getElementById("fleet-filter");
const stateSelect = document.getElementById("fleet-state");
const filterResult = document.getElementById("fleet-filter-result");

const robots = new Map(); // id -> robot model
const dirty = new Set();
const rows = new Map(); // id -> {tr, cells} for rows built so far
let order = []; // ids in view order after filter and sort
let orderDirty = true;
let windowDirty = true;
let lastMetricSort = 0;
let rendered = { first: 0, last: -1 };
let rowHeight = 0;
let sort = { key: "id", dir: 1 };
// A search with '=' is a label selector, evaluated by the cloud: the ids it matched (null: not a selector).
let selected = null;
let selectorAsked = "";

// --------------------------------------------------------------------------- the model

function normalise(raw, previous) {
  return {
    id: raw.id,
    name: raw.name || "",
    labels: raw.labels ?? previous?.labels ?? {},
    connected: Boolean(raw.connected),
    status: raw.status,
    lastSeen: isoSeconds(raw.last_seen),
    offloading: raw.offloading ?? raw.config?.offloading ?? "",
    skills: new Map(
      (raw.skills ?? []).map((skill) => [
        skill.skill_id,
        {
          status: skill.status,
          components: new Map(
            (skill.components ?? []).map((c) => [c.component_id, { active: c.active_location || "", status: c.status }]),
          ),
        },
      ]),
    ),
    // A fresh copy from the API carries no metrics: keep the live ones.
    metrics: { ...(previous?.metrics ?? {}), ...(raw.metrics ?? {}) },
  };
}

function counts(robot) {
  let onRobot = 0;
  let onCloud = 0;
  let total = 0;
  for (const skill of robot.skills.values()) {
    for (const component of skill.components.values()) {
      total += 1;
      if (!ACTIVE.has(component.status)) continue;
      if (component.active === "robot") onRobot += 1;
      else if (component.active === "cloud") onCloud += 1;
    }
  }
  return { skills: robot.skills.size, onRobot, onCloud, total };
}

function upsert(raw) {
  const robot = normalise(raw, robots.get(raw.id));
  const known = robots.has(robot.id);
  robots.set(robot.id, robot);
  if (!known) orderDirty = true;
  touch(robot.id, !known);
}

function touch(id, structural = false) {
  dirty.add(id);
  if (structural || sort.key === "connected" || stateSelect.value !== "all") orderDirty = true;
  schedule();
}

const fetching = new Set();

/** Load a robot the page does not know yet (added after the page loaded) or whose skills changed. */
async function refresh(id) {
  if (fetching.has(id)) return;
  fetching.add(id);
  const answer = await get(`/api/robot/${seg(id)}`);
  fetching.delete(id);
  if (answer.ok) upsert(answer.data);
}

// --------------------------------------------------------------------------- live frames

function onMetrics(frame) {
  const robot = robots.get(frame.data.robot);
  if (!robot) return;
  let changed = false;
  for (const point of frame.data.metrics) {
    if (point.skill || point.component || !(point.name in ROBOT_METRICS)) continue;
    const known = robot.metrics[point.name];
    if (!known || point.ts >= known[1]) {
      robot.metrics[point.name] = [point.value, point.ts];
      changed = true;
    }
  }
  if (changed) touch(robot.id);
}

function onConnection(frame, connected) {
  const robot = robots.get(frame.data.robot);
  if (!robot) {
    refresh(frame.data.robot);
    return;
  }
  robot.connected = connected;
  if (connected) robot.status = "running";
  robot.lastSeen = frame.ts || Date.now() / 1000;
  touch(robot.id, sort.key === "seen");
}

function component(frame) {
  const robot = robots.get(frame.data.robot);
  const found = robot?.skills.get(frame.data.skill)?.components.get(frame.data.component);
  if (!found) refresh(frame.data.robot);
  return found;
}

function wire(live) {
  live.on("metrics", onMetrics);
  live.on("connection_established", (frame) => onConnection(frame, true));
  live.on("connection_lost", (frame) => onConnection(frame, false));
  live.on("component_status", (frame) => {
    const found = component(frame);
    if (!found) return;
    found.status = frame.data.status;
    if (frame.data.location) found.active = frame.data.location;
    touch(frame.data.robot);
  });
  live.on("component_location", (frame) => {
    const found = component(frame);
    if (!found) return;
    found.active = frame.data.location;
    touch(frame.data.robot);
  });
  live.on("skill_status", (frame) => {
    const skill = robots.get(frame.data.robot)?.skills.get(frame.data.skill);
    if (!skill) refresh(frame.data.robot);
    else skill.status = frame.data.status;
  });
  live.on("skill_config", (frame) => refresh(frame.data.robot));
  live.on("offloading", (frame) => {
    const robot = robots.get(frame.data.robot);
    if (!robot) return;
    robot.offloading = frame.data.mode;
    touch(robot.id);
  });
  // A deleted robot leaves the table at once (the cloud pushes its event-log entry).
  live.on("log_event", (frame) => {
    if (frame.data.kind === "robot_deleted") forget(frame.data.robot);
  });
  // Frames may have been missed while reconnecting: reload the fleet's state.
  live.onResync(async () => {
    const answer = await get("/api/robot");
    if (!answer.ok) return;
    const current = new Set(answer.data.map((raw) => raw.id));
    for (const id of robots.keys()) {
      if (!current.has(id)) forget(id);
    }
    for (const raw of answer.data) upsert(raw);
    schedule();
  });
}

/** Drop a robot that no longer exists from the table. */
function forget(id) {
  if (!robots.delete(id)) return;
  rows.delete(id);
  dirty.delete(id);
  orderDirty = true;
  schedule();
}

// --------------------------------------------------------------------------- order: filter and sort

const SORT_KEYS = {
  id: (r) => r.id,
  connected: (r) => (r.connected ? 0 : 1),
  cpu: (r) => r.metrics.cpu?.[0] ?? -1,
  ram: (r) => r.metrics.ram?.[0] ?? -1,
  bandwidth: (r) => r.metrics.bandwidth?.[0] ?? -1,
  battery: (r) => r.metrics.battery?.[0] ?? -1,
  offloading: (r) => r.offloading,
  skills: (r) => r.skills.size,
  components: (r) => counts(r).onCloud,
  seen: (r) => (r.connected ? Number.MAX_VALUE : r.lastSeen ?? 0),
};

function recomputeOrder() {
  const text = filterInput.value.trim().toLowerCase();
  const state = stateSelect.value;
  const key = SORT_KEYS[sort.key];
  order = [];
  for (const robot of robots.values()) {
    if (state === "online" && !robot.connected) continue;
    if (state === "offline" && robot.connected) continue;
    if (selected) {
      if (!selected.has(robot.id)) continue;
    } else if (text && !robot.id.includes(text) && !robot.name.toLowerCase().includes(text)) continue;
    order.push(robot);
  }
  order.sort((a, b) => {
    const ka = key(a);
    const kb = key(b);
    if (ka < kb) return -sort.dir;
    if (ka > kb) return sort.dir;
    return a.id < b.id ? -1 : 1;
  });
  order = order.map((robot) => robot.id);
  table.setAttribute("aria-rowcount", String(order.length + 1));
  orderDirty = false;
  windowDirty = true;
  lastMetricSort = performance.now();
}

// --------------------------------------------------------------------------- rows

function meterCell(cls) {
  const value = el("span", { class: "value" });
  const fill = el("span", { class: "fill" });
  const td = el("td", { class: `num ${cls}` }, value, el("span", { class: "bar", "aria-hidden": "true" }, fill));
  return { td, value, fill };
}

function buildRow(id) {
  const link = el("a", { href: `/robots/${seg(id)}/`, class: "robot-link" }, id);
  const name = el("span", { class: "sub" });
  const labels = el("span", { class: "labels" });
  const conn = el("span", { class: "badge" });
  const status = el("span", { class: "sub" });
  const metrics = Object.fromEntries(METRIC_NAMES.map((n) => [n, meterCell(`c-${n}`)]));
  const mode = el("span", { class: "mode" });
  const skills = el("td", { class: "num c-skills" });
  const onRobot = el("span", { class: "loc robot" });
  const onCloud = el("span", { class: "loc cloud" });
  const comps = el("td", { class: "c-comp" }, onRobot, " ", onCloud);
  const seen = el("td", { class: "c-seen" });
  const tr = el(
    "tr",
    { dataset: { robot: id } },
    el("th", { scope: "row", class: "c-robot" }, link, name, labels),
    el("td", { class: "c-conn" }, conn, status),
    ...METRIC_NAMES.map((n) => metrics[n].td),
    el("td", { class: "c-mode" }, mode),
    skills,
    comps,
    seen,
  );
  const entry = { tr, cells: { name, labels, conn, status, metrics, mode, skills, onRobot, onCloud, comps, seen } };
  rows.set(id, entry);
  return entry;
}

function updateRow(entry, robot, now) {
  const c = entry.cells;
  setText(c.name, robot.name);
  const text = labelText(robot.labels);
  if (c.labels.dataset.text !== text) {
    c.labels.dataset.text = text;
    c.labels.title = text;
    c.labels.replaceChildren(...labelChips(robot.labels, "span"));
  }
  setText(c.conn, robot.connected ? "online" : "offline");
  setClass(c.conn, "online", robot.connected);
  setClass(c.conn, "offline", !robot.connected);
  setText(c.status, robot.connected ? robot.status : "");
  setClass(entry.tr, "is-offline", !robot.connected);
  for (const name of METRIC_NAMES) {
    const cell = c.metrics[name];
    const point = robot.metrics[name];
    setText(cell.value, point ? fmtMetric(name, point[0]) : "—");
    const max = ROBOT_METRICS[name].max;
    const pct = point && max ? Math.max(0, Math.min(100, (point[0] / max) * 100)) : 0;
    const width = `${pct.toFixed(1)}%`;
    if (cell.fill.style.width !== width) cell.fill.style.width = width;
    setClass(cell.td, "empty", !point);
    setClass(cell.td, "hot", Boolean(point) && name !== "battery" && pct >= 85);
    setClass(cell.td, "low", Boolean(point) && name === "battery" && pct <= 15);
    const stale = Boolean(point) && !robot.connected;
    setClass(cell.td, "stale", stale);
    const title = point ? `${fmtMetric(name, point[0])} at ${fmtTime(point[1])}` : "no value in the last hour";
    if (cell.td.title !== title) cell.td.title = title;
  }
  setText(c.mode, robot.offloading || "—");
  c.mode.dataset.mode = robot.offloading;
  const n = counts(robot);
  setText(c.skills, String(n.skills));
  setText(c.onRobot, String(n.onRobot));
  setText(c.onCloud, String(n.onCloud));
  const label = `${n.total} components: ${n.onRobot} running on the robot, ${n.onCloud} in the cloud`;
  if (c.comps.title !== label) {
    c.comps.title = label;
    c.comps.setAttribute("aria-label", label);
  }
  setText(c.seen, robot.connected ? "connected" : fmtAgo(robot.lastSeen, now));
}

function measureRowHeight() {
  const first = tbody.querySelector("tr[data-robot]");
  if (first) rowHeight = first.getBoundingClientRect().height || rowHeight;
  // Before any row exists, the height the stylesheet gives rows.
  return rowHeight || Number.parseFloat(getComputedStyle(table).getPropertyValue("--row-h")) || 52;
}

/** Work out which rows are on screen (the page scrolls, not the table). */
function visibleRange() {
  const height = measureRowHeight();
  const top = tbody.getBoundingClientRect().top;
  const first = Math.max(0, Math.floor(-top / height) - OVERSCAN);
  const count = Math.ceil(window.innerHeight / height) + 2 * OVERSCAN;
  return { first, last: Math.min(order.length - 1, first + count - 1), height };
}

function spacer(height) {
  return el("tr", { class: "spacer", "aria-hidden": "true" }, el("td", { colspan: "10", style: `height:${height}px` }));
}

function renderWindow(now) {
  const { first, last, height } = visibleRange();
  const children = [];
  if (first > 0) children.push(spacer(first * height));
  for (let i = first; i <= last; i += 1) {
    const id = order[i];
    const entry = rows.get(id) ?? buildRow(id);
    entry.tr.setAttribute("aria-rowindex", String(i + 2));
    updateRow(entry, robots.get(id), now);
    children.push(entry.tr);
  }
  if (last < order.length - 1) children.push(spacer((order.length - 1 - last) * height));
  // Moving a row out and back in blurs it: a keyboard user must keep their place through re-sorts.
  const focused = tbody.contains(document.activeElement) ? document.activeElement : null;
  tbody.replaceChildren(...children);
  if (focused?.isConnected && document.activeElement !== focused) focused.focus({ preventScroll: true });
  rendered = { first, last };
  windowDirty = false;
  // Spacers sized with a guessed row height misplace the window: measure, and redo it once.
  if (Math.abs(measureRowHeight() - height) > 0.5) {
    windowDirty = true;
    schedule();
  }
  // Rows far off screen are rebuilt on demand: keep memory flat with thousands of robots.
  if (rows.size > 4 * (last - first + 1) + 100) {
    const keep = new Set(order.slice(first, last + 1));
    for (const id of rows.keys()) if (!keep.has(id)) rows.delete(id);
  }
}

let summaryText = "";

function updateSummary() {
  let online = 0;
  let skills = 0;
  let onRobot = 0;
  let onCloud = 0;
  for (const robot of robots.values()) {
    if (robot.connected) online += 1;
    const n = counts(robot);
    skills += n.skills;
    onRobot += n.onRobot;
    onCloud += n.onCloud;
  }
  const text = [robots.size, online, robots.size - online, skills, onRobot, onCloud].join("|");
  if (text === summaryText) return;
  summaryText = text;
  const item = (value, label, cls = "") => el("li", { class: cls }, el("strong", {}, String(value)), ` ${label}`);
  summary.replaceChildren(
    item(robots.size, robots.size === 1 ? "robot" : "robots"),
    item(online, "online", "online"),
    item(robots.size - online, "offline", "offline"),
    item(skills, skills === 1 ? "skill" : "skills"),
    item(onRobot, "components on robots", "loc-robot"),
    item(onCloud, "in the cloud", "loc-cloud"),
  );
  emptyNote.hidden = robots.size > 0;
}

function flush() {
  const now = Date.now() / 1000;
  const metricSort = sort.key in ROBOT_METRICS;
  if (metricSort && dirty.size && performance.now() - lastMetricSort > METRIC_RESORT_MS) orderDirty = true;
  if (orderDirty) recomputeOrder();
  if (windowDirty) {
    renderWindow(now);
  } else {
    for (const id of dirty) {
      const entry = rows.get(id);
      if (entry?.tr.isConnected) updateRow(entry, robots.get(id), now);
    }
  }
  dirty.clear();
  noMatch.hidden = order.length > 0 || robots.size === 0;
  updateSummary();
  if (!document.body.dataset.fleetReady) {
    document.body.dataset.fleetReady = "true";
    performance.mark("fleet-rendered");
  }
}

const schedule = frameBatcher(flush);

// --------------------------------------------------------------------------- controls

function setSort(key) {
  sort = { key, dir: sort.key === key ? -sort.dir : key === "id" || key === "offloading" ? 1 : -1 };
  for (const th of table.querySelectorAll("th[data-sort]")) {
    th.setAttribute("aria-sort", th.dataset.sort === sort.key ? (sort.dir > 0 ? "ascending" : "descending") : "none");
  }
  orderDirty = true;
  schedule();
}

function controls() {
  for (const th of table.querySelectorAll("th[data-sort]")) {
    th.querySelector("button").addEventListener("click", () => setSort(th.dataset.sort));
  }
  const refilter = () => {
    orderDirty = true;
    schedule();
  };
  const askCloud = debounce(async () => {
    const text = filterInput.value.trim();
    selectorAsked = text;
    const answer = await get(`/api/robot?fields=id&selector=${encodeURIComponent(text)}`);
    if (selectorAsked !== text) return; // typed on since
    if (answer.ok) {
      selected = new Set(answer.data.map((robot) => robot.id));
      filterResult.className = "result";
      setText(filterResult, `Label selector: ${selected.size} robot(s) match.`);
    } else {
      selected = new Set();
      filterResult.className = "result error";
      setText(filterResult, errorText(answer.data, answer.status));
    }
    refilter();
  }, 250);
  const reselect = () => {
    if (filterInput.value.includes("=")) {
      askCloud();
      return;
    }
    selected = null;
    selectorAsked = "";
    setText(filterResult, "");
    refilter();
  };
  filterInput.form.addEventListener("submit", (event) => event.preventDefault());
  filterInput.addEventListener("input", reselect);
  stateSelect.addEventListener("change", refilter);
  const rewindow = () => {
    const { first, last } = visibleRange();
    if (first !== rendered.first || last !== rendered.last) {
      windowDirty = true;
      schedule();
    }
  };
  window.addEventListener("scroll", rewindow, { passive: true });
  window.addEventListener("resize", rewindow, { passive: true });
  tbody.addEventListener("keydown", moveFocus);
  // "3 min ago" ages without any frame arriving.
  setInterval(() => {
    for (const id of order.slice(rendered.first, rendered.last + 1)) dirty.add(id);
    schedule();
  }, 15000);
}

/** Arrow keys move between robots' rows, rendering the next ones when they are off screen. */
function moveFocus(event) {
  if (event.key !== "ArrowDown" && event.key !== "ArrowUp") return;
  const row = event.target.closest("tr[data-robot]");
  if (!row) return;
  const step = event.key === "ArrowDown" ? 1 : -1;
  const next = order[order.indexOf(row.dataset.robot) + step];
  if (next === undefined) return;
  event.preventDefault();
  const focusNext = (tries) => {
    const link = tbody.querySelector(`tr[data-robot="${CSS.escape(next)}"] a.robot-link`);
    if (link) {
      link.focus({ preventScroll: true });
      link.closest("tr").scrollIntoView({ block: "nearest" });
    } else if (tries > 0) {
      window.scrollBy(0, step * measureRowHeight());
      requestAnimationFrame(() => requestAnimationFrame(() => focusNext(tries - 1)));
    }
  };
  focusNext(4);
}

// --------------------------------------------------------------------------- start

for (const raw of pageData("fleet-data") ?? []) upsert(raw);
controls();
flush();
wire(startLive());

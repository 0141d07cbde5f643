// Fleet overview: a page of robots, searched, sorted and paged by the cloud, its rows kept live.
//
// The cloud answers one page (100 robots) with the whole fleet's counts: rendered into the page
// first, then from GET /fleet/page when the search, the order or the page changes. The page asks
// for the live metrics of its own robots only (metrics_subscribe), so a 10,000-robot fleet sends
// it a hundred robots' values, not ten thousand. Frames change a plain model and mark robots dirty;
// one requestAnimationFrame pass rewrites only the cells whose text changed. An event that may
// change the counts or which robots the page holds (a robot connecting, added or deleted)
// reloads the page's data, at most once every RELOAD_MS.

import { get, seg } from "./api.js";
import { labelChips, labelText } from "./labels.js";
import { startLive } from "./live.js";
import {
  ROBOT_METRICS,
  debounce,
  el,
  fmtAgo,
  fmtMetric,
  fmtNumber,
  fmtTime,
  frameBatcher,
  isoSeconds,
  pageData,
  setClass,
  setText,
  throttle,
  toast,
} from "./util.js";

const METRIC_NAMES = Object.keys(ROBOT_METRICS);
const ACTIVE = new Set(["running", "starting", "migrating", "stopping"]);
// Reloads of the page's data, when events say the fleet changed, come at most this often.
const RELOAD_MS = 2000;
// Sorts whose first click is ascending; the others start with the largest (or newest) first.
const ASCENDING_FIRST = new Set(["id", "offloading"]);
// A deleted robot, an added one, or a renamed or relabelled one: the event log's kinds that change the table.
const ROBOT_CHANGES = new Set(["robot_created", "robot_updated", "robot_deleted"]);

const table = document.getElementById("fleet");
const tbody = document.getElementById("fleet-rows");
const summary = document.getElementById("fleet-summary");
const pager = document.getElementById("fleet-pager");
const emptyNote = document.getElementById("fleet-empty");
const noMatch = document.getElementById("fleet-no-match");
const filterInput = document.getElementById("fleet-filter");
const stateSelect = document.getElementById("fleet-state");
const filterResult = document.getElementById("fleet-filter-result");

let robots = new Map(); // id -> robot model, the robots of this page
const rows = new Map(); // id -> {tr, cells} of this page's rows
const dirty = new Set();
let order = []; // this page's ids, in the cloud's order
let orderDirty = true;
let current = null; // the page's data as the cloud last answered it (robots aside)
let query = { q: "", state: "all", sort: "id", page: 1 };

// --------------------------------------------------------------------------- the model

function normalise(raw, previous) {
  // A live value newer than the page's data is kept: the data may have been read just before it came.
  const metrics = { ...(previous?.metrics ?? {}) };
  for (const [name, point] of Object.entries(raw.metrics ?? {})) {
    if (!metrics[name] || point[1] >= metrics[name][1]) metrics[name] = point;
  }
  return {
    id: raw.id,
    name: raw.name || "",
    labels: raw.labels ?? {},
    connected: Boolean(raw.connected),
    status: raw.status,
    lastSeen: isoSeconds(raw.last_seen),
    offloading: raw.offloading ?? "",
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
    metrics,
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

/** Take a page of the fleet as the cloud answered it: its robots, counts and paging. */
function apply(data) {
  const next = new Map();
  for (const raw of data.robots) next.set(raw.id, normalise(raw, robots.get(raw.id)));
  robots = next;
  for (const id of rows.keys()) if (!robots.has(id)) rows.delete(id);
  order = data.robots.map((raw) => raw.id);
  for (const id of order) dirty.add(id);
  current = { ...data, robots: undefined };
  query = { ...data.query, page: data.page };
  orderDirty = true;
  schedule();
  live.subscribeMetrics(order, () => reload());
}

function touch(id) {
  dirty.add(id);
  schedule();
}

// --------------------------------------------------------------------------- loading pages

const params = (q) => {
  const search = new URLSearchParams();
  if (q.q) search.set("q", q.q);
  if (q.state !== "all") search.set("state", q.state);
  if (q.sort !== "id") search.set("sort", q.sort);
  if (q.page > 1) search.set("page", String(q.page));
  return search.toString();
};

const address = (q) => {
  const search = params(q);
  return search ? `?${search}` : location.pathname;
};

let asked = 0;
let wanted = null; // the page last asked for: a reload asks for it again, not for the one on screen

/** Load a page of the fleet and draw it; `history` says how the address follows ("push", "replace" or none). */
async function load(next, history = "replace") {
  const ticket = ++asked;
  wanted = next;
  // The address follows at once, so a reload that overtakes this answer keeps it.
  if (history) window.history[history === "push" ? "pushState" : "replaceState"](null, "", address(next));
  const answer = await get(`/fleet/page?${params(next)}`);
  if (ticket !== asked) return; // asked for another page meanwhile
  if (answer.status === 400 && answer.data?.q) {
    // A malformed label selector: say why beside the search box, and match nothing.
    apply({ ...current, robots: [], count: 0, page: 1, pages: 1, offset: 0, query: next, error: answer.data.q.join(" ") });
  } else if (answer.ok) {
    apply(answer.data);
    // Past the last page the cloud answers the last one: the address says which.
    if (answer.data.page !== next.page) window.history.replaceState(null, "", address(query));
  } else {
    toast(`The fleet did not load: ${answer.data?.detail ?? `HTTP ${answer.status}`}`, "error");
  }
}

/** Read the page's data again: the fleet changed (robots connected, added, deleted) or frames were missed. */
const reload = throttle(() => load(wanted ?? query, null), RELOAD_MS);

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
  // The fleet's online count changed, and a robot new to the fleet may belong on this page.
  reload();
  const robot = robots.get(frame.data.robot);
  if (!robot) return;
  robot.connected = connected;
  if (connected) robot.status = "running";
  robot.lastSeen = frame.ts || Date.now() / 1000;
  touch(robot.id);
}

/** Return this page's component a frame is about; reload when it is one the page does not know yet. */
function component(frame) {
  // The fleet's counts of components on robots and in the cloud may have changed.
  reload();
  return robots.get(frame.data.robot)?.skills.get(frame.data.skill)?.components.get(frame.data.component);
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
    const robot = robots.get(frame.data.robot);
    const skill = robot?.skills.get(frame.data.skill);
    if (skill) skill.status = frame.data.status;
    else if (robot) reload();
  });
  // A Skill added or changed: the fleet's count of Skills, and the robot's row if it is here.
  live.on("skill_config", reload);
  live.on("offloading", (frame) => {
    const robot = robots.get(frame.data.robot);
    if (!robot) return;
    robot.offloading = frame.data.mode;
    touch(robot.id);
  });
  live.on("log_event", (frame) => {
    if (!ROBOT_CHANGES.has(frame.data.kind)) return;
    // A deleted robot leaves the table at once; the reload then brings the next one up.
    if (frame.data.kind === "robot_deleted") forget(frame.data.robot);
    reload();
  });
  // Frames may have been missed while reconnecting.
  live.onResync(reload);
}

/** Drop a robot that no longer exists from the table. */
function forget(id) {
  if (!robots.delete(id)) return;
  rows.delete(id);
  dirty.delete(id);
  order = order.filter((other) => other !== id);
  orderDirty = true;
  schedule();
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

function renderRows(now) {
  const children = order.map((id, i) => {
    const entry = rows.get(id) ?? buildRow(id);
    entry.tr.setAttribute("aria-rowindex", String(current.offset + i + 2));
    updateRow(entry, robots.get(id), now);
    return entry.tr;
  });
  // Moving a row out and back in blurs it: a keyboard user must keep their place through a reload.
  const focused = tbody.contains(document.activeElement) ? document.activeElement : null;
  tbody.replaceChildren(...children);
  if (focused?.isConnected && document.activeElement !== focused) focused.focus({ preventScroll: true });
  table.setAttribute("aria-rowcount", String(current.count + 1));
  orderDirty = false;
}

// --------------------------------------------------------------------------- around the table

let summaryText = "";

function updateSummary() {
  const s = current.summary;
  const text = [s.robots, s.online, s.skills, s.on_robot, s.on_cloud].join("|");
  if (text === summaryText) return;
  summaryText = text;
  const item = (value, label, cls = "") => el("li", { class: cls }, el("strong", {}, fmtNumber(value)), ` ${label}`);
  summary.replaceChildren(
    item(s.robots, s.robots === 1 ? "robot" : "robots"),
    item(s.online, "online", "online"),
    item(s.robots - s.online, "offline", "offline"),
    item(s.skills, s.skills === 1 ? "skill" : "skills"),
    item(s.on_robot, "components on robots", "loc-robot"),
    item(s.on_cloud, "in the cloud", "loc-cloud"),
  );
  emptyNote.hidden = s.robots > 0;
}

function pageLink(label, page, rel) {
  if (page === null) return el("span", { class: "muted", "aria-disabled": "true" }, label);
  return el("a", { href: address({ ...query, page }), rel, dataset: { page: String(page) } }, label);
}

function updatePager() {
  const { offset, count, page, pages } = current;
  const shown = order.length;
  pager.hidden = count === 0;
  const range =
    pages > 1
      ? `Robots ${fmtNumber(offset + 1)}–${fmtNumber(offset + shown)} of ${fmtNumber(count)} · page ${page} of ${fmtNumber(pages)}`
      : `${fmtNumber(count)} ${count === 1 ? "robot" : "robots"}`;
  pager.replaceChildren(
    pageLink("Previous", page > 1 ? page - 1 : null, "prev"),
    el("span", { id: "fleet-range", role: "status" }, range),
    pageLink("Next", page < pages ? page + 1 : null, "next"),
  );
}

function updateControls() {
  if (document.activeElement !== filterInput && filterInput.value !== query.q) filterInput.value = query.q;
  stateSelect.value = query.state;
  const key = query.sort.replace(/^-/, "");
  const dir = query.sort.startsWith("-") ? "descending" : "ascending";
  for (const th of table.querySelectorAll("th[data-sort]")) {
    th.setAttribute("aria-sort", th.dataset.sort === key ? dir : "none");
  }
  if (current.error) {
    filterResult.className = "result error";
    setText(filterResult, current.error);
  } else {
    filterResult.className = "result";
    setText(filterResult, query.q.includes("=") ? `Label selector: ${current.count} robot(s) match.` : "");
  }
}

function flush() {
  const now = Date.now() / 1000;
  if (orderDirty) {
    renderRows(now);
    updatePager();
    updateControls();
  } else {
    for (const id of dirty) {
      const entry = rows.get(id);
      if (entry?.tr.isConnected) updateRow(entry, robots.get(id), now);
    }
  }
  dirty.clear();
  noMatch.hidden = current.count > 0 || current.summary.robots === 0;
  updateSummary();
  if (!document.body.dataset.fleetReady) {
    document.body.dataset.fleetReady = "true";
    performance.mark("fleet-rendered");
  }
}

const schedule = frameBatcher(flush);

// --------------------------------------------------------------------------- controls

function setSort(key) {
  const [currentKey, descending] = [query.sort.replace(/^-/, ""), query.sort.startsWith("-")];
  const ascending = currentKey === key ? descending : ASCENDING_FIRST.has(key);
  load({ ...query, sort: ascending ? key : `-${key}`, page: 1 });
}

function controls() {
  for (const th of table.querySelectorAll("th[data-sort]")) {
    th.querySelector("button").addEventListener("click", () => setSort(th.dataset.sort));
  }
  const search = debounce(() => load({ ...query, q: filterInput.value.trim(), page: 1 }), 250);
  filterInput.form.addEventListener("submit", (event) => {
    event.preventDefault();
    load({ ...query, q: filterInput.value.trim(), page: 1 });
  });
  filterInput.addEventListener("input", search);
  stateSelect.addEventListener("change", () => load({ ...query, state: stateSelect.value, page: 1 }));
  pager.addEventListener("click", (event) => {
    const link = event.target.closest("a[data-page]");
    if (!link || event.metaKey || event.ctrlKey || event.shiftKey) return;
    event.preventDefault();
    load({ ...query, page: Number(link.dataset.page) }, "push").then(() => window.scrollTo(0, 0));
  });
  window.addEventListener("popstate", () => load(fromAddress(), null));
  tbody.addEventListener("keydown", moveFocus);
  // "3 min ago" ages without any frame arriving.
  setInterval(() => {
    for (const id of order) dirty.add(id);
    schedule();
  }, 15000);
}

function fromAddress() {
  const search = new URLSearchParams(location.search);
  return {
    q: search.get("q") ?? "",
    state: search.get("state") ?? "all",
    sort: search.get("sort") ?? "id",
    page: Number(search.get("page")) || 1,
  };
}

/** Arrow keys move between the robots' rows. */
function moveFocus(event) {
  if (event.key !== "ArrowDown" && event.key !== "ArrowUp") return;
  const row = event.target.closest("tr[data-robot]");
  const next = event.key === "ArrowDown" ? row?.nextElementSibling : row?.previousElementSibling;
  const link = next?.querySelector("a.robot-link");
  if (!link) return;
  event.preventDefault();
  link.focus({ preventScroll: true });
  next.scrollIntoView({ block: "nearest" });
}

// --------------------------------------------------------------------------- start

const live = startLive();
wire(live);
controls();
apply(pageData("fleet-data"));
flush();

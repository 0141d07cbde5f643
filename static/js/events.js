// Events and logs: the filtered event log, older pages on demand, and new events pushed live over /ws/client/.

import { get, seg } from "./api.js";
import { startLive } from "./live.js";
import { crashDetails } from "./loglines.js";
import { coalesce, el, errorText, fmtDateTime, fmtTime, isoSeconds } from "./util.js";

const PAGE = 100;
const MAX_ROWS = 1000;
const LEVELS = ["debug", "info", "warning", "error"];

const form = document.getElementById("event-filters");
const tbody = document.getElementById("event-rows");
const countNode = document.getElementById("event-count");
const olderButton = document.getElementById("event-older");
const errorNode = document.getElementById("event-error");
const tailBox = document.getElementById("event-tail");

const seen = new Set();
let newest = null; // raw ISO time of the newest event shown
let oldest = null;
let total = 0;
let generation = 0; // a filter change makes answers to earlier requests stale

/** Turn a datetime-local value (the operator's local time) into ISO, and back. */
const toIso = (local) => (local ? new Date(local).toISOString() : "");
function toLocal(iso) {
  const date = new Date(iso);
  if (Number.isNaN(date.getTime())) return "";
  const pad = (n) => String(n).padStart(2, "0");
  return `${date.getFullYear()}-${pad(date.getMonth() + 1)}-${pad(date.getDate())}T${pad(date.getHours())}:${pad(date.getMinutes())}:${pad(date.getSeconds())}`;
}

function filters() {
  const values = {};
  for (const name of ["robot", "skill", "component", "level"]) {
    const value = form.elements[name].value.trim();
    if (value) values[name] = value;
  }
  for (const name of ["since", "until"]) {
    const value = toIso(form.elements[name].value);
    if (value) values[name] = value;
  }
  return values;
}

function query(extra = {}) {
  const params = new URLSearchParams({ ...filters(), ...extra });
  return `/api/events?${params}`;
}

function row(event, fresh) {
  const ts = isoSeconds(event.ts);
  const robotCell = event.robot ? el("a", { href: `/robots/${seg(event.robot)}/` }, event.robot) : el("span", { class: "muted" }, "—");
  const data = event.data && Object.keys(event.data).length ? JSON.stringify(event.data) : "";
  // The data in a disclosure rather than a hover title, so a keyboard reaches it too.
  const details = data ? el("details", { class: "event-data" }, el("summary", {}, "data"), el("code", {}, data)) : null;
  return el(
    "tr",
    { class: fresh ? "new" : "", tabindex: "0", dataset: { event: String(event.id) } },
    el("td", { class: "c-time", title: fmtDateTime(ts) }, el("time", { datetime: event.ts }, fmtTime(ts))),
    el("td", { class: "c-level" }, el("span", { class: `badge level-${event.level}` }, event.level)),
    el("td", {}, robotCell),
    el("td", {}, event.skill || ""),
    el("td", {}, event.component || ""),
    el("td", {}, el("code", {}, event.kind || "—")),
    // A crash's last lines one click away (data.lines), with the log viewer at that time.
    el("td", { class: "c-message" }, event.message, details, crashDetails(event)),
  );
}

function fail(answer) {
  errorNode.hidden = false;
  errorNode.textContent = `The event log did not load: ${errorText(answer.data, answer.status)}`;
  countNode.textContent = "";
  olderButton.hidden = true;
}

function updateFoot(hasOlder) {
  countNode.textContent = total === 0 ? "No event matches the filters." : `${tbody.rows.length} of ${total} shown`;
  if (hasOlder !== undefined) olderButton.hidden = !hasOlder;
}

async function load() {
  const mine = ++generation;
  seen.clear();
  newest = oldest = null;
  countNode.textContent = "Loading…";
  const answer = await get(query({ limit: PAGE }));
  if (mine !== generation) return;
  if (!answer.ok) {
    tbody.replaceChildren();
    return fail(answer);
  }
  errorNode.hidden = true;
  const events = answer.data.results;
  total = answer.data.count;
  for (const event of events) seen.add(event.id);
  newest = events[0]?.ts ?? null;
  oldest = events.at(-1)?.ts ?? null;
  tbody.replaceChildren(...events.map((event) => row(event, false)));
  updateFoot(Boolean(answer.data.next));
}

async function older() {
  if (!oldest) return;
  const mine = generation;
  olderButton.disabled = true;
  const until = filters().until;
  const bound = until && until < oldest ? until : oldest;
  const answer = await get(query({ until: bound, limit: PAGE }));
  olderButton.disabled = false;
  if (mine !== generation) return;
  if (!answer.ok) return fail(answer);
  const events = answer.data.results.filter((event) => !seen.has(event.id));
  for (const event of events) seen.add(event.id);
  oldest = answer.data.results.at(-1)?.ts ?? oldest;
  tbody.append(...events.map((event) => row(event, false)));
  updateFoot(Boolean(answer.data.next));
}

/** Put fresh events on top, dropping the oldest rows past MAX_ROWS. */
function prepend(events) {
  for (const event of events) seen.add(event.id);
  total += events.length;
  tbody.prepend(...events.map((event) => row(event, true)));
  while (tbody.rows.length > MAX_ROWS) {
    const last = tbody.rows[tbody.rows.length - 1];
    seen.delete(Number(last.dataset.event));
    last.remove();
    olderButton.hidden = false;
  }
  oldest = tbody.rows[tbody.rows.length - 1]?.querySelector("time")?.getAttribute("datetime") ?? oldest;
  updateFoot();
}

/** Tell whether a pushed event passes the filters, as the API would filter it. */
function matches(event) {
  const wanted = filters();
  for (const name of ["robot", "skill", "component"]) {
    if (wanted[name] && event[name] !== wanted[name]) return false;
  }
  if (wanted.level && LEVELS.indexOf(event.level) < LEVELS.indexOf(wanted.level)) return false;
  if (wanted.since && new Date(event.ts) < new Date(wanted.since)) return false;
  return true;
}

/** Show an event the cloud pushed as it was written (log_event frame). */
function onLogEvent(frame) {
  const event = frame.data;
  if (!tailBox.checked || filters().until || seen.has(event.id) || !matches(event)) return;
  if (!newest || event.ts > newest) newest = event.ts;
  prepend([event]);
}

let tailing = false;

/** Fetch events newer than the newest shown and put them on top (after a reconnect: frames may be lost). */
async function tail() {
  if (!tailBox.checked || tailing || filters().until || document.hidden) return;
  tailing = true;
  const mine = generation;
  const answer = await get(query(newest ? { since: newest, limit: PAGE } : { limit: PAGE }));
  tailing = false;
  if (mine !== generation || !answer.ok) return;
  const events = answer.data.results.filter((event) => !seen.has(event.id));
  if (!events.length) return;
  newest = answer.data.results[0].ts;
  oldest ??= answer.data.results.at(-1).ts;
  prepend(events);
}

/** Keep the filters in the address, so a filtered view can be bookmarked or shared. */
function remember() {
  const params = new URLSearchParams(filters());
  if (!tailBox.checked) params.set("tail", "off");
  history.replaceState(null, "", `${location.pathname}${params.size ? `?${params}` : ""}`);
}

function restore() {
  const params = new URLSearchParams(location.search);
  for (const name of ["since", "until"]) {
    if (params.get(name)) form.elements[name].value = toLocal(params.get(name));
  }
  tailBox.checked = params.get("tail") !== "off";
}

form.addEventListener("submit", (event) => {
  event.preventDefault();
  remember();
  load();
});
form.addEventListener("reset", () => {
  setTimeout(() => {
    remember();
    load();
  });
});
tailBox.addEventListener("change", () => {
  remember();
  tail();
});
olderButton.addEventListener("click", older);

// Every new entry of the event log arrives as a log_event frame; nothing is polled. After a
// reconnect the page asks the API once for what it may have missed.
const tailSoon = coalesce(tail, 400);
const live = startLive();
live.on("log_event", onLogEvent);
live.onResync(tailSoon);

restore();
load();

// How a log line looks, in the viewer and in a crash event's disclosure (the events page and the robot page).

import { seg } from "./api.js";
import { filterQuery } from "./logcore.js";
import { el, isoSeconds } from "./util.js";

const clock = new Intl.DateTimeFormat(undefined, {
  hour: "2-digit",
  minute: "2-digit",
  second: "2-digit",
  fractionalSecondDigits: 3,
  hourCycle: "h23",
});
const day = new Intl.DateTimeFormat(undefined, { month: "short", day: "numeric" });
// Five characters at most, so the text column starts at one place on every line.
const SHORT_LEVEL = { debug: "DEBUG", info: "INFO", warning: "WARN", error: "ERROR", critical: "CRIT" };

/** Render one line: time, level, where it came from (unless the view is one component's), text. */
export function lineNode(line, { source = true } = {}) {
  const date = new Date(line.ts * 1000);
  const level = line.level || "";
  return el(
    "div",
    { class: `log-line${level ? ` lv-${level}` : ""}${line.stream === "stderr" ? " stderr" : ""}` },
    el("time", { datetime: date.toISOString(), title: `${day.format(date)} ${clock.format(date)}` }, clock.format(date)),
    el("span", { class: "lv", title: level }, SHORT_LEVEL[level] ?? ""),
    source ? el("span", { class: `src loc-${line.location}` }, `${line.skill}/${line.component}`) : null,
    el("span", { class: "txt" }, line.text),
  );
}

/** Read a crash event's lines: the robot's LogLines (data.lines), or a cloud copy's plain output (data.logs). */
export function crashLines(event) {
  const data = event.data || {};
  const where = data.location || (event.kind?.startsWith("cloud_component_") ? "cloud" : "robot");
  const base = { skill: event.skill, component: event.component, location: where, stream: "stdout", level: null };
  if (Array.isArray(data.lines)) {
    return data.lines.map((line, i) => ({
      ...base,
      ...line,
      seq: line.seq ?? i + 1,
      ts: typeof line.ts === "number" ? line.ts : (isoSeconds(line.ts) ?? isoSeconds(event.ts)),
    }));
  }
  if (Array.isArray(data.logs)) {
    const ts = isoSeconds(event.ts);
    return data.logs.map((text, i) => ({ ...base, seq: i + 1, ts, text: String(text) }));
  }
  return null;
}

/** Link to the viewer at the time of a crash: the component, from a minute before its last lines to just after. */
export function crashViewerUrl(event, lines) {
  const at = isoSeconds(event.ts);
  const first = lines?.length ? Math.min(...lines.map((line) => line.ts)) : at;
  const filters = {
    skill: event.skill,
    component: event.component,
    since: new Date((Math.min(first, at) - 60) * 1000).toISOString(),
    until: new Date((at + 5) * 1000).toISOString(),
  };
  return `/robots/${seg(event.robot)}/logs/?${filterQuery(filters)}`;
}

/** A crash event's last lines, one click away, and a link to the viewer at that time; null for other events. */
export function crashDetails(event) {
  const lines = crashLines(event);
  if (!lines) return null;
  const link = event.robot ? el("a", { class: "crash-open", href: crashViewerUrl(event, lines) }, "Open in the log viewer") : null;
  return el(
    "details",
    { class: "crash-lines", dataset: { crash: String(event.id ?? "") } },
    el("summary", {}, lines.length ? `Last ${lines.length} lines` : "No lines printed"),
    el("div", { class: "log-lines short" }, lines.map((line) => lineNode(line, { source: false }))),
    link,
  );
}

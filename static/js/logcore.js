// The log viewer's rules over plain data (no DOM, no socket): levels, filters, the ordered and bounded buffer.

export const LEVELS = ["debug", "info", "warning", "error", "critical"];
// Filters the Robot API's /logs and /logs/download take, in the order they show in an address.
export const FILTERS = ["skill", "component", "location", "level", "q", "regex", "since", "until"];

/** Rank a line's level; a line without one counts as info, as the API counts it. */
export function levelRank(level) {
  const rank = LEVELS.indexOf(level || "info");
  return rank < 0 ? 1 : rank;
}

/** Name one line of one component once: a line sent twice (a resend, the ring and the store) shows once. */
export function lineKey(line) {
  return `${line.skill}/${line.component}/${line.location}/${line.seq}`;
}

/**
 * Build the test a line must pass to show, as the API filters: scope, minimum level, text.
 *
 * Throws a SyntaxError (with `field: "q"`) when the text is asked as a regular expression and is not one.
 */
export function matcher(filters) {
  const minimum = filters.level ? levelRank(filters.level) : 0;
  let text = null;
  if (filters.q) {
    if (filters.regex) {
      let pattern;
      try {
        pattern = new RegExp(filters.q, "i");
      } catch (error) {
        throw Object.assign(new SyntaxError(`not a regular expression: ${error.message}`), { field: "q" });
      }
      text = (value) => pattern.test(value);
    } else {
      const needle = filters.q.toLowerCase();
      text = (value) => value.toLowerCase().includes(needle);
    }
  }
  const since = filters.since ? Date.parse(filters.since) / 1000 : null;
  const until = filters.until ? Date.parse(filters.until) / 1000 : null;
  return (line) =>
    (!filters.skill || line.skill === filters.skill) &&
    (!filters.component || line.component === filters.component) &&
    (!filters.location || line.location === filters.location) &&
    levelRank(line.level) >= minimum &&
    (since === null || line.ts >= since) &&
    (until === null || line.ts <= until) &&
    (text === null || text(line.text));
}

/** Turn a pushed component_logs frame into lines of the viewer's shape (ts in seconds). */
export function framesLines(data) {
  const { skill, component } = data;
  const location = data.location || "robot";
  return (data.lines || []).map((line) => ({ ...line, skill, component, location, level: line.level ?? null }));
}

/** Turn one row of GET /api/robot/<id>/logs into a line of the viewer's shape. */
export function apiLine(row) {
  return { ...row, ts: Date.parse(row.ts) / 1000, level: row.level ?? null };
}

/** Order lines by time, then by their component's count (lines of one instant keep their order). */
export function before(a, b) {
  return a.ts < b.ts || (a.ts === b.ts && a.seq < b.seq);
}

/**
 * The lines shown, oldest first, at most `max`, each once.
 *
 * `add` answers where each new line went so the page mirrors it in the DOM without redrawing:
 * {appended: [...], inserted: [[line, beforeLine], ...], evicted: [...]}.
 */
export class LineBuffer {
  constructor(max = 5000) {
    this.max = max;
    this.lines = [];
    this.keys = new Set();
  }

  get size() {
    return this.lines.length;
  }

  get oldest() {
    return this.lines[0] ?? null;
  }

  get newest() {
    return this.lines.at(-1) ?? null;
  }

  has(line) {
    return this.keys.has(lineKey(line));
  }

  clear() {
    this.lines = [];
    this.keys.clear();
  }

  /** Add lines (any order); evict from the `evict` end ("oldest" or "newest") past the cap. */
  add(lines, { evict = "oldest" } = {}) {
    const fresh = [];
    for (const line of lines) {
      const key = lineKey(line);
      if (this.keys.has(key)) continue;
      this.keys.add(key);
      fresh.push(line);
    }
    fresh.sort((a, b) => (before(a, b) ? -1 : before(b, a) ? 1 : 0));
    const appended = [];
    const inserted = [];
    for (const line of fresh) {
      const last = this.lines.at(-1);
      if (!last || !before(line, last)) {
        this.lines.push(line);
        appended.push(line);
        continue;
      }
      // Late lines (the robot's ring, an older page) go to their place by binary search.
      let low = 0;
      let high = this.lines.length;
      while (low < high) {
        const mid = (low + high) >> 1;
        if (before(line, this.lines[mid])) high = mid;
        else low = mid + 1;
      }
      inserted.push([line, this.lines[low]]);
      this.lines.splice(low, 0, line);
    }
    const over = this.lines.length - this.max;
    let evicted = [];
    if (over > 0) {
      evicted = evict === "newest" ? this.lines.splice(this.lines.length - over, over) : this.lines.splice(0, over);
      for (const line of evicted) this.keys.delete(lineKey(line));
    }
    return { appended, inserted, evicted };
  }
}

/** Format a line as the download does: `2026-12-04T19:00:00.123Z robot stdout INFO skill/component: text`. */
export function formatLine(line) {
  const level = (line.level || "-").toUpperCase();
  return `${new Date(line.ts * 1000).toISOString()} ${line.location} ${line.stream} ${level} ${line.skill}/${line.component}: ${line.text}`;
}

/** Build the query string of the API for a set of filters (empty ones left out; regex only with a text). */
export function filterQuery(filters, extra = {}) {
  const params = new URLSearchParams();
  for (const name of FILTERS) {
    const value = filters[name];
    if (name === "regex") {
      if (value && filters.q) params.set("regex", "true");
    } else if (value) {
      params.set(name, value);
    }
  }
  for (const [name, value] of Object.entries(extra)) params.set(name, String(value));
  return params;
}

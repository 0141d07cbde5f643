// Small helpers every page shares: DOM building, formatting, frame batching, toasts.

/** Build an element: el("a", {href: "/", class: "x", text: "hi"}, child, ...). Text is never parsed as HTML. */
export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (value === undefined || value === null || value === false) continue;
    if (key === "class") node.className = value;
    else if (key === "text") node.textContent = value;
    else if (key === "dataset") Object.assign(node.dataset, value);
    // Through the CSSOM: the content security policy refuses style attributes.
    else if (key === "style") node.style.cssText = value;
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else node.setAttribute(key, value === true ? "" : String(value));
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined || child === false) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

/** Set a node's text only when it changed: writes are what make the browser re-lay out. */
export function setText(node, text) {
  if (node.textContent !== text) node.textContent = text;
}

/** Set one class on or off only when it changed. */
export function setClass(node, name, on) {
  if (node.classList.contains(name) !== on) node.classList.toggle(name, on);
}

/** Read a json_script block rendered by the page's template. */
export function pageData(id) {
  const node = document.getElementById(id);
  return node ? JSON.parse(node.textContent) : null;
}

/** Return the CSRF token Django rendered into the page, for POSTs to the API. */
export function csrfToken() {
  return document.querySelector('meta[name="csrf-token"]')?.content ?? "";
}

/** Run fn at most once per animation frame, however often it is scheduled. */
export function frameBatcher(fn) {
  let pending = false;
  return () => {
    if (pending) return;
    pending = true;
    requestAnimationFrame(() => {
      pending = false;
      fn();
    });
  };
}

/** Call fn once, ms after the first of a burst of calls: a steady stream of calls cannot starve it. */
export function coalesce(fn, ms) {
  let timer = null;
  return () => {
    if (timer !== null) return;
    timer = setTimeout(() => {
      timer = null;
      fn();
    }, ms);
  };
}

/** Call fn at once, then at most once every ms while calls keep coming; a call meanwhile is made at the end. */
export function throttle(fn, ms) {
  let timer = null;
  let last = Number.NEGATIVE_INFINITY;
  const run = () => {
    timer = null;
    last = performance.now();
    fn();
  };
  return () => {
    if (timer !== null) return;
    timer = setTimeout(run, Math.max(0, last + ms - performance.now()));
  };
}

/** Call fn once, wait ms after the last of a burst of calls. */
export function debounce(fn, ms) {
  let timer = null;
  return (...args) => {
    clearTimeout(timer);
    timer = setTimeout(() => fn(...args), ms);
  };
}

const number = new Intl.NumberFormat(undefined, { maximumFractionDigits: 1 });
const precise = new Intl.NumberFormat(undefined, { maximumFractionDigits: 3 });

export function fmtNumber(value, { digits = 1 } = {}) {
  if (value === null || value === undefined || Number.isNaN(value)) return "—";
  return (digits > 1 ? precise : number).format(value);
}

// The robot-wide metrics the dashboard knows how to show, and their units (see the README).
export const ROBOT_METRICS = {
  cpu: { label: "CPU", unit: "%", max: 100 },
  ram: { label: "RAM", unit: "%", max: 100 },
  bandwidth: { label: "Bandwidth", unit: "Mbit/s", max: null },
  battery: { label: "Battery", unit: "%", max: 100 },
};

// Units of the other series robots report (bridgeos_agent.monitor); per interface as "net_rx:eth0".
const OTHER_UNITS = {
  ram_used: "MiB",
  bandwidth_available: "Mbit/s",
  net_rx: "B/s",
  net_tx: "B/s",
  net_cloud_rx: "B/s",
  net_cloud_tx: "B/s",
  io_read: "B/s",
  io_write: "B/s",
};
const COMPONENT_UNITS = { cpu: "% of a core", ram: "MiB" };

/** Return the unit of a metric, robot-wide or of a component ("" when unknown). */
export function unitOf(name, { component = false } = {}) {
  const base = name.split(":")[0];
  if (component) return COMPONENT_UNITS[base] ?? OTHER_UNITS[base] ?? "";
  return ROBOT_METRICS[base]?.unit ?? OTHER_UNITS[base] ?? "";
}

export function fmtMetric(name, value) {
  if (value === null || value === undefined) return "—";
  const unit = ROBOT_METRICS[name]?.unit ?? "";
  return unit === "%" ? `${number.format(value)}%` : `${number.format(value)}${unit ? ` ${unit}` : ""}`;
}

const timeFormat = new Intl.DateTimeFormat(undefined, { hour: "2-digit", minute: "2-digit", second: "2-digit" });
const dateTimeFormat = new Intl.DateTimeFormat(undefined, { dateStyle: "medium", timeStyle: "medium" });

/** Format seconds since the epoch as a clock time today, or a date and time otherwise. */
export function fmtTime(seconds) {
  if (!seconds) return "—";
  const date = new Date(seconds * 1000);
  const sameDay = new Date().toDateString() === date.toDateString();
  return sameDay ? timeFormat.format(date) : dateTimeFormat.format(date);
}

export function fmtDateTime(seconds) {
  return seconds ? dateTimeFormat.format(new Date(seconds * 1000)) : "—";
}

/** Say how long ago a time (seconds since the epoch) was, coarsely. */
export function fmtAgo(seconds, now = Date.now() / 1000) {
  if (!seconds) return "never";
  const delta = Math.max(0, now - seconds);
  if (delta < 10) return "just now";
  if (delta < 60) return `${Math.floor(delta)} s ago`;
  if (delta < 3600) return `${Math.floor(delta / 60)} min ago`;
  if (delta < 86400) return `${Math.floor(delta / 3600)} h ago`;
  return `${Math.floor(delta / 86400)} d ago`;
}

/** Parse an ISO time from the API into seconds since the epoch (null when absent). */
export function isoSeconds(text) {
  if (!text) return null;
  const ms = Date.parse(text);
  return Number.isNaN(ms) ? null : ms / 1000;
}

/** Show a short message in the corner; screen readers hear it through the live region. */
export function toast(message, kind = "info", ms = 5000) {
  const box = document.getElementById("toasts");
  if (!box) return;
  const item = el("div", { class: `toast ${kind}`, role: kind === "error" ? "alert" : "status" }, message);
  box.append(item);
  setTimeout(() => item.remove(), ms);
}

/** Flatten DRF's error body ({field: [messages]} or {detail}) into one readable line. */
export function errorText(data, status) {
  if (!data) return `HTTP ${status}`;
  if (typeof data === "string") return data;
  if (data.detail) return data.detail;
  const parts = [];
  for (const [field, messages] of Object.entries(data)) {
    const list = Array.isArray(messages) ? messages : [messages];
    parts.push(field === "non_field_errors" ? list.join(" ") : `${field}: ${list.join(" ")}`);
  }
  return parts.join(" · ") || `HTTP ${status}`;
}

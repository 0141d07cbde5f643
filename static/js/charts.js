// Live time-series charts on the vendored uPlot (window.uPlot, see static/vendor/README.md).
//
// Points land in fixed time buckets (the last value of a bucket wins) inside a bounded window,
// so however fast metrics arrive a chart holds at most window/bucket points per series. A chart
// redraws at most once per REDRAW_MS, and only while it is on screen.

import { el, fmtNumber } from "./util.js";

const REDRAW_MS = 1000;
const clock = new Intl.DateTimeFormat(undefined, { hour: "2-digit", minute: "2-digit" });
const clockSeconds = new Intl.DateTimeFormat(undefined, { hour: "2-digit", minute: "2-digit", second: "2-digit" });
const compact = new Intl.NumberFormat(undefined, { notation: "compact", maximumFractionDigits: 1 });
// Large rates (bytes per second) read better as 1.2K, 3.4M.
const axisNumber = (v) => (Math.abs(v) >= 10000 ? compact.format(v) : fmtNumber(v));
const PALETTE = ["#2563eb", "#db2777", "#059669", "#d97706", "#7c3aed", "#0891b2", "#dc2626", "#4d7c0f"];

const AXIS_FONT = "11px system-ui, -apple-system, 'Segoe UI', Roboto, sans-serif";
let measurer = null;

/** Width in CSS pixels of a text in the axis font. */
function textWidth(text) {
  measurer ??= document.createElement("canvas").getContext("2d");
  measurer.font = AXIS_FONT;
  return measurer.measureText(text).width;
}

// The widest time label (with seconds, in this locale) plus a gap: ticks never come closer, so
// labels cannot run into each other at any card width (uPlot's default spacing is 50 px).
let timeLabelSpace = null;
export function timeAxisSpace() {
  timeLabelSpace ??= Math.ceil(textWidth(clockSeconds.format(new Date(2000, 11, 31, 22, 58, 58)))) + 18;
  return timeLabelSpace;
}

// uPlot's time increments up to an hour, in seconds (the charts' windows are minutes long).
const TIME_INCRS = [1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600];
const LABEL_GAP = 8;

/** Ticks every incr seconds on the local clock within [min, max]. */
function localTicks(min, max, incr) {
  const offset = -new Date(min * 1000).getTimezoneOffset() * 60;
  const ticks = [];
  for (let t = Math.ceil((min + offset) / incr) * incr - offset; t <= max; t += incr) ticks.push(t);
  return ticks;
}

/** The label a time tick gets: with its seconds when ticks are under a minute apart or off the minute. */
function timeLabel(t, step) {
  return (step < 60 || t % 60 ? clockSeconds : clock).format(new Date(t * 1000));
}

/**
 * The time axis' ticks: uPlot's increment, or the coarsest finer one whose labels still fit when
 * that leaves fewer than two (a 10-minute window at 5-minute ticks holds one when it starts just
 * after a multiple of five, and one label does not say what the axis spans).
 */
export function timeSplits(u, axisIdx, min, max, incr) {
  let ticks = localTicks(min, max, incr);
  const pxPerS = u.bbox.width / window.uPlot.pxRatio / Math.max(max - min, 1e-9);
  for (const finer of TIME_INCRS.filter((i) => i < incr).reverse()) {
    if (ticks.length >= 2) break;
    const candidate = localTicks(min, max, finer);
    const widest = Math.max(...candidate.map((t) => textWidth(timeLabel(t, finer))));
    if (finer * pxPerS < widest + LABEL_GAP) break;
    ticks = candidate;
  }
  return ticks;
}

function cssVar(name, fallback) {
  return getComputedStyle(document.documentElement).getPropertyValue(name).trim() || fallback;
}

const onScreen = new WeakMap(); // chart element -> bool
const observer =
  "IntersectionObserver" in window
    ? new IntersectionObserver((entries) => {
        for (const entry of entries) {
          onScreen.set(entry.target, entry.isIntersecting);
          if (entry.isIntersecting) entry.target.chart?.redrawSoon();
        }
      })
    : null;

export class TimeChart {
  /**
   * @param {HTMLElement} parent where the chart goes
   * @param {{title: string, unit?: string, windowS?: number, bucketS?: number, min?: number, max?: number}} options
   */
  constructor(parent, { title, unit = "", windowS = 600, bucketS = 1, min = null, max = null }) {
    this.title = title;
    this.unit = unit;
    this.windowS = windowS;
    this.bucketS = bucketS;
    this.min = min;
    this.max = max;
    this.series = new Map(); // label -> Map(bucket seconds -> value)
    this.plot = null;
    this.plotLabels = [];
    this.lastDraw = 0;
    this.timer = null;
    this.plotNode = el("div", { class: "plot" });
    this.emptyNode = el("p", { class: "empty" }, "Waiting for values…");
    this.node = el(
      "figure",
      { class: "chart", role: "group", "aria-label": `${title}${unit ? ` (${unit})` : ""}, last ${windowS / 60} minutes` },
      el("h3", {}, title, unit ? el("span", { class: "muted" }, ` · ${unit}`) : null),
      this.emptyNode,
      this.plotNode,
    );
    this.node.chart = this;
    parent.append(this.node);
    observer?.observe(this.node);
    if ("ResizeObserver" in window) {
      new ResizeObserver(() => this.resize()).observe(this.plotNode);
    }
  }

  /** Add one point (seconds since the epoch) to a series; the chart redraws soon. */
  add(label, ts, value, { bucketS = this.bucketS } = {}) {
    let points = this.series.get(label);
    if (!points) {
      points = new Map();
      this.series.set(label, points);
    }
    points.set(Math.floor(ts / bucketS) * bucketS, value);
    this.redrawSoon();
  }

  redrawSoon() {
    if (this.timer) return;
    const wait = Math.max(0, REDRAW_MS - (performance.now() - this.lastDraw));
    this.timer = setTimeout(() => {
      this.timer = null;
      if (observer && onScreen.get(this.node) === false) return;
      requestAnimationFrame(() => this.draw());
    }, wait);
  }

  /** Align every series on the union of their buckets within the window, dropping older points. */
  data() {
    const oldest = Date.now() / 1000 - this.windowS;
    const xs = new Set();
    for (const points of this.series.values()) {
      for (const x of points.keys()) {
        if (x < oldest) points.delete(x);
        else xs.add(x);
      }
    }
    const sorted = Float64Array.from(xs).sort();
    const labels = [...this.series.keys()].sort();
    const columns = labels.map((label) => {
      const points = this.series.get(label);
      return Array.from(sorted, (x) => (points.has(x) ? points.get(x) : null));
    });
    return { labels, data: [Array.from(sorted), ...columns] };
  }

  draw() {
    this.lastDraw = performance.now();
    const { labels, data } = this.data();
    this.emptyNode.hidden = data[0].length > 0;
    if (!data[0].length) {
      this.emptyNode.textContent = `No values in the last ${this.windowS / 60} minutes.`;
      return;
    }
    if (!this.plot || labels.join("\u0000") !== this.plotLabels.join("\u0000")) {
      this.plot?.destroy();
      this.plotLabels = labels;
      this.plot = new window.uPlot(this.options(labels), data, this.plotNode);
    } else {
      this.plot.setData(data);
    }
  }

  options(labels) {
    const axis = {
      stroke: cssVar("--muted", "#667"),
      font: AXIS_FONT,
      grid: { stroke: cssVar("--line", "#ddd"), width: 1 },
      ticks: { show: false },
    };
    const unit = this.unit;
    return {
      width: Math.max(200, this.plotNode.clientWidth),
      height: 150,
      cursor: { drag: { x: false, y: false } },
      legend: { show: true },
      scales: {
        x: { time: true },
        y: {
          range: (u, dataMin, dataMax) => [
            this.min ?? Math.min(0, dataMin ?? 0),
            this.max !== null ? Math.max(this.max, dataMax ?? 0) : Math.max(1, (dataMax ?? 1) * 1.15),
          ],
        },
      },
      axes: [
        {
          ...axis,
          space: timeAxisSpace,
          splits: timeSplits,
          // Ticks under a minute apart need their seconds, or two ticks read the same.
          values: (u, ticks, axisIdx, space, incr) =>
            ticks.map((t) => timeLabel(t, ticks.length > 1 ? ticks[1] - ticks[0] : incr)),
        },
        { ...axis, size: 50, values: (u, ticks) => ticks.map(axisNumber) },
      ],
      series: [
        {},
        ...labels.map((label, i) => ({
          label,
          stroke: PALETTE[i % PALETTE.length],
          width: 1.6,
          spanGaps: true,
          points: { show: false },
          value: (u, v) => (v === null || v === undefined ? "—" : `${axisNumber(v)}${unit.startsWith("%") ? "%" : unit ? ` ${unit}` : ""}`),
        })),
      ],
    };
  }

  resize() {
    if (this.plot) this.plot.setSize({ width: Math.max(200, this.plotNode.clientWidth), height: 150 });
  }
}

// The log viewer's rules (static/js/logcore.js) under Node's test runner: `node --test tests/js/logviewer/`.

import assert from "node:assert/strict";
import { readFile } from "node:fs/promises";
import { test } from "node:test";

// static/js has no package.json saying "module": load the file as the ES module the browser loads.
const source = await readFile(new URL("../../../static/js/logcore.js", import.meta.url), "utf8");
const core = await import(`data:text/javascript,${encodeURIComponent(source)}`);
const { LineBuffer, apiLine, filterQuery, formatLine, framesLines, levelRank, matcher } = core;

const line = (seq, ts, extra = {}) => ({
  skill: "nav",
  component: "planner",
  location: "robot",
  stream: "stdout",
  level: null,
  text: `line ${seq}`,
  seq,
  ts,
  ...extra,
});

test("a line without a level counts as info", () => {
  assert.equal(levelRank(null), levelRank("info"));
  assert.ok(levelRank("warning") > levelRank(null));
  assert.ok(levelRank("debug") < levelRank(undefined));
});

test("the level filter keeps that level and the ones above it", () => {
  const keep = matcher({ level: "warning" });
  const levels = ["debug", "info", null, "warning", "error", "critical"];
  assert.deepEqual(
    levels.filter((level) => keep(line(1, 1, { level }))),
    ["warning", "error", "critical"],
  );
});

test("the text filter is a case-insensitive substring, or a regular expression when asked", () => {
  const substring = matcher({ q: "TIMEOUT." });
  assert.ok(substring(line(1, 1, { text: "planner timeout. retrying" })));
  assert.ok(!substring(line(1, 1, { text: "planner timeoutX" })));
  const regex = matcher({ q: "time(out|d)\\.", regex: true });
  assert.ok(regex(line(1, 1, { text: "TIMED. again" })));
  assert.ok(!regex(line(1, 1, { text: "timeX" })));
});

test("a bad regular expression is refused naming the text field", () => {
  assert.throws(() => matcher({ q: "(unclosed", regex: true }), (error) => error.field === "q");
  // Not asked as a regular expression, the same text is a plain substring.
  assert.ok(matcher({ q: "(unclosed" })(line(1, 1, { text: "x (unclosed y" })));
});

test("scope and time narrow the lines", () => {
  const keep = matcher({ skill: "nav", component: "planner", location: "cloud", since: "1970-01-01T00:00:10Z" });
  assert.ok(keep(line(1, 11, { location: "cloud" })));
  assert.ok(!keep(line(1, 9, { location: "cloud" })));
  assert.ok(!keep(line(1, 11)));
  assert.ok(!keep(line(1, 11, { location: "cloud", component: "mapper" })));
});

test("the buffer keeps lines in time order, each once, and evicts the oldest past its cap", () => {
  const buffer = new LineBuffer(4);
  let change = buffer.add([line(2, 2), line(1, 1), line(3, 3)]);
  assert.deepEqual(change.appended.map((l) => l.seq), [1, 2, 3]);
  change = buffer.add([line(3, 3), line(2, 2)]);
  assert.deepEqual(change, { appended: [], inserted: [], evicted: [] }, "a line sent twice shows once");
  // A late line (the robot's ring) goes to its place, before the line after it.
  change = buffer.add([line(10, 2.5, { component: "mapper" })]);
  assert.equal(change.inserted.length, 1);
  assert.equal(change.inserted[0][1].seq, 3);
  change = buffer.add([line(4, 4), line(5, 5)]);
  assert.deepEqual(change.evicted.map((l) => l.seq), [1, 2]);
  assert.deepEqual(buffer.lines.map((l) => l.seq), [10, 3, 4, 5]);
  // An evicted line may come back (an older page).
  assert.ok(!buffer.has(line(1, 1)));
});

test("reading back evicts the newest instead", () => {
  const buffer = new LineBuffer(3);
  buffer.add([line(5, 5), line(6, 6), line(7, 7)]);
  const change = buffer.add([line(3, 3), line(4, 4)], { evict: "newest" });
  assert.deepEqual(change.evicted.map((l) => l.seq), [6, 7]);
  assert.deepEqual(buffer.lines.map((l) => l.seq), [3, 4, 5]);
});

test("a pushed frame and an API row become the same line", () => {
  const [pushed] = framesLines({
    robot: "r1",
    skill: "nav",
    component: "planner",
    location: "cloud",
    lines: [{ seq: 7, ts: 1796410800.5, stream: "stderr", text: "boom" }],
    dropped: 0,
  });
  const stored = apiLine({
    skill: "nav",
    component: "planner",
    location: "cloud",
    seq: 7,
    ts: "2026-12-04T19:00:00.500Z",
    stream: "stderr",
    level: null,
    text: "boom",
  });
  assert.deepEqual(pushed, stored);
  const buffer = new LineBuffer();
  buffer.add([pushed]);
  assert.ok(buffer.has(stored));
});

test("lines format as the download writes them", () => {
  assert.equal(
    formatLine(line(1, 1796410800.123, { level: "info" })),
    "2026-12-04T19:00:00.123Z robot stdout INFO nav/planner: line 1",
  );
});

test("the API's query carries only the filters set, regex only with a text", () => {
  assert.equal(filterQuery({ skill: "nav", level: "", regex: true }).toString(), "skill=nav");
  assert.equal(
    filterQuery({ q: "a.b", regex: true, until: "2026-12-04T19:00:00.000Z" }, { order: "desc" }).toString(),
    "q=a.b&regex=true&until=2026-12-04T19%3A00%3A00.000Z&order=desc",
  );
});

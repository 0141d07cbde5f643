// A robot's log viewer: history from the Robot API (cursor pages), a live tail over /ws/client/, crashes' last lines.

import { get, seg } from "./api.js";
import { startLive } from "./live.js";
import { LineBuffer, apiLine, filterQuery, framesLines, matcher } from "./logcore.js";
import { crashDetails, lineNode } from "./loglines.js";
import { el, errorText, fmtTime, frameBatcher, isoSeconds, setText } from "./util.js";

// Lines kept in the page: a chatty component would otherwise grow the DOM without end.
const MAX_LINES = 5000;
const PAGE = 500;
const CRASHES_SHOWN = 5;
const CRASH_KINDS = ["component_status", "cloud_component_crashed", "cloud_component_failed"];

const root = document.getElementById("log-viewer");
if (root) setup(root);

function setup(root) {
  const robotId = root.dataset.robot;
  const api = `/api/robot/${seg(robotId)}/logs`;
  const form = document.getElementById("log-filters");
  const linesNode = document.getElementById("logs-lines");
  const emptyNode = document.getElementById("logs-empty");
  const stateNode = document.getElementById("logs-state");
  const droppedNode = document.getElementById("logs-dropped");
  const errorNode = document.getElementById("logs-error");
  const qError = document.getElementById("logs-q-error");
  const olderButton = document.getElementById("logs-older");
  const followBox = document.getElementById("logs-follow");
  const pauseButton = document.getElementById("logs-pause");
  const download = document.getElementById("logs-download");
  const crashesNode = document.getElementById("logs-crashes");
  const crashList = document.getElementById("logs-crash-list");
  const live = startLive();

  const buffer = new LineBuffer(MAX_LINES);
  const nodes = new WeakMap(); // line -> its element
  let filters = {};
  let test = () => true;
  let generation = 0; // a filter change makes answers to earlier requests stale
  let loading = false; // history in flight: live lines wait, so they land after it in order
  let incoming = []; // live lines waiting for the next animation frame
  let pending = []; // lines that came while paused (the newest MAX_LINES), shown on resume
  let pendingCount = 0;
  let paused = false;
  let tailing = false; // no `until`: the view follows the robot live
  let subscribed = null;
  let olderUrl = null;
  let trimmedOld = false; // the oldest lines left the page: "load older" asks by time, not by cursor
  let trimmedNew = false; // "load older" pushed the newest out: resuming reloads
  let dropped = 0;
  let lastAutoTop = 0;

  // ------------------------------------------------------------------------- filters and the address

  const toIso = (local) => (local ? new Date(local).toISOString() : "");
  function toLocal(iso) {
    const date = new Date(/^\d+(\.\d+)?$/.test(iso) ? Number(iso) * 1000 : iso);
    if (Number.isNaN(date.getTime())) return "";
    const pad = (n) => String(n).padStart(2, "0");
    return `${date.getFullYear()}-${pad(date.getMonth() + 1)}-${pad(date.getDate())}T${pad(date.getHours())}:${pad(date.getMinutes())}:${pad(date.getSeconds())}`;
  }

  function readForm() {
    const values = {};
    const [skill, component] = form.elements.scope.value.split("/");
    if (skill) values.skill = skill;
    if (component) values.component = component;
    for (const name of ["location", "level", "q"]) {
      const value = form.elements[name].value.trim();
      if (value) values[name] = value;
    }
    if (form.elements.regex.checked) values.regex = true;
    for (const name of ["since", "until"]) {
      const value = toIso(form.elements[name].value);
      if (value) values[name] = value;
    }
    return values;
  }

  function writeForm(params) {
    const skill = params.get("skill") ?? "";
    const scope = skill ? `${skill}/${params.get("component") ?? ""}` : "";
    if (scope && ![...form.elements.scope.options].some((option) => option.value === scope)) {
      // A component the page does not list (yet): still a valid filter.
      form.elements.scope.append(el("option", { value: scope }, scope));
    }
    form.elements.scope.value = scope;
    for (const name of ["location", "level", "q"]) form.elements[name].value = params.get(name) ?? "";
    form.elements.regex.checked = params.get("regex") === "true";
    for (const name of ["since", "until"]) form.elements[name].value = params.get(name) ? toLocal(params.get(name)) : "";
  }

  function remember() {
    if (!root.dataset.syncUrl) return;
    const params = filterQuery(filters);
    history.replaceState(null, "", `${location.pathname}${params.size ? `?${params}` : ""}`);
  }

  function showError(text, field) {
    errorNode.hidden = !text;
    errorNode.textContent = text || "";
    const q = form.elements.q;
    if (field === "q") q.setAttribute("aria-invalid", "true");
    else q.removeAttribute("aria-invalid");
    qError.hidden = field !== "q";
    qError.textContent = field === "q" ? text : "";
  }

  // ------------------------------------------------------------------------- drawing

  const atBottom = () => linesNode.scrollHeight - linesNode.scrollTop - linesNode.clientHeight < 4;

  function scrollToEnd() {
    linesNode.scrollTop = linesNode.scrollHeight;
    lastAutoTop = linesNode.scrollTop;
  }

  /** Mirror in the DOM what the buffer did: evicted lines leave, new ones go to their place. */
  function draw({ appended, inserted, evicted }, { keepBottom = false } = {}) {
    const source = !(filters.skill && filters.component);
    const fromBottom = linesNode.scrollHeight - linesNode.scrollTop;
    const gone = new Set(evicted);
    for (const line of evicted) nodes.get(line)?.remove();
    const fresh = new Set([...appended, ...inserted.map(([line]) => line)].filter((line) => !gone.has(line)));
    // From the newest back, each new line goes before the line after it, which is in place by then:
    // lines of several components interleave in time, and a late one costs no redraw.
    let next = null;
    for (let i = buffer.lines.length - 1, left = fresh.size; i >= 0 && left > 0; i--) {
      const line = buffer.lines[i];
      if (fresh.has(line)) {
        const node = lineNode(line, { source });
        nodes.set(line, node);
        linesNode.insertBefore(node, next);
        left--;
        next = node;
      } else {
        next = nodes.get(line);
      }
    }
    if (followBox.checked && !keepBottom) scrollToEnd();
    else if (keepBottom) linesNode.scrollTop = linesNode.scrollHeight - fromBottom; // older lines above: stay put
    emptyNode.hidden = buffer.size > 0;
    updateState();
  }

  function updateState() {
    let state;
    let text;
    if (!tailing) {
      state = "range";
      text = `${buffer.size} lines${filters.since ? ` from ${fmtTime(isoSeconds(filters.since))}` : ""} until ${fmtTime(isoSeconds(filters.until))}`;
    } else if (paused) {
      state = "paused";
      text = `Paused · ${pendingCount} new line${pendingCount === 1 ? "" : "s"}`;
    } else {
      state = subscribed ? "live" : "connecting";
      text = `${subscribed ? "Live" : "Connecting…"} · ${buffer.size} lines`;
    }
    stateNode.dataset.state = state;
    stateNode.dataset.pending = String(pendingCount);
    setText(stateNode, text);
    droppedNode.hidden = dropped === 0;
    setText(droppedNode, dropped ? `${dropped} lines dropped on the robot` : "");
    olderButton.hidden = !(olderUrl || trimmedOld);
  }

  const flush = frameBatcher(() => {
    if (loading || !incoming.length) return;
    const lines = incoming;
    incoming = [];
    if (paused) {
      pending.push(...lines);
      pendingCount += lines.length;
      if (pending.length > MAX_LINES) pending.splice(0, pending.length - MAX_LINES);
      updateState();
      return;
    }
    const change = buffer.add(lines);
    if (change.evicted.length) trimmedOld = true;
    draw(change);
  });

  // ------------------------------------------------------------------------- history (the Robot API)

  async function loadHistory(mine) {
    loading = true;
    const answer = await get(`${api}?${filterQuery(filters, { order: "desc", limit: PAGE })}`);
    if (mine !== generation) return;
    loading = false;
    if (!answer.ok) {
      const field = answer.status === 400 && answer.data && Object.keys(answer.data)[0];
      showError(`The logs did not load: ${errorText(answer.data, answer.status)}`, field);
    } else {
      showError("");
      olderUrl = answer.data.next;
      dropped += answer.data.dropped ?? 0;
      draw(buffer.add(answer.data.results.map(apiLine)));
      scrollToEnd();
    }
    flush();
  }

  async function older() {
    const mine = generation;
    const oldest = buffer.oldest;
    const url =
      trimmedOld && oldest
        ? `${api}?${filterQuery({ ...filters, until: new Date(oldest.ts * 1000).toISOString() }, { order: "desc", limit: PAGE })}`
        : olderUrl;
    if (!url) return;
    olderButton.disabled = true;
    const answer = await get(url);
    olderButton.disabled = false;
    if (mine !== generation) return;
    if (!answer.ok) return showError(`Older lines did not load: ${errorText(answer.data, answer.status)}`);
    olderUrl = answer.data.next;
    trimmedOld = trimmedOld && answer.data.results.length > 0 && Boolean(answer.data.next);
    const change = buffer.add(answer.data.results.map(apiLine), { evict: "newest" });
    if (change.evicted.length) {
      // The page holds MAX_LINES: reading further back lets the newest go, and holds the tail still.
      trimmedNew = true;
      if (tailing && !paused) setPaused(true);
    }
    draw(change, { keepBottom: true });
  }

  // ------------------------------------------------------------------------- the live tail

  function scopeOf(f) {
    const scope = { robot: robotId };
    if (f.skill) scope.skill = f.skill;
    if (f.component) scope.component = f.component;
    return scope;
  }

  function receive(frame) {
    const data = frame.data;
    if (!tailing || (data.robot && data.robot !== robotId)) return;
    dropped += data.dropped ?? 0;
    const lines = framesLines(data).filter(test);
    if (lines.length) {
      incoming.push(...lines);
      flush();
    } else if (data.dropped) {
      updateState();
    }
  }

  const sameScope = (a, b) => a.skill === b.skill && a.component === b.component;

  async function subscribe() {
    const scope = scopeOf(filters);
    const current = () => tailing && sameScope(scope, scopeOf(filters));
    try {
      // tail 0: the history comes from the API, filtered; ring: lines the robot never shipped come too.
      const answer = await live.request("logs_subscribe", { ...scope, tail: 0, ring: true });
      if (!current()) {
        // The filters moved on while the cloud answered: leave what nobody reads any more.
        live.request("logs_unsubscribe", scope).catch(() => {});
        return;
      }
      subscribed = scope;
      if (answer.event === "component_logs") receive(answer);
      updateState();
    } catch (error) {
      if (!current() || error.code === "closed") return;
      stateNode.dataset.state = "unavailable";
      setText(stateNode, `Live tail unavailable: ${error.message}`);
    }
  }

  function unsubscribe() {
    if (!subscribed) return;
    live.request("logs_unsubscribe", subscribed).catch(() => {});
    subscribed = null;
  }

  // After a reconnect the cloud forgot the subscription and frames may have been missed.
  async function resync() {
    if (!tailing) return;
    const mine = generation;
    subscribed = null;
    subscribe();
    const newest = buffer.newest;
    const since = newest ? new Date(newest.ts * 1000).toISOString() : filters.since;
    const answer = await get(`${api}?${filterQuery({ ...filters, since }, { order: "asc", limit: 1000 })}`);
    if (mine !== generation || !answer.ok) return;
    incoming.push(...answer.data.results.map(apiLine));
    flush();
  }

  // ------------------------------------------------------------------------- follow and pause

  function setPaused(on) {
    paused = on;
    pauseButton.setAttribute("aria-pressed", String(on));
    setText(pauseButton, on ? "Resume" : "Pause");
    if (!on) {
      if (trimmedNew) return apply(); // the newest left the page while reading back: load them again
      incoming = [...pending, ...incoming];
      pending = [];
      pendingCount = 0;
      followBox.checked = true;
      flush();
    }
    updateState();
  }

  let previousTop = 0;
  linesNode.addEventListener("scroll", () => {
    // The reader scrolled up: stop following; scrolled back down to the end: follow again.
    const top = linesNode.scrollTop;
    if (followBox.checked && top < lastAutoTop - 2 && !atBottom()) followBox.checked = false;
    else if (!followBox.checked && tailing && top > previousTop && atBottom()) followBox.checked = true;
    previousTop = top;
  });
  followBox.addEventListener("change", () => followBox.checked && scrollToEnd());
  pauseButton.addEventListener("click", () => setPaused(!paused));
  olderButton.addEventListener("click", older);

  // ------------------------------------------------------------------------- crashes

  function crashItem(event) {
    const details = crashDetails(event);
    if (!details) return null;
    const ts = isoSeconds(event.ts);
    return el(
      "li",
      { dataset: { event: String(event.id) } },
      el("time", { datetime: event.ts }, fmtTime(ts)),
      " ",
      el("span", {}, event.message),
      details,
    );
  }

  function showCrashes(events) {
    const items = events.map(crashItem).filter(Boolean).slice(0, CRASHES_SHOWN);
    crashList.replaceChildren(...items);
    crashesNode.hidden = items.length === 0;
    setText(document.getElementById("logs-crashes-title"), `Recent crashes (${items.length})`);
  }

  async function loadCrashes(mine) {
    const scope = {};
    if (filters.skill) scope.skill = filters.skill;
    if (filters.component) scope.component = filters.component;
    const answers = await Promise.all(
      CRASH_KINDS.map((kind) => get(`/api/events?${new URLSearchParams({ robot: robotId, kind, level: "error", limit: 20, ...scope })}`)),
    );
    if (mine !== generation) return;
    const events = answers.flatMap((answer) => (answer.ok ? answer.data.results : []));
    events.sort((a, b) => (a.ts < b.ts ? 1 : -1));
    showCrashes(events);
  }

  live.on("log_event", (frame) => {
    const event = frame.data;
    if (event.robot !== robotId || !CRASH_KINDS.includes(event.kind)) return;
    if ((filters.skill && event.skill !== filters.skill) || (filters.component && event.component !== filters.component)) return;
    const item = crashItem(event);
    if (!item) return;
    crashList.prepend(item);
    while (crashList.children.length > CRASHES_SHOWN) crashList.lastElementChild.remove();
    crashesNode.hidden = false;
    setText(document.getElementById("logs-crashes-title"), `Recent crashes (${crashList.children.length})`);
  });

  // ------------------------------------------------------------------------- applying filters

  function apply() {
    const wanted = readForm();
    let wantedTest;
    try {
      wantedTest = matcher(wanted);
    } catch (error) {
      return showError(error.message, error.field);
    }
    const mine = ++generation;
    const before = filters;
    filters = wanted;
    test = wantedTest;
    showError("");
    remember();
    download.href = `${api}/download?${filterQuery(filters)}`;
    buffer.clear();
    linesNode.replaceChildren();
    incoming = [];
    pending = [];
    pendingCount = 0;
    dropped = 0;
    olderUrl = null;
    trimmedOld = trimmedNew = false;
    paused = false;
    pauseButton.setAttribute("aria-pressed", "false");
    setText(pauseButton, "Pause");
    const wasTailing = tailing;
    tailing = !filters.until;
    pauseButton.disabled = !tailing;
    followBox.disabled = !tailing;
    const sameScope = wasTailing && tailing && before.skill === filters.skill && before.component === filters.component;
    if (!sameScope) {
      unsubscribe();
      if (tailing) subscribe();
    }
    updateState();
    loadHistory(mine);
    loadCrashes(mine);
  }

  form.addEventListener("submit", (event) => {
    event.preventDefault();
    apply();
  });
  form.addEventListener("reset", () => setTimeout(apply));
  // The component and level pickers apply at once; text and times on submit (Enter).
  for (const name of ["scope", "location", "level"]) form.elements[name].addEventListener("change", apply);
  live.on("component_logs", receive);
  live.onResync(resync);

  if (root.dataset.syncUrl) writeForm(new URLSearchParams(location.search));
  apply();
}

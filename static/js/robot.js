// Robot page: skills and components with their commands, live charts, offloading decisions, config.

import { get, post, seg } from "./api.js";
import { TimeChart } from "./charts.js";
import { startLive } from "./live.js";
import { setupConfigForm } from "./robotconfig.js";
import {
  ROBOT_METRICS,
  coalesce,
  debounce,
  el,
  errorText,
  fmtAgo,
  fmtMetric,
  fmtNumber,
  fmtTime,
  isoSeconds,
  pageData,
  setClass,
  setText,
  toast,
  unitOf,
} from "./util.js";

const DECISION_METRIC = "offloading.decision";
const DECISION_EVENT = "offloading_decision";
const DECISIONS_SHOWN = 12;
const HISTORY_S = 600;
const HISTORY_BUCKET_S = 5;
const COMMAND_WAIT_S = 5;

let robot = pageData("robot-data");
// What the request's role allows on this robot: the page shows only those buttons; the API refuses the rest.
const rights = pageData("robot-rights");
const robotId = robot.id;
const base = `/api/robot/${seg(robotId)}`;
const live = startLive();

// --------------------------------------------------------------------------- header and tiles

const connection = document.getElementById("robot-connection");
const statusNode = document.getElementById("robot-status");
const offloadingNode = document.getElementById("robot-offloading");
const seenNode = document.getElementById("robot-seen");
let lastSeen = isoSeconds(robot.last_seen);

function renderHeader() {
  setText(connection, robot.connected ? "online" : "offline");
  setClass(connection, "online", robot.connected);
  setClass(connection, "offline", !robot.connected);
  setText(statusNode, robot.status);
  setText(offloadingNode, robot.config?.offloading ?? "—");
  setText(seenNode, robot.connected ? "connected" : lastSeen ? `${fmtAgo(lastSeen)} (${fmtTime(lastSeen)})` : "never");
}

const tiles = {};
for (const [name, meta] of Object.entries(ROBOT_METRICS)) {
  const big = el("div", { class: "big" }, "—");
  const when = el("div", { class: "when" }, "no value yet");
  document.getElementById("tiles").append(el("div", { class: "tile" }, el("div", { class: "label" }, meta.label), big, when));
  tiles[name] = { big, when, ts: 0 };
}

function updateTile(name, value, ts) {
  const tile = tiles[name];
  // History arrives after the first live values: never let an older value replace a newer one.
  if (ts < tile.ts) return;
  tile.ts = ts;
  setText(tile.big, fmtMetric(name, value));
  setText(tile.when, `at ${fmtTime(ts)}`);
}

for (const button of document.querySelectorAll("[data-robot-command]")) {
  const verb = button.dataset.robotCommand;
  const what = `${verb[0].toUpperCase()}${verb.slice(1)} the robot`;
  button.addEventListener("click", () => command(button, `${base}/${verb}`, undefined, what));
}

// --------------------------------------------------------------------------- skills and components

const skillsNode = document.getElementById("skills");
const skillsEmpty = document.getElementById("skills-empty");
const componentRows = new Map(); // "skill/component" -> {cells}
const outcomes = new Map(); // "skill/component" -> {text, kind}

const ALLOWED = { robot: "robot only", cloud: "cloud only", either: "robot or cloud" };

function findComponent(skillId, componentId) {
  const skill = robot.skills.find((s) => s.skill_id === skillId);
  return skill?.components.find((c) => c.component_id === componentId);
}

/** Run one command through the API and say what came of it, in place and in a toast. */
async function command(button, url, body, what, key) {
  button.setAttribute("aria-busy", "true");
  button.disabled = true;
  const answer = await post(`${url}?wait=${COMMAND_WAIT_S}`, body);
  button.removeAttribute("aria-busy");
  button.disabled = false;
  let text;
  let kind;
  if (answer.ok && answer.data?.accepted) {
    [text, kind] = [`${what}: accepted by the robot`, "ok"];
  } else if (answer.ok) {
    [text, kind] = [`${what}: refused by the robot (${answer.data?.reply?.data?.message ?? "no reason"})`, "error"];
  } else if (answer.status === 409) {
    [text, kind] = [`${what}: the robot is offline`, "error"];
  } else if (answer.status === 504) {
    [text, kind] = [`${what}: the robot did not answer within ${COMMAND_WAIT_S} s`, "error"];
  } else {
    [text, kind] = [`${what}: ${errorText(answer.data, answer.status)}`, "error"];
  }
  toast(text, kind);
  if (key) {
    outcomes.set(key, { text, kind });
    updateComponent(...key.split("/"));
  }
  return answer;
}

function badge(text, cls) {
  return el("span", { class: `badge ${cls}` }, text);
}

function renderSkills() {
  componentRows.clear();
  skillsEmpty.hidden = robot.skills.length > 0;
  skillsNode.replaceChildren(...robot.skills.map(renderSkill));
}

function renderSkill(skill) {
  const sid = skill.skill_id;
  const skillUrl = `${base}/skill/${seg(sid)}`;
  const status = badge(skill.status, `status-${skill.status}`);
  status.dataset.skillStatus = sid;
  const start = el("button", { type: "button", class: "small", "aria-label": `Start skill ${sid}` }, "Start");
  const stop = el("button", { type: "button", class: "small secondary", "aria-label": `Stop skill ${sid}` }, "Stop");
  const remove = el("button", { type: "button", class: "small danger", "aria-label": `Remove skill ${sid}` }, "Remove");
  start.addEventListener("click", () => command(start, `${skillUrl}/start`, undefined, `Start ${sid}`));
  stop.addEventListener("click", () => command(stop, `${skillUrl}/stop`, undefined, `Stop ${sid}`));
  remove.addEventListener("click", () => removeSkill(remove, sid));
  const rows = skill.components.map((component) => renderComponent(sid, component));
  return el(
    "article",
    { class: "skill", "aria-labelledby": `skill-${sid}`, dataset: { skill: sid } },
    el(
      "div",
      { class: "skill-head" },
      el("h3", { id: `skill-${sid}` }, skill.name || sid, el("code", {}, sid), status),
      el(
        "div",
        { class: "actions", role: "group", "aria-label": `Commands for skill ${sid}` },
        rights.command ? [start, stop] : [],
        rights.develop ? remove : [],
      ),
    ),
    el(
      "div",
      { class: "table-wrap flush" },
      el(
        "table",
        { class: "components" },
        el(
          "thead",
          {},
          el(
            "tr",
            {},
            ["Component", "May run", "Location", "Status", "Commands"].map((h) => el("th", { scope: "col" }, h)),
          ),
        ),
        el("tbody", {}, rows),
      ),
    ),
  );
}

function renderComponent(sid, component) {
  const cid = component.component_id;
  const key = `${sid}/${cid}`;
  const url = `${base}/skill/${seg(sid)}/component/${seg(cid)}`;
  const location = el("span", { class: "badge", dataset: { location: key } });
  const status = el("span", { class: "badge", dataset: { status: key } });
  const reason = el("span", { class: "reason", dataset: { reason: key } });
  const pull = el("progress", { class: "pull", dataset: { pull: key }, hidden: "" });
  const allowed = component.location;
  const where = el(
    "select",
    { "aria-label": `Where to start ${cid}` },
    ["robot", "cloud"].filter((side) => allowed === "either" || allowed === side).map((side) => el("option", { value: side }, side)),
  );
  const start = el("button", { type: "button", class: "small", "aria-label": `Start ${cid}` }, "Start");
  const stop = el("button", { type: "button", class: "small secondary", "aria-label": `Stop ${cid}` }, "Stop");
  const migrate = el("button", { type: "button", class: "small secondary", dataset: { migrate: key } }, "Migrate");
  start.addEventListener("click", () => command(start, `${url}/start`, { location: where.value }, `Start ${cid}`, key));
  stop.addEventListener("click", () => command(stop, `${url}/stop`, {}, `Stop ${cid}`, key));
  migrate.addEventListener("click", async () => {
    const before = findComponent(sid, cid)?.active_location;
    const answer = await command(migrate, `${url}/migrate`, {}, `Migrate ${cid}`, key);
    if (answer.ok && answer.data?.accepted) {
      // The robot may have reported the new location before its answer to the command arrived.
      const now = findComponent(sid, cid)?.active_location;
      outcomes.set(key, now !== before ? { text: `now runs on the ${now}`, kind: "ok" } : { text: "migrating…", kind: "" });
      updateComponent(sid, cid);
    }
  });
  const outcome = el("span", { class: "outcome", role: "status" });
  const image = el("span", { class: "sub image" });
  const row = el(
    "tr",
    { dataset: { component: key } },
    el("th", { scope: "row" }, el("span", {}, cid), el("span", { class: "sub" }, component.name ?? ""), image, logsLink(sid, cid)),
    el("td", { dataset: { label: "May run" } }, ALLOWED[allowed] ?? allowed),
    el("td", { dataset: { label: "Location" } }, location),
    el("td", { dataset: { label: "Status" } }, status, reason, pull),
    el(
      "td",
      { class: "commands" },
      rights.command ? el("div", { class: "actions" }, el("span", { class: "start-at" }, start, where), stop, migrate) : [],
      outcome,
    ),
  );
  componentRows.set(key, { location, status, reason, pull, migrate, outcome, where, image });
  updateComponent(sid, cid);
  return row;
}

// A component's logs: the robot's log viewer filtered to it, at an address of its own.
const logsLink = (sid, cid) => el("a", { class: "logs-link", href: `/robots/${seg(robotId)}/logs/?${new URLSearchParams({ skill: sid, component: cid })}`, "aria-label": `Logs of ${cid}` }, "logs");

function updateComponent(sid, cid) {
  const key = `${sid}/${cid}`;
  const cells = componentRows.get(key);
  const component = findComponent(sid, cid);
  if (!cells || !component) return;
  const active = component.active_location || "";
  setText(cells.location, active || "not placed");
  cells.location.className = `badge loc-${active || "none"}`;
  setText(cells.status, component.status);
  cells.status.className = `badge status-${component.status}`;
  // Why it is in that status (why it failed), as the robot said; nothing once it runs again.
  setText(cells.reason, component.message || "");
  cells.status.title = component.message || "";
  // The image it runs: a Skill's image from the cloud's registry is pinned, so the digest shows.
  const runs = component.container?.[active]?.image ?? component.container?.robot?.image ?? "";
  const [name, digest] = runs.split("@");
  setText(cells.image, digest ? `${name}@${digest.slice(0, 19)}…` : runs);
  cells.image.title = runs;
  // Its image on the way to the robot: bytes pulled of its compressed size, until it runs.
  const pull = component.container?.robot?.pull;
  const pulling = Boolean(pull) && component.status !== "running" && component.status !== "failed";
  cells.pull.hidden = !pulling;
  if (pulling) {
    cells.pull.max = Math.max(pull.total, 1);
    cells.pull.value = Math.min(pull.done, cells.pull.max);
    const mb = (bytes) => (bytes / 1e6).toFixed(1);
    cells.pull.title = `pulling ${pull.image}: ${mb(pull.done)} of ${mb(pull.total)} MB`;
    cells.pull.setAttribute("aria-label", cells.pull.title);
  }
  const movable = component.location === "either" && Boolean(active);
  cells.migrate.disabled = !movable;
  setText(cells.migrate, movable ? `Migrate to ${active === "robot" ? "cloud" : "robot"}` : "Migrate");
  cells.migrate.setAttribute("aria-label", `${cells.migrate.textContent.replace("Migrate", `Migrate ${cid}`)}`);
  cells.migrate.title = component.location === "either" ? "" : `${cid} may only run on the ${component.location}`;
  const outcome = outcomes.get(key);
  setText(cells.outcome, outcome?.text ?? "");
  cells.outcome.className = `outcome ${outcome?.kind ?? ""}`;
}

async function removeSkill(button, sid) {
  button.disabled = true;
  const answer = await post(`${base}/skill/remove`, { skill: sid });
  button.disabled = false;
  if (answer.status === 204) {
    toast(`Removed skill ${sid}`, "ok");
    robot.skills = robot.skills.filter((s) => s.skill_id !== sid);
    renderSkills();
  } else {
    toast(`Remove ${sid}: ${errorText(answer.data, answer.status)}`, "error");
  }
}

/** Reload the robot's state (after a reconnect, or when its skills changed under us). */
const reload = debounce(async () => {
  const answer = await get(`${base}/info`);
  if (answer.status === 404) return gone();
  if (!answer.ok) return;
  robot = { ...answer.data, skills: withNames(answer.data.skills) };
  lastSeen = isoSeconds(robot.last_seen);
  renderHeader();
  renderSkills();
}, 200);

/** The Robot API's robot state has no component names; keep those the page knows. */
function withNames(skills) {
  const names = new Map();
  for (const skill of robot.skills) for (const c of skill.components) names.set(`${skill.skill_id}/${c.component_id}`, c.name);
  return skills.map((skill) => ({
    ...skill,
    components: skill.components.map((c) => ({ ...c, name: names.get(`${skill.skill_id}/${c.component_id}`) ?? "" })),
  }));
}

// --------------------------------------------------------------------------- charts

const robotCharts = new Map();
const componentCharts = new Map();
const componentChartsNode = document.getElementById("component-charts");
const componentChartsEmpty = document.getElementById("component-charts-empty");

for (const [name, meta] of Object.entries(ROBOT_METRICS)) {
  robotCharts.set(
    name,
    new TimeChart(document.getElementById("robot-charts"), {
      title: meta.label,
      unit: meta.unit,
      windowS: HISTORY_S,
      max: meta.max,
    }),
  );
}

function componentChart(name) {
  let chart = componentCharts.get(name);
  if (!chart) {
    chart = new TimeChart(componentChartsNode, { title: name, unit: unitOf(name, { component: true }), windowS: HISTORY_S });
    componentCharts.set(name, chart);
    componentChartsEmpty.hidden = true;
  }
  return chart;
}

// Robot-wide series beyond the four above, folded away: a closed section costs no drawing.
const moreCharts = new Map();
const moreNode = document.getElementById("more-robot-metrics");

function moreChart(family) {
  let chart = moreCharts.get(family);
  if (!chart) {
    chart = new TimeChart(document.getElementById("more-robot-charts"), { title: family, unit: unitOf(family), windowS: HISTORY_S });
    moreCharts.set(family, chart);
    moreNode.hidden = false;
  }
  return chart;
}

const multiSkill = () => robot.skills.length > 1;

function plot(point, options) {
  if (point.name === DECISION_METRIC) return;
  if (!point.skill && !point.component) {
    const chart = robotCharts.get(point.name);
    if (chart) {
      chart.add("robot", point.ts, point.value, options);
    } else {
      // "net_rx:eth0" is the eth0 line of the net_rx chart; plain "net_rx" its total.
      const [family, part] = point.name.split(":");
      moreChart(family).add(part ?? "total", point.ts, point.value, options);
    }
    return;
  }
  const label = multiSkill() || !point.component ? `${point.skill ?? "—"}/${point.component ?? "skill"}` : point.component;
  componentChart(point.name).add(label, point.ts, point.value, options);
}

async function loadHistory() {
  const until = new Date(Date.now() + 60_000);
  const since = new Date(Date.now() - HISTORY_S * 1000);
  const answer = await post("/api/database/query", {
    robots: [robotId],
    since: since.toISOString(),
    until: until.toISOString(),
    aggregate: "avg",
    bucket: HISTORY_BUCKET_S,
    limit: 10000,
  });
  if (!answer.ok) return;
  const latest = {};
  for (const row of answer.data.results) {
    const point = { name: row.name, skill: row.skill || null, component: row.component || null, value: row.value, ts: isoSeconds(row.bucket) };
    plot(point, { bucketS: HISTORY_BUCKET_S });
    if (!point.skill && !point.component && point.name in tiles && !(point.name in latest)) latest[point.name] = point;
  }
  for (const point of Object.values(latest)) updateTile(point.name, point.value, point.ts);
  // Charts with no history say so, instead of waiting.
  for (const chart of robotCharts.values()) chart.redrawSoon();
}

// --------------------------------------------------------------------------- offloading decisions

const decisionsBody = document.querySelector("#decisions tbody");
const decisionsEmpty = document.getElementById("decisions-empty");
// Decisions to stay are metric points; moves (done or failed) are offloading_decision events.
let decisionRows = [];

function decisionFromPoint(point) {
  const labels = point.labels ?? {};
  return {
    ts: point.ts,
    component: point.component,
    policy: labels.policy,
    costRobot: Number.parseFloat(labels.cost_robot),
    costCloud: Number.parseFloat(labels.cost_cloud),
    reward: point.value,
    outcome: labels.decision === "migrate" ? "decided" : "stay",
    location: labels.location,
    target: labels.target,
    reason: labels.reason,
    decidedBy: labels.decided_by,
  };
}

function decisionFromEvent(data) {
  return {
    ts: data.decided_at,
    component: data.component,
    policy: data.policy,
    costRobot: data.cost_robot,
    costCloud: data.cost_cloud,
    reward: data.prediction ?? data.estimated_reward,
    outcome: data.outcome,
    location: data.location,
    target: data.target,
    reason: data.error ? `${data.reason}; failed: ${data.error}` : `${data.reason}; took ${fmtNumber(data.duration_s, { digits: 2 })} s`,
    decidedBy: data.decided_by,
    networkError: data.network_error,
    estimateError: data.estimate_error,
  };
}

// Who decided (a rule, the policy's estimate or the network that learnt from outcomes) and, when the
// network was scored, its held-out error against the estimate's at the target: why it was trusted or not.
function decidedBy(row) {
  if (!row.decidedBy) return null;
  const by = { rule: "by a rule", estimate: "by the estimate", network: "by the learned network" }[row.decidedBy] ?? `by ${row.decidedBy}`;
  const scored = Number.isFinite(row.networkError) && Number.isFinite(row.estimateError);
  const why = scored ? ` (error ${fmtNumber(row.networkError, { digits: 3 })} vs ${fmtNumber(row.estimateError, { digits: 3 })})` : "";
  return el("span", { class: "sub", "data-decided-by": row.decidedBy }, by + why);
}

function decisionBadge(row) {
  if (row.outcome === "moved") return el("span", { class: `badge loc-${row.target ?? "none"}` }, `moved → ${row.target ?? "?"}`);
  if (row.outcome === "failed") return el("span", { class: "badge status-failed" }, `move → ${row.target ?? "?"} failed`);
  if (row.outcome === "decided") return el("span", { class: `badge loc-${row.target ?? "none"}` }, `migrate → ${row.target ?? "?"}`);
  return el("span", { class: "badge" }, `stay on ${row.location ?? "?"}`);
}

function renderDecisions() {
  // The newest of each kind: a stream of decisions to stay never pushes the rarer moves out.
  const sorted = decisionRows.toSorted((a, b) => b.ts - a.ts);
  const stays = sorted.filter((row) => row.outcome === "stay").slice(0, DECISIONS_SHOWN);
  const moves = sorted.filter((row) => row.outcome !== "stay").slice(0, DECISIONS_SHOWN);
  decisionRows = [...stays, ...moves].toSorted((a, b) => b.ts - a.ts);
  decisionsEmpty.hidden = decisionRows.length > 0;
  decisionsBody.replaceChildren(
    ...decisionRows.map((row) => {
      const cheaper = row.costRobot < row.costCloud ? "robot" : row.costCloud < row.costRobot ? "cloud" : "";
      return el(
        "tr",
        { "data-outcome": row.outcome, title: row.reason ?? "" },
        el("td", {}, fmtTime(row.ts)),
        el("td", {}, row.component ?? "—", row.policy ? el("span", { class: "sub" }, `policy ${row.policy}`) : null),
        el("td", { class: `num ${cheaper === "robot" ? "better" : ""}` }, fmtNumber(row.costRobot, { digits: 3 })),
        el("td", { class: `num ${cheaper === "cloud" ? "better" : ""}` }, fmtNumber(row.costCloud, { digits: 3 })),
        el("td", { class: "num" }, fmtNumber(row.reward, { digits: 3 })),
        el("td", {}, decisionBadge(row), decidedBy(row)),
      );
    }),
  );
}

async function loadDecisions() {
  const since = Date.now() / 1000 - 86400;
  const query = new URLSearchParams({
    robot: robotId,
    kind: DECISION_EVENT,
    since: new Date(since * 1000).toISOString(),
    limit: String(DECISIONS_SHOWN),
  });
  const [points, events] = await Promise.all([
    live
      .request("metrics_get", { robot: robotId, names: [DECISION_METRIC], since, limit: DECISIONS_SHOWN })
      .then((answer) => answer.data.metrics, () => null),
    get(`/api/events?${query}`).then((answer) => (answer.ok ? answer.data.results : null)),
  ]);
  if (points === null && events === null) return;
  decisionRows = [...(points ?? []).map(decisionFromPoint), ...(events ?? []).map((event) => decisionFromEvent(event.data))];
  renderDecisions();
}

// Decisions to stay arrive in the live feed without their labels: read them from the database shortly after.
const decisionsSoon = coalesce(loadDecisions, 1200);

// --------------------------------------------------------------------------- live frames

function mine(frame) {
  return frame.data?.robot === robotId;
}

live.on("metrics", (frame) => {
  if (!mine(frame)) return;
  for (const point of frame.data.metrics) {
    if (point.name === DECISION_METRIC) {
      decisionsSoon();
      continue;
    }
    plot(point);
    if (!point.skill && !point.component && point.name in tiles) updateTile(point.name, point.value, point.ts);
  }
});
live.on("connection_established", (frame) => {
  if (!mine(frame)) return;
  robot.connected = true;
  robot.status = "running";
  renderHeader();
});
live.on("connection_lost", (frame) => {
  if (!mine(frame)) return;
  robot.connected = false;
  lastSeen = frame.ts || Date.now() / 1000;
  renderHeader();
});
live.on("skill_status", (frame) => {
  if (!mine(frame)) return;
  const skill = robot.skills.find((s) => s.skill_id === frame.data.skill);
  if (!skill) return reload();
  skill.status = frame.data.status;
  const node = skillsNode.querySelector(`[data-skill-status="${CSS.escape(skill.skill_id)}"]`);
  if (node) {
    setText(node, skill.status);
    node.className = `badge status-${skill.status}`;
  }
});
for (const event of ["component_status", "component_location"]) {
  live.on(event, (frame) => {
    if (!mine(frame)) return;
    const component = findComponent(frame.data.skill, frame.data.component);
    if (!component) return reload();
    if (frame.data.status) {
      component.status = frame.data.status;
      component.message = frame.data.message ?? "";
    }
    if (frame.data.location) component.active_location = frame.data.location;
    const key = `${frame.data.skill}/${frame.data.component}`;
    if (outcomes.get(key)?.text === "migrating…" && event === "component_location") {
      outcomes.set(key, { text: `now runs on the ${frame.data.location}`, kind: "ok" });
    }
    updateComponent(frame.data.skill, frame.data.component);
  });
}
live.on("component_information", (frame) => {
  if (!mine(frame)) return;
  const component = findComponent(frame.data.skill, frame.data.component);
  if (!component) return;
  component.container = { ...(component.container ?? {}), [frame.data.location]: frame.data.container };
  updateComponent(frame.data.skill, frame.data.component);
});
live.on(DECISION_EVENT, (frame) => {
  if (!mine(frame)) return;
  decisionRows.push(decisionFromEvent(frame.data));
  renderDecisions();
});
live.on("skill_config", (frame) => mine(frame) && reload());
live.on("offloading", (frame) => {
  if (!mine(frame)) return;
  robot.config.offloading = frame.data.mode;
  renderHeader();
});
live.onResync(() => {
  reload();
  loadDecisions();
});
live.on("log_event", (frame) => frame.data.kind === "robot_deleted" && mine(frame) && gone());

/** The robot was deleted: say so instead of its page, which has nothing left to show. */
function gone() {
  const main = document.getElementById("content");
  if (main.dataset.gone) return;
  main.dataset.gone = "true";
  main.replaceChildren(
    el(
      "section",
      { class: "card gone", role: "status" },
      el("h1", {}, `Robot ${robotId} was deleted`),
      el("p", {}, "Its skills, components, metrics and events went with it. ", el("a", { href: "/" }, "Back to the fleet")),
    ),
  );
  document.title = `${robotId} (deleted) · bridgeOS Cloud`;
}

// --------------------------------------------------------------------------- start

renderHeader();
renderSkills();
setupConfigForm(robot, live, renderHeader);
loadHistory();
loadDecisions();
setInterval(() => robot.connected || renderHeader(), 30000);

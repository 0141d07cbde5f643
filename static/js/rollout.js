// One rollout, live: its counts, batches and robots read again every second while it is active,
// and a developer's Pause, Resume and Abort (the API refuses them to anyone else anyway).

import { get, post, seg } from "./api.js";
import { el, errorText, fmtDateTime, fmtTime, isoSeconds, pageData, setText } from "./util.js";

const POLL_MS = 1000;
// The states a rollout can still leave: paused included, as another operator may resume it.
const ACTIVE = new Set(["running", "paused", "rolling_back"]);
// Which states each action applies to (rollouts.rolling.steer refuses the rest with a 409).
const ALLOWED = { pause: ["running"], resume: ["paused"], abort: ["running", "paused"] };

const root = document.getElementById("rollout");
const base = `/api/rollouts/${seg(root.dataset.rollout)}`;
const stateNode = document.getElementById("rollout-state");
const reasonNode = document.getElementById("rollout-reason");
const errorNode = document.getElementById("rollout-error");
const actions = document.getElementById("rollout-actions");
const confirmBox = document.getElementById("abort-confirm");

let pollTimer = null;
let reads = 0;
let readFailed = false; // the message shown is a failed read's, which the next good read clears

function say(message) {
  errorNode.hidden = !message;
  setText(errorNode, message);
}

const timeCell = (iso) => el("td", { title: fmtDateTime(isoSeconds(iso)) }, iso ? el("time", { datetime: iso }, fmtTime(isoSeconds(iso))) : "—");

function countBadges(counts) {
  const shown = Object.entries(counts).filter(([, robots]) => robots > 0);
  if (!shown.length) return [el("span", { class: "muted" }, "none yet")];
  return shown.flatMap(([status, robots]) => [el("span", { class: `badge status-${status}`, dataset: { status } }, `${status} ${robots}`), " "]);
}

// A robot fetching the release's images: bytes pulled of the layers' compressed size.
function pulled(member) {
  if (member.status !== "downloading" || !member.bytes_total) return "";
  const mb = (n) => (n / 1e6).toFixed(1);
  return el("span", { class: "pulled" }, ` ${mb(member.bytes_done)} of ${mb(member.bytes_total)} MB`);
}

function robotRow(member) {
  return el(
    "tr",
    { dataset: { robot: member.robot, status: member.status } },
    el("th", { scope: "row" }, el("a", { href: `/robots/${seg(member.robot)}/` }, member.robot)),
    el("td", { "data-label": "Batch" }, String(member.batch + 1)),
    el("td", { "data-label": "Status" }, el("span", { class: `badge status-${member.status}` }, member.status), pulled(member)),
    el("td", { "data-label": "Reason" }, member.reason || ""),
    timeCell(member.started_at),
    timeCell(member.finished_at),
  );
}

function batchRow(batch, rollout) {
  return el(
    "tr",
    { dataset: { batch: String(batch.index + 1), state: batch.state }, "aria-current": batch.index === rollout.batch ? "step" : false },
    el("th", { scope: "row" }, `${batch.index + 1} of ${rollout.batch_sizes.length}`),
    el("td", { class: "num" }, String(batch.size)),
    el("td", {}, el("span", { class: `badge state-${batch.state}` }, batch.state)),
    el("td", {}, countBadges(batch.counts)),
  );
}

function render(rollout) {
  setText(stateNode, rollout.state);
  stateNode.className = `badge state-${rollout.state}`;
  setText(reasonNode, rollout.reason);
  reasonNode.hidden = !rollout.reason;
  setText(document.getElementById("rollout-batch"), `${rollout.batch + 1} of ${rollout.batch_sizes.length}`);
  setText(document.getElementById("rollout-finished"), rollout.finished_at ? fmtDateTime(isoSeconds(rollout.finished_at)) : "—");
  document.getElementById("rollout-counts").replaceChildren(...countBadges(rollout.counts));
  document.getElementById("rollout-batches").replaceChildren(...rollout.batches.map((batch) => batchRow(batch, rollout)));
  document.getElementById("rollout-robots").replaceChildren(...rollout.robots.map(robotRow));
  document.getElementById("rollout-no-robots").hidden = rollout.robots.length > 0;
  root.dataset.state = rollout.state;
  if (actions && confirmBox.hidden) {
    for (const button of actions.querySelectorAll("[data-steer]")) button.hidden = !ALLOWED[button.dataset.steer].includes(rollout.state);
  }
}

/** Read the rollout again and show it; keep reading while it is active. */
let waitingForTab = false;

async function refresh() {
  clearTimeout(pollTimer);
  pollTimer = null;
  if (document.hidden) {
    // Nobody looks: no read a second for a thousand robots until the tab shows again.
    waitingForTab = true;
    return;
  }
  const asked = ++reads;
  const answer = await get(base);
  if (asked !== reads) return; // a later read (after an action) answers instead: its state is newer
  if (!answer.ok) {
    readFailed = true;
    say(`The rollout did not refresh: ${errorText(answer.data, answer.status)}`);
    // Out of reach now (another organization picked, the session over): reading again would not help.
    if ([401, 403, 404].includes(answer.status)) return;
  } else {
    if (readFailed) say("");
    readFailed = false;
    render(answer.data);
    if (!ACTIVE.has(answer.data.state)) return;
  }
  pollTimer = setTimeout(refresh, POLL_MS);
}

async function steer(action, button) {
  button.disabled = true;
  button.setAttribute("aria-busy", "true");
  let answer;
  try {
    answer = await post(`${base}/${action}`);
  } finally {
    button.disabled = false;
    button.removeAttribute("aria-busy");
  }
  // A 409 says why in its detail: the rollout moved on since this page last read it.
  readFailed = false;
  say(answer.ok ? "" : `${action[0].toUpperCase()}${action.slice(1)}: ${errorText(answer.data, answer.status)}`);
  await refresh();
}

/** Ask once more before an abort: it rolls back every robot the rollout touched. */
function askToAbort() {
  confirmBox.hidden = false;
  for (const button of actions.querySelectorAll("[data-steer]")) button.hidden = true;
  document.getElementById("abort-yes").focus();
}

function endAsking() {
  confirmBox.hidden = true;
}

actions?.addEventListener("click", (event) => {
  const button = event.target.closest("button");
  if (!button) return;
  if (button.dataset.steer === "abort") askToAbort();
  else if (button.dataset.steer) steer(button.dataset.steer, button);
  else if (button.id === "abort-yes") {
    endAsking();
    steer("abort", button);
  } else if (button.id === "abort-no") {
    endAsking();
    refresh();
  }
});

const first = pageData("rollout-data");
// In the operator's own time zone, as every other time the page shows.
setText(document.getElementById("rollout-created"), fmtDateTime(isoSeconds(first.created_at)));
render(first);
if (ACTIVE.has(first.state)) pollTimer = setTimeout(refresh, POLL_MS);
document.addEventListener("visibilitychange", () => {
  if (!document.hidden && waitingForTab) {
    waitingForTab = false;
    refresh();
  }
});

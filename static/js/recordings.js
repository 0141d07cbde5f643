// Robot page: start, stop, download and delete the robot's MCAP recordings through the Robot API.
//
// The table is kept from the API's list: read once when the page opens (the server rendered the
// first state), again after each action, and every POLL_MS while a recording runs or its chunks are
// still arriving; polling stops once none does. The API holds every rule: the form sends what was
// typed and shows the API's answer next to the field it names.

import { api, get, post, seg } from "./api.js";
import { NON_FIELD, clearErrors, showFormErrors } from "./forms.js";
import { el, errorText, pageData, setClass, setText } from "./util.js";

const robotId = pageData("robot-data").id;
const base = `/api/robot/${seg(robotId)}/recordings`;
const MIB = 1024 * 1024;
const POLL_MS = 1000;
const LIST_LIMIT = 50; // the newest, as the page renders them
const WAIT_S = 10; // how long the API waits for the robot's answer to a start or a stop
const RUNNING = new Set(["starting", "recording"]);
const ENDED = new Set(["finished", "failed"]);

const rights = pageData("robot-rights");
const form = document.getElementById("recording-form");
const result = document.getElementById("recording-result");
const title = document.getElementById("recordings-title");
const wrap = document.getElementById("recordings-wrap");
const body = document.querySelector("#recordings tbody");
const empty = document.getElementById("recordings-empty");
const liveTopics = document.getElementById("recording-live-topics");
const topicsInput = form?.elements.topics;

let known = new Map(); // recording id -> its last seen status, to say when one ends
let pollTimer = null;
let reads = 0; // reads of the list asked for, so only the latest one renders

/** Split what was typed into topic names: commas, spaces or newlines between them. */
function parseTopics(text) {
  return text.split(/[\s,]+/).filter(Boolean);
}

/** Build the Robot API's start body from the form; empty limits are left to the API's defaults. */
function startBody() {
  const data = new FormData(form);
  const body = { topics: parseTopics(String(data.get("topics") ?? "")) };
  const ros = String(data.get("ros") ?? "");
  if (ros) body.ros = ros;
  const mib = String(data.get("max_mib") ?? "").trim();
  if (mib) body.max_bytes = Math.round(Number(mib) * MIB);
  const seconds = String(data.get("max_duration_s") ?? "").trim();
  if (seconds) body.max_duration_s = Number(seconds);
  return body;
}

/**
 * Turn the API's error body into {field: [messages]} for showFormErrors: a topic's own error (DRF
 * keys it by the topic's index) names the topic, and a refusal without a field goes to the summary.
 */
function startErrors(data, status, topics) {
  if (!data || typeof data !== "object" || data.detail) return { [NON_FIELD]: [errorText(data, status)] };
  const errors = {};
  for (const [field, value] of Object.entries(data)) {
    const key = field === "non_field_errors" ? NON_FIELD : field;
    const messages = Array.isArray(value)
      ? value.map(String)
      : Object.entries(value).flatMap(([index, list]) => [list].flat().map((m) => `${topics[Number(index)] ?? index}: ${m}`));
    (errors[key] ??= []).push(...messages);
  }
  return errors;
}

// --------------------------------------------------------------------------- the table

/** Format a size as Django's filesizeformat does, so rows the page rendered and rows read later agree. */
function fmtSize(bytes) {
  if (bytes < 1024) return `${bytes}\u00a0${bytes === 1 ? "byte" : "bytes"}`;
  const units = ["KB", "MB", "GB", "TB", "PB"];
  let value = bytes / 1024;
  let unit = 0;
  while (value >= 1024 && unit < units.length - 1) {
    value /= 1024;
    unit += 1;
  }
  return `${value.toFixed(1)}\u00a0${units[unit]}`;
}

/** Format an API time as the page's template does ("Y-m-d H:i:s" in the cloud's time zone, UTC). */
function fmtStamp(iso) {
  return iso ? new Date(iso).toISOString().slice(0, 19).replace("T", " ") : "—";
}

const what = (recording) => `the recording of ${recording.topics.join(", ")}`;
const What = (recording) => `The recording of ${recording.topics.join(", ")}`;

function actions(recording) {
  if (!rights.command) return []; // a viewer downloads; stopping and deleting are an operator's
  if (RUNNING.has(recording.status)) {
    const stop = el("button", { type: "button", class: "small secondary", "aria-label": `Stop ${what(recording)}` }, "Stop");
    stop.addEventListener("click", () => stopRecording(stop, recording));
    return [stop];
  }
  if (ENDED.has(recording.status)) {
    const remove = el("button", { type: "button", class: "small danger", "aria-label": `Delete ${what(recording)} from ${fmtStamp(recording.started_at ?? recording.created_at)}` }, "Delete");
    remove.addEventListener("click", () => askToDelete(remove, recording));
    return [remove];
  }
  return []; // stopping: the robot ended it and its last chunks are on their way
}

function row(recording) {
  const download = recording.download ? new URL(recording.download, window.location.href).pathname : null;
  return el(
    "tr",
    { dataset: { recording: recording.id, status: recording.status } },
    el("td", {}, fmtStamp(recording.started_at ?? recording.created_at)),
    el("td", {}, recording.topics.join(", ")),
    el("td", {}, recording.ros || "—"),
    el(
      "td",
      {},
      el("span", { class: `badge status-${recording.status}` }, recording.status),
      recording.message ? [" ", el("span", { class: "muted" }, `(${recording.message})`)] : null,
    ),
    el("td", { class: "num" }, String(recording.message_count)),
    el("td", { class: "num" }, recording.duration_s === null ? "—" : `${recording.duration_s.toFixed(1)} s`),
    el("td", { class: "num" }, fmtSize(recording.size_bytes)),
    el("td", {}, download ? el("a", { href: download, download: true }, "Download .mcap") : "—"),
    el("td", { class: "row-actions" }, actions(recording)),
  );
}

function say(text, kind = "") {
  setText(result, text);
  setClass(result, "ok", kind === "ok");
  setClass(result, "error", kind === "error");
}

/** Say when a recording the page saw running has ended, with what it holds. */
function announceEnded(recordings) {
  for (const recording of recordings) {
    const before = known.get(recording.id);
    if (before && !ENDED.has(before) && ENDED.has(recording.status)) {
      const how = recording.message ? ` (${recording.message})` : "";
      const kind = recording.status === "finished" ? "ok" : "error";
      say(`${What(recording)} ${recording.status}${how}: ${recording.message_count} messages, ${fmtSize(recording.size_bytes)}.`, kind);
    }
  }
  known = new Map(recordings.map((recording) => [recording.id, recording.status]));
}

function render(recordings) {
  announceEnded(recordings);
  // A redraw replaces the buttons: keep focus on the same one, or on the card's title once it is gone.
  const focused = body.contains(document.activeElement) ? document.activeElement.getAttribute("aria-label") : null;
  body.replaceChildren(...recordings.map(row));
  if (focused) (body.querySelector(`button[aria-label="${CSS.escape(focused)}"]`) ?? title).focus();
  wrap.hidden = recordings.length === 0;
  empty.hidden = recordings.length > 0;
}

/** Read the list again and render it; keep polling while any recording is not over. */
async function refresh() {
  clearTimeout(pollTimer);
  pollTimer = null;
  const asked = ++reads;
  const answer = await get(`${base}?limit=${LIST_LIMIT}`);
  if (asked !== reads) return; // a later read (after an action) answers instead: its list is newer
  if (!answer.ok) {
    say(`Could not read the recordings: ${errorText(answer.data, answer.status)}`, "error");
    return;
  }
  // Keep a delete being confirmed on screen: a redraw would take its buttons away.
  if (!body.querySelector("[data-confirming]")) render(answer.data);
  if (answer.data.some((recording) => !ENDED.has(recording.status))) pollTimer = setTimeout(refresh, POLL_MS);
}

// --------------------------------------------------------------------------- actions

async function busy(button, action) {
  button.disabled = true;
  button.setAttribute("aria-busy", "true");
  try {
    return await action();
  } finally {
    button.disabled = false;
    button.removeAttribute("aria-busy");
  }
}

async function stopRecording(button, recording) {
  const answer = await busy(button, () => post(`${base}/${seg(recording.id)}/stop?wait=${WAIT_S}`));
  if (answer.ok) say(`Stopping ${what(recording)}; the robot is sending its last part.`, "ok");
  else say(`Stop ${what(recording)}: ${errorText(answer.data, answer.status)}`, "error");
  await refresh();
}

/** Ask once more before deleting: the file is gone for good. */
function askToDelete(button, recording) {
  const cell = button.closest("td");
  cell.dataset.confirming = "";
  const confirm = el("button", { type: "button", class: "small danger", "aria-label": `Delete ${what(recording)} for good` }, "Delete for good");
  const cancel = el("button", { type: "button", class: "small secondary" }, "Cancel");
  const question = el("span", { class: "muted" }, "Delete the file?");
  const restore = () => {
    cell.replaceChildren(...actions(recording));
    delete cell.dataset.confirming;
    cell.querySelector("button")?.focus();
  };
  cancel.addEventListener("click", restore);
  confirm.addEventListener("click", async () => {
    const answer = await busy(confirm, () => api("DELETE", `${base}/${seg(recording.id)}`));
    delete cell.dataset.confirming;
    if (answer.ok) {
      say(`Deleted ${what(recording)}.`, "ok");
      title.focus(); // its row is going away, and focus with it
    } else {
      say(`Delete ${what(recording)}: ${errorText(answer.data, answer.status)}`, "error");
    }
    await refresh();
  });
  cell.replaceChildren(question, confirm, cancel);
  confirm.focus();
}

form?.addEventListener("submit", async (event) => {
  event.preventDefault();
  clearErrors(form);
  say("");
  const request = startBody();
  const submit = form.querySelector('button[type="submit"]');
  const answer = await busy(submit, () => post(`${base}?wait=${WAIT_S}`, request));
  if (!answer.ok) {
    // The form keeps what was typed, so the one wrong thing can be fixed.
    showFormErrors(form, startErrors(answer.data, answer.status, request.topics), { prefix: "recording" });
    return;
  }
  say(`Recording ${request.topics.join(", ")}.`, "ok");
  await refresh();
});

// The Live topics card (topics.js) says which topics the robot has once it has listed them.
document.addEventListener("robot-topics", (event) => {
  const topics = event.detail?.topics ?? [];
  liveTopics.replaceChildren(
    el("span", { class: "muted" }, "Live topics:"),
    ...topics.map((topic) => {
      const add = el("button", { type: "button", class: "small secondary", "aria-label": `Add ${topic} to the recording` }, topic);
      add.addEventListener("click", () => {
        const chosen = parseTopics(topicsInput.value);
        if (!chosen.includes(topic)) topicsInput.value = [...chosen, topic].join(" ");
        topicsInput.focus();
      });
      return add;
    }),
  );
  liveTopics.hidden = topics.length === 0;
});

if (body) refresh();

// Robot page: the robot's live topics, their types and, on request, their rates.
//
// The page asks for a single-use ticket and opens the robot's rosbridge through the cloud (no new
// port on the robot, the owner's rights only). It lists the graph's topics with /rosapi/topics and
// measures a topic's rate only when asked, by subscribing for a few seconds and counting what
// arrives: the robot never subscribes to every topic, and never for longer than the window.

import { post, seg } from "./api.js";
import { el, errorText, pageData, setText } from "./util.js";

const robotId = pageData("robot-data").id;
const button = document.getElementById("topics-load");
const result = document.getElementById("topics-result");
const table = document.getElementById("topics");
const body = table?.querySelector("tbody");
const WINDOW_MS = 3000;

let socket = null; // the page's one rosbridge connection, opened on demand
let nextId = 0;
const pending = new Map(); // call id -> resolve(service_response)
const counters = new Map(); // topic -> messages heard in the current window

/** Open the robot's rosbridge through the cloud with a fresh ticket (or reuse the open one). */
async function connect() {
  if (socket && socket.readyState === WebSocket.OPEN) return socket;
  const answer = await post(`/api/robot/${seg(robotId)}/bridge-ticket`);
  if (!answer.ok) throw new Error(`No ticket: ${errorText(answer.data, answer.status)}`);
  const ws = new WebSocket(answer.data.rosbridge_url);
  await new Promise((resolve, reject) => {
    ws.addEventListener("open", resolve, { once: true });
    ws.addEventListener("close", (event) => reject(new Error(event.reason || "the robot's rosbridge closed")), { once: true });
  });
  ws.addEventListener("message", (event) => heard(JSON.parse(event.data)));
  ws.addEventListener("close", (event) => {
    socket = null;
    for (const resolve of pending.values()) resolve({ result: false, values: event.reason || "the connection closed" });
    pending.clear();
    if (event.reason) setText(result, event.reason);
  });
  socket = ws;
  return ws;
}

function heard(message) {
  if (message.op === "service_response") {
    pending.get(message.id)?.(message);
    pending.delete(message.id);
  } else if (message.op === "publish" && counters.has(message.topic)) {
    counters.set(message.topic, counters.get(message.topic) + 1);
  } else if (message.op === "status" && message.level === "error") {
    setText(result, message.msg);
  }
}

async function call(service, args = {}) {
  const ws = await connect();
  const id = `topics-${++nextId}`;
  const answer = new Promise((resolve) => pending.set(id, resolve));
  ws.send(JSON.stringify({ op: "call_service", id, service, args }));
  const response = await answer;
  if (!response.result) throw new Error(typeof response.values === "string" ? response.values : `${service} failed`);
  return response.values;
}

/** Subscribe to one topic for a short window and return its messages per second. */
async function measure(topic, type) {
  const ws = await connect();
  const id = `rate-${++nextId}`;
  counters.set(topic, 0);
  ws.send(JSON.stringify({ op: "subscribe", id, topic, type, queue_length: 1000 }));
  await new Promise((resolve) => setTimeout(resolve, WINDOW_MS));
  const count = counters.get(topic);
  counters.delete(topic);
  if (ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify({ op: "unsubscribe", id, topic }));
  return count / (WINDOW_MS / 1000);
}

function row(topic, type) {
  const rate = el("td", { class: "num", text: "—" });
  const measureButton = el("button", { type: "button", class: "secondary small", text: "Measure rate", "aria-label": `Measure the rate of ${topic}` });
  measureButton.addEventListener("click", async () => {
    measureButton.disabled = true;
    setText(rate, "measuring…");
    try {
      const perSecond = await measure(topic, type);
      setText(rate, `${perSecond.toFixed(1)} msg/s`);
    } catch (error) {
      setText(rate, "—");
      setText(result, error.message);
    }
    measureButton.disabled = false;
  });
  return el("tr", { dataset: { topic } }, el("td", {}, el("code", { text: topic })), el("td", {}, el("code", { text: type })), rate, el("td", {}, measureButton));
}

button?.addEventListener("click", async () => {
  button.disabled = true;
  setText(result, "");
  try {
    const { topics, types } = await call("/rosapi/topics");
    const rows = topics.map((topic, index) => [topic, types[index]]).sort(([a], [b]) => a.localeCompare(b));
    body.replaceChildren(...rows.map(([topic, type]) => row(topic, type)));
    table.hidden = false;
    setText(result, `${rows.length} topic${rows.length === 1 ? "" : "s"}`);
    // The Recordings card (recordings.js) offers them for a recording.
    document.dispatchEvent(new CustomEvent("robot-topics", { detail: { topics: rows.map(([topic]) => topic) } }));
  } catch (error) {
    setText(result, error.message);
  }
  button.disabled = false;
});

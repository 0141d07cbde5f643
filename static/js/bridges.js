// Robot page: the rosbridge and Foxglove URLs of this robot, each with a fresh single-use ticket.

import { post, seg } from "./api.js";
import { errorText, fmtTime, pageData, setText } from "./util.js";

const robotId = pageData("robot-data").id;
const button = document.getElementById("bridge-urls");
const result = document.getElementById("bridge-result");
const fields = { rosbridge_url: document.getElementById("bridge-rosbridge"), foxglove_url: document.getElementById("bridge-foxglove") };
const expiry = document.getElementById("bridge-expiry");

button?.addEventListener("click", async () => {
  button.disabled = true;
  setText(result, "");
  const answer = await post(`/api/robot/${seg(robotId)}/bridge-ticket`);
  button.disabled = false;
  if (!answer.ok) {
    setText(result, `No ticket: ${errorText(answer.data, answer.status)}`);
    return;
  }
  for (const [key, input] of Object.entries(fields)) input.value = answer.data[key];
  setText(expiry, `Valid once, until ${fmtTime(Date.parse(answer.data.expires_at) / 1000)}.`);
  document.getElementById("bridge-links").hidden = false;
});

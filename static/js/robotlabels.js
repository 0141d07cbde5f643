// The robot page's labels: chips for everyone, and for an admin of its organization a form that replaces them.

import { api, seg } from "./api.js";
import { labelChips, labelText, parseLabelText } from "./labels.js";
import { errorText, pageData, setText, toast } from "./util.js";

const robot = pageData("robot-data");
const chips = document.getElementById("robot-labels");
const form = document.getElementById("labels-form");

function showLabels(labels) {
  const items = labelChips(labels);
  chips.replaceChildren(...(items.length ? items : [Object.assign(document.createElement("li"), { className: "muted", textContent: "none" })]));
}

if (form) {
  const input = form.elements.labels;
  const result = document.getElementById("labels-result");
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    result.className = "result";
    const parsed = parseLabelText(input.value);
    if (parsed.error) {
      result.className = "result error";
      setText(result, parsed.error);
      input.setAttribute("aria-invalid", "true");
      return;
    }
    const answer = await api("PATCH", `/api/robot/${seg(robot.id)}`, { labels: parsed.labels });
    if (!answer.ok) {
      result.className = "result error";
      setText(result, errorText(answer.data, answer.status));
      input.setAttribute("aria-invalid", "true");
      return;
    }
    input.removeAttribute("aria-invalid");
    robot.labels = answer.data.labels;
    showLabels(robot.labels);
    input.value = input.defaultValue = labelText(robot.labels);
    result.className = "result ok";
    setText(result, "Labels saved.");
    toast(`Labels of ${robot.id} saved.`, "ok");
  });
}

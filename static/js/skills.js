// Skill catalog: add templates to robots; upload a Skill config, see its errors at each field, use it.

import { api, post, seg } from "./api.js";
import { NON_FIELD, configErrors, parseJson, renderOutline } from "./forms.js";
import { el, errorText, toast } from "./util.js";

function say(node, text, kind, link) {
  node.className = `result ${kind}`;
  node.replaceChildren(text, ...(link ? [" ", el("a", { href: link.href }, link.text)] : []));
}

async function addSkill(robotId, body, resultNode) {
  const answer = await post(`/api/robot/${seg(robotId)}/skill/add`, body);
  if (answer.status === 201) {
    const text = `Added ${answer.data.skill_id} to ${robotId}.`;
    say(resultNode, text, "ok", { href: `/robots/${seg(robotId)}/`, text: "Open the robot" });
    toast(text, "ok");
  } else {
    say(resultNode, errorText(answer.data, answer.status), "error");
  }
  return answer;
}

// --------------------------------------------------------------------------- templates

for (const form of document.querySelectorAll("form[data-add-template]")) {
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    const button = form.querySelector("button");
    button.disabled = true;
    await addSkill(form.elements.robot.value, { template: Number(form.dataset.addTemplate) }, form.querySelector(".result"));
    button.disabled = false;
  });
}

// --------------------------------------------------------------------------- upload

const uploadForm = document.getElementById("upload-form");
const fileInput = document.getElementById("upload-file");
const textInput = document.getElementById("upload-text");
const result = document.getElementById("upload-result");
const report = document.getElementById("upload-report");
const actions = document.getElementById("upload-actions");
let checked = null; // the normalised config once it passed the schema

function showErrors(config, errors) {
  checked = null;
  actions.hidden = true;
  const count = Object.values(errors).reduce((n, list) => n + list.length, 0);
  say(result, `${count} problem${count === 1 ? "" : "s"}: see each field below.`, "error");
  renderOutline(report, config, errors, { prefix: "upload" });
}

async function check() {
  const text = textInput.value.trim();
  if (!text) {
    say(result, "Choose a file or paste a config first.", "error");
    return;
  }
  const parsed = parseJson(text);
  if (parsed.error) {
    showErrors(null, { [NON_FIELD]: [parsed.error] });
    return;
  }
  say(result, "Checking…", "");
  const answer = await api("POST", "/validate/skill-config", parsed.value);
  if (!answer.ok || !answer.data.valid) {
    showErrors(parsed.value, answer.data?.errors ?? { [NON_FIELD]: [errorText(answer.data, answer.status)] });
    return;
  }
  checked = answer.data.config;
  const components = Object.entries(checked.components);
  say(result, `Valid: ${checked.skill} (${checked.skill_id}) with ${components.length} component${components.length === 1 ? "" : "s"}.`, "ok");
  report.replaceChildren(
    el(
      "div",
      { class: "ok-summary" },
      el("strong", {}, "The config matches the schema. "),
      components.map(([id, c]) => el("span", { class: `badge loc-${c.location === "either" ? "none" : c.location}` }, `${id} · ${c.location}`)),
    ),
  );
  actions.hidden = false;
  const name = document.querySelector("#upload-save [name=name]");
  if (name && !name.value) name.value = checked.skill;
}

uploadForm.addEventListener("submit", (event) => {
  event.preventDefault();
  check();
});

fileInput.addEventListener("change", async () => {
  const file = fileInput.files[0];
  if (!file) return;
  if (file.size > 1_048_576) {
    say(result, "The file is larger than 1 MiB, the most the cloud accepts.", "error");
    return;
  }
  textInput.value = await file.text();
  // Choosing the same file again (after fixing it) must be read again.
  fileInput.value = "";
  check();
});

textInput.addEventListener("input", () => {
  checked = null;
  actions.hidden = true;
});

/** Answers about a config (400 with {"config": ["path: message"]}) go back onto the outline. */
function configAnswer(answer, resultNode) {
  if (answer.status === 400 && Array.isArray(answer.data?.config)) {
    showErrors(parseJson(textInput.value).value ?? null, configErrors(answer.data.config));
    say(resultNode, "The cloud refused the config: see the fields above.", "error");
    return true;
  }
  return false;
}

document.getElementById("upload-add")?.addEventListener("submit", async (event) => {
  event.preventDefault();
  const form = event.currentTarget;
  if (!checked) return;
  const answer = await addSkill(form.elements.robot.value, { config: checked }, form.querySelector(".result"));
  configAnswer(answer, form.querySelector(".result"));
});

document.getElementById("upload-save")?.addEventListener("submit", async (event) => {
  event.preventDefault();
  const form = event.currentTarget;
  const node = form.querySelector(".result");
  if (!checked) return;
  const tags = form.elements.tags.value.split(",").map((t) => t.trim()).filter(Boolean);
  const organization = form.elements.organization.value;
  const answer = await post("/api/templates", {
    // Empty: the cloud's catalog, which only staff keep.
    ...(organization ? { organization } : {}),
    name: form.elements.name.value.trim(),
    description: form.elements.description.value.trim(),
    tags,
    config: checked,
  });
  if (answer.status === 201) {
    say(node, `Saved "${answer.data.name}" to the catalog.`, "ok", { href: location.pathname, text: "Show it" });
    toast(`Saved "${answer.data.name}" to the catalog.`, "ok");
  } else if (!configAnswer(answer, node)) {
    say(node, errorText(answer.data, answer.status), "error");
  }
});

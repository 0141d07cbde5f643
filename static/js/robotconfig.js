// Robot page: the configuration form (typed fields plus the advanced part as JSON), checked, then saved.

import { api } from "./api.js";
import { clearErrors, configErrors, parseJson, showFormErrors } from "./forms.js";
import { errorText, setText, toast } from "./util.js";

const ADVANCED_KEYS = ["energy", "costs", "subnets"];

/** Wire the robot page's config form; onSaved runs once the robot's new config is stored. */
export function setupConfigForm(robot, live, onSaved) {
  const robotId = robot.id;
  const form = document.getElementById("config-form");
  const advanced = document.getElementById("config-advanced");
  const configResult = document.getElementById("config-result");

  function fillAdvanced() {
    const part = Object.fromEntries(ADVANCED_KEYS.filter((k) => k in robot.config).map((k) => [k, robot.config[k]]));
    advanced.value = JSON.stringify(part, null, 2);
    advanced.defaultValue = advanced.value;
  }

  function setPath(target, path, value) {
    const parts = path.split(".");
    let node = target;
    for (const part of parts.slice(0, -1)) {
      if (typeof node[part] !== "object" || node[part] === null) node[part] = {};
      node = node[part];
    }
    node[parts.at(-1)] = value;
  }

  /** Build the config the form describes; null (with the error shown) when the JSON part is broken. */
  function formConfig() {
    const config = structuredClone(robot.config);
    for (const input of form.querySelectorAll("[data-path]:not(textarea)")) {
      let value = input.value;
      if (input.type === "number") {
        value = value.trim() === "" ? (input.hasAttribute("data-optional") ? null : "") : Number(value);
      }
      setPath(config, input.dataset.path, value);
    }
    const parsed = parseJson(advanced.value || "{}");
    if (parsed.error) return { errors: { "*": [parsed.error] } };
    if (typeof parsed.value !== "object" || parsed.value === null || Array.isArray(parsed.value)) {
      return { errors: { "*": ["must be a JSON object such as {\"energy\": {…}}"] } };
    }
    Object.assign(config, parsed.value);
    return { config };
  }

  async function saveConfig(event) {
    event.preventDefault();
    clearErrors(form);
    setText(configResult, "");
    const built = formConfig();
    if (built.errors) {
      advanced.closest("details").open = true;
      showFormErrors(form, built.errors, { prefix: "config" });
      return;
    }
    const checked = await api("POST", "/validate/robot-config", built.config);
    if (!checked.ok || !checked.data.valid) {
      const errors = checked.data?.errors ?? { __all__: [errorText(checked.data, checked.status)] };
      if (Object.keys(errors).some((path) => ADVANCED_KEYS.includes(path.split(".")[0]))) advanced.closest("details").open = true;
      showFormErrors(form, errors, { prefix: "config" });
      return;
    }
    const config = checked.data.config;
    const changes = Object.fromEntries(
      Object.entries(config).filter(([key, value]) => JSON.stringify(value) !== JSON.stringify(robot.config[key] ?? null)),
    );
    if (!Object.keys(changes).length) {
      setText(configResult, "Nothing changed.");
      return;
    }
    try {
      await live.request("robot_config_update", { robot: robotId, changes });
    } catch (error) {
      const errors = error.field === "data.config" ? configErrors(error.message.split("; ")) : { __all__: [error.message] };
      showFormErrors(form, errors, { prefix: "config" });
      return;
    }
    robot.config = config;
    onSaved();
    fillAdvanced();
    for (const input of form.querySelectorAll("input[data-path]")) input.defaultValue = input.value;
    for (const select of form.querySelectorAll("select")) for (const option of select.options) option.defaultSelected = option.selected;
    const text = robot.connected ? "Saved; the robot received it." : "Saved; the robot receives it when it reconnects.";
    configResult.className = "result ok";
    setText(configResult, text);
    toast(`Configuration of ${robotId}: ${text}`, "ok");
  }

  form.addEventListener("submit", saveConfig);
  form.addEventListener("reset", () => {
    clearErrors(form);
    setText(configResult, "");
  });

  fillAdvanced();
}

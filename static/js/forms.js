// Field errors from the shared config schemas, shown where the field is: on form inputs, or
// inline in an outline of an uploaded config. Paths are dotted (components.detector.resources.cpu).

import { el } from "./util.js";

export const NON_FIELD = "__all__";
const PATH_PREFIX = /^([A-Za-z0-9_.\-[\]]+): (.+)$/s;

/** Turn the API's ["path: message", ...] list (a config's 400 answer) into {path: [messages]}. */
export function configErrors(messages) {
  const errors = {};
  for (const message of messages ?? []) {
    const match = PATH_PREFIX.exec(message);
    const [path, text] = match ? [match[1], match[2]] : [NON_FIELD, message];
    (errors[path] ??= []).push(text);
  }
  return errors;
}

/** Parse JSON text, saying where it breaks (line and column) when it does. */
export function parseJson(text) {
  try {
    return { value: JSON.parse(text) };
  } catch (error) {
    const at = /position (\d+)/.exec(error.message);
    if (at) {
      const before = text.slice(0, Number(at[1]));
      const line = before.split("\n").length;
      const column = Number(at[1]) - before.lastIndexOf("\n");
      return { error: `not valid JSON at line ${line}, column ${column}: ${error.message}` };
    }
    return { error: `not valid JSON: ${error.message}` };
  }
}

export const fieldId = (prefix, path) => `${prefix}-${path.replace(/[^A-Za-z0-9_-]/g, "_")}`;

/** Remove every error message and invalid mark a previous check left in a container. */
export function clearErrors(container) {
  for (const node of container.querySelectorAll(".field-error, .error-summary, .ok-summary")) node.remove();
  for (const node of container.querySelectorAll("[aria-invalid]")) {
    node.removeAttribute("aria-invalid");
    node.removeAttribute("aria-describedby");
  }
}

/** Build the box that lists every problem, each linking to its field. */
export function errorSummary(errors, hrefFor) {
  const paths = Object.keys(errors);
  const count = paths.reduce((n, path) => n + errors[path].length, 0);
  const items = [];
  for (const path of paths) {
    for (const message of errors[path]) {
      const label = path === NON_FIELD ? message : `${path}: ${message}`;
      const href = path === NON_FIELD ? null : hrefFor(path);
      items.push(el("li", {}, href ? el("a", { href }, label) : label));
    }
  }
  return el(
    "div",
    { class: "error-summary", role: "alert", tabindex: "-1" },
    el("h3", {}, count === 1 ? "1 problem to fix" : `${count} problems to fix`),
    el("ul", {}, items),
  );
}

/**
 * Mark the form inputs whose data-path matches an error; errors under a path no input has go
 * to the input of the nearest enclosing path (e.g. a JSON textarea), naming the full path.
 */
export function showFormErrors(form, errors, { prefix }) {
  clearErrors(form);
  const inputs = new Map([...form.querySelectorAll("[data-path]")].map((input) => [input.dataset.path, input]));
  const placed = {};
  for (const [path, messages] of Object.entries(errors)) {
    let input = inputs.get(path);
    let label = "";
    if (!input) {
      const parts = path.split(".");
      while (parts.length && !input) {
        parts.pop();
        input = inputs.get(parts.join(".")) ?? (parts.length ? undefined : inputs.get("*"));
      }
      label = `${path}: `;
    }
    if (!input || path === NON_FIELD) continue;
    (placed[input.dataset.path] ??= { input, lines: [] }).lines.push(...messages.map((m) => label + m));
  }
  for (const { input, lines } of Object.values(placed)) {
    const id = fieldId(prefix, input.dataset.path);
    input.setAttribute("aria-invalid", "true");
    input.setAttribute("aria-describedby", id);
    input.id ||= `${id}-input`;
    input.after(el("p", { class: "field-error", id }, lines.join(" · ")));
  }
  const summary = errorSummary(errors, (path) => {
    const input = inputs.get(path);
    return input ? `#${input.id}` : null;
  });
  form.prepend(summary);
  summary.focus();
}

// --------------------------------------------------------------------------- the outline of an uploaded config

function scalar(value) {
  return value === null ? "null" : typeof value === "string" ? JSON.stringify(value) : String(value);
}

/**
 * Render a config as a tree of its fields, with each error written under the field it names.
 * Branches holding an error are open, the rest folded; a missing field is shown where it
 * should be, under its parent.
 */
export function renderOutline(container, config, errors, { prefix = "cfg" } = {}) {
  const paths = Object.keys(errors).filter((path) => path !== NON_FIELD);
  const holdsError = (path) => paths.some((p) => p === path || p.startsWith(`${path}.`));
  const nodes = new Map(); // path -> li
  const build = (value, path) => {
    const list = el("ul", {});
    const entries = Array.isArray(value) ? value.map((v, i) => [String(i), v]) : Object.entries(value);
    for (const [key, child] of entries) {
      const childPath = path ? `${path}.${key}` : key;
      const label = [el("span", { class: "key" }, key), ": "];
      let item;
      if (child !== null && typeof child === "object") {
        const size = Array.isArray(child) ? `[${child.length}]` : `{${Object.keys(child).length}}`;
        item = el(
          "li",
          { id: fieldId(prefix, childPath), dataset: { path: childPath } },
          el("details", { open: holdsError(childPath) }, el("summary", {}, label, el("span", { class: "val muted" }, size)), build(child, childPath)),
        );
      } else {
        item = el("li", { id: fieldId(prefix, childPath), dataset: { path: childPath } }, label, el("span", { class: "val" }, scalar(child)));
      }
      nodes.set(childPath, item);
      list.append(item);
    }
    return list;
  };
  const root = config !== null && typeof config === "object" ? build(config, "") : el("ul", {});
  for (const path of paths) {
    let item = nodes.get(path);
    if (!item) {
      // A missing field: add it under the nearest parent that exists, marked missing.
      const parts = path.split(".");
      const missing = [];
      while (parts.length && !nodes.has(parts.join("."))) missing.unshift(parts.pop());
      const parent = parts.length ? nodes.get(parts.join(".")) : null;
      const parentList = parent ? parent.querySelector(":scope > details > ul") : root;
      item = el(
        "li",
        { id: fieldId(prefix, path), class: "missing", dataset: { path } },
        el("span", { class: "key" }, missing.join(".")),
        ": ",
        el("span", { class: "val" }, "missing"),
      );
      (parentList ?? root).append(item);
      nodes.set(path, item);
    }
    item.classList.add("invalid");
    const id = `${item.id}-error`;
    item.setAttribute("aria-describedby", id);
    const message = el("p", { class: "field-error", id }, errors[path].join(" · "));
    const summary = item.querySelector(":scope > details > summary");
    if (summary) summary.after(message);
    else item.append(message);
  }
  const summary = Object.keys(errors).length ? errorSummary(errors, (path) => `#${fieldId(prefix, path)}`) : null;
  container.replaceChildren(
    ...(summary ? [summary] : []),
    el("div", { class: "outline", tabindex: "0", role: "region", "aria-label": "The uploaded config, field by field" }, root),
  );
  summary?.focus();
}

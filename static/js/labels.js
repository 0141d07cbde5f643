// Robot labels on the dashboard: their chips, and the `k=v,k2=v2` text the forms and the fleet's search take.

import { el } from "./util.js";

const sorted = (labels) => Object.entries(labels ?? {}).sort(([a], [b]) => (a < b ? -1 : a > b ? 1 : 0));

/** Write labels as `k=v,k2=v2`, keys in order. */
export function labelText(labels) {
  return sorted(labels)
    .map(([key, value]) => `${key}=${value}`)
    .join(",");
}

/** Build one chip per label, keys in order. */
export function labelChips(labels, tag = "li") {
  return sorted(labels).map(([key, value]) => el(tag, { class: "chip", dataset: { label: key } }, `${key}=${value}`));
}

/** Split `k=v,k2=v2` into labels ({labels} or {error}); the cloud checks the rules of keys and values. */
export function parseLabelText(text) {
  const labels = {};
  if (!text.trim()) return { labels };
  for (const term of text.split(",").map((part) => part.trim())) {
    const at = term.indexOf("=");
    if (at < 0) return { error: `label ${JSON.stringify(term)} has no '=': write key=value` };
    labels[term.slice(0, at).trim()] = term.slice(at + 1).trim();
  }
  return { labels };
}

// The Robot API over the browser's session: JSON in, {ok, status, data} out, never a throw for HTTP errors.

import { csrfToken } from "./util.js";

/** Call the API; POST, PATCH and DELETE carry the CSRF token DRF's SessionAuthentication asks for. */
export async function api(method, url, body) {
  const headers = { Accept: "application/json" };
  const init = { method, headers, credentials: "same-origin" };
  if (method !== "GET" && method !== "HEAD") headers["X-CSRFToken"] = csrfToken();
  if (body !== undefined) {
    headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  let response;
  try {
    response = await fetch(url, init);
  } catch (error) {
    return { ok: false, status: 0, data: { detail: `The cloud did not answer (${error.message}).` } };
  }
  if (response.redirected && new URL(response.url).pathname.startsWith("/accounts/login/")) {
    // The session expired: a page reload takes the operator to the login form.
    return { ok: false, status: 401, data: { detail: "Your session expired; reload the page to log in again." } };
  }
  let data = null;
  const type = response.headers.get("content-type") ?? "";
  if (response.status !== 204) {
    data = type.includes("json") ? await response.json().catch(() => null) : { detail: `HTTP ${response.status}` };
  }
  return { ok: response.ok, status: response.status, data };
}

export const get = (url) => api("GET", url);
export const post = (url, body) => api("POST", url, body ?? {});

/** Encode a path segment (ids are slugs, but never trust that in a URL). */
export const seg = encodeURIComponent;

// REST access by the session cookie (HttpOnly: the page never holds the key); writes carry
// the session's CSRF token; a 401 anywhere logs the user out.

const BASE = "/api/v1";
let csrfToken = null;

/** The CSRF token of the current session (from POST or GET /session), kept in memory only. */
export function setCsrf(token) {
  csrfToken = token;
}

export class ApiError extends Error {
  constructor(status, body) {
    super(body?.detail || `HTTP ${status}`);
    this.status = status;
    this.type = body?.type;
    this.body = body;
  }
}

let onUnauthorized = () => {};
export function setUnauthorizedHandler(fn) {
  onUnauthorized = fn;
}

/** Call the API; JSON in and out unless `text` is set. Throws ApiError on a non-2xx answer.
 * `quiet` skips the logout on a 401 (the login calls themselves). */
export async function api(path, { method = "GET", body, text = false, quiet = false } = {}) {
  const headers = {};
  if (body !== undefined) headers["Content-Type"] = "application/json";
  if (method !== "GET" && method !== "HEAD" && csrfToken) headers["X-CSRF-Token"] = csrfToken;
  const r = await fetch(BASE + path, {
    method,
    headers,
    credentials: "same-origin",
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  if (!r.ok) {
    const err = new ApiError(r.status, await r.json().catch(() => ({ detail: r.statusText })));
    if (r.status === 401 && !quiet) onUnauthorized(err);
    throw err;
  }
  if (r.status === 204) return null;
  return text ? r.text() : r.json();
}

/** Whether the API has an endpoint (used to reveal features as the API grows). */
export async function hasEndpoint(path) {
  try {
    const r = await fetch(BASE + path, { credentials: "same-origin" });
    return r.status !== 404 && r.status !== 405;
  } catch {
    return false;
  }
}

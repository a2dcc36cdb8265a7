// REST access: every call carries the stored key; a 401 anywhere logs the user out.

const KEY_STORE = "eqgw.key";
const BASE = "/api/v1";

export function getKey() {
  return localStorage.getItem(KEY_STORE);
}

export function setKey(key) {
  localStorage.setItem(KEY_STORE, key);
}

export function forgetKey() {
  localStorage.removeItem(KEY_STORE);
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

/** Call the API; JSON in and out unless `text` is set. Throws ApiError on a non-2xx answer. */
export async function api(path, { method = "GET", body, key = getKey(), text = false } = {}) {
  const headers = { Authorization: `Bearer ${key}` };
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const r = await fetch(BASE + path, {
    method,
    headers,
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  if (!r.ok) {
    const err = new ApiError(r.status, await r.json().catch(() => ({ detail: r.statusText })));
    if (r.status === 401) onUnauthorized(err);
    throw err;
  }
  return text ? r.text() : r.json();
}

/** Whether the API has an endpoint (used to reveal features as the API grows). */
export async function hasEndpoint(path) {
  try {
    const r = await fetch(BASE + path, { headers: { Authorization: `Bearer ${getKey()}` } });
    return r.status !== 404 && r.status !== 405;
  } catch {
    return false;
  }
}

// The dashboard's entry: login, the header (who, live connection), and the hash router.

import { api, hasEndpoint, setCsrf, setUnauthorizedHandler } from "./api.js";
import { esc } from "./format.js";
import { LiveConnection } from "./live.js";
import { renderAlerts } from "./alerts.js";
import { renderOverview } from "./overview.js";
import { applyMessage, loadAlerts, loadFleet } from "./store.js";
import { renderVehicle } from "./vehicle.js";

const main = document.getElementById("main");
const topbar = document.querySelector(".topbar");
const conn = document.getElementById("conn");
const banner = document.getElementById("conn-banner");

export const session = { me: null, live: null, features: { alerts: false } };
let cleanup = null;
let bannerTimer = null;
let alertsTimer = null;
const ALERTS_REFRESH_MS = 30_000; // besides the websocket: catches up after a reconnect

function showLogin(message = "") {
  stopSession();
  topbar.hidden = true;
  banner.hidden = true;
  main.innerHTML = `
    <section class="login">
      <h1>eqgw depot dashboard</h1>
      <p>Log in with an API key, or open a login link: <code>eqgw serve</code> prints one on its
      first start, <code>eqgw keys login-link ID</code> makes another. An admin makes more keys
      with <code>eqgw keys create</code>.</p>
      <form id="login-form">
        <label for="login-key">API key</label>
        <input id="login-key" name="key" type="password" autocomplete="current-password"
               required spellcheck="false" placeholder="eqgw_…">
        <button class="btn btn-primary" type="submit">Log in</button>
        <p class="error" id="login-error" role="alert">${esc(message)}</p>
      </form>
      <div class="sso" id="sso" hidden>
        <p>Depot staff: sign in with your organisation's account.</p>
        <a class="btn btn-primary" id="sso-login" href="/auth/oidc/login">Sign in with SSO</a>
      </div>
    </section>`;
  const form = document.getElementById("login-form");
  const input = document.getElementById("login-key");
  input.focus();
  offerSso();
  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const key = input.value.trim();
    input.value = "";
    try {
      // The key is exchanged for an HttpOnly session cookie; the page keeps none of it.
      await api("/session", { method: "POST", body: { key }, quiet: true });
    } catch (err) {
      document.getElementById("login-error").textContent =
        err.status === 401 ? "That key is unknown or revoked." : `Cannot log in: ${err.message}`;
      return;
    }
    start();
  });
}

// Single sign-on, when the gateway has it (GET /auth/oidc answers 404 otherwise): a link to
// /auth/oidc/login, which goes to the identity provider and comes back with a session cookie.
async function offerSso() {
  let sso;
  try {
    const r = await fetch("/auth/oidc", { credentials: "same-origin" });
    if (!r.ok) return;
    sso = await r.json();
  } catch {
    return;
  }
  const box = document.getElementById("sso");
  if (!box) return;
  const link = document.getElementById("sso-login");
  link.textContent = sso.label;
  link.href = sso.login_url;
  box.hidden = false;
}

// A login link: /#login=CODE, a one-time code (never a key) in the fragment, which no server,
// proxy or Referer sees. The page takes it out of the address at once, says whose key it
// logs in as, and uses it only when asked: a link another site made cannot log anyone in
// unnoticed (and the server refuses a login another site's page sends).
const LOGIN_FRAGMENT = /^#login=([A-Za-z0-9_-]{1,200})$/;

function takeLoginCode() {
  const m = LOGIN_FRAGMENT.exec(location.hash);
  if (!m) return null;
  history.replaceState(null, "", location.pathname + location.search);
  return m[1];
}

async function confirmLoginCode(code) {
  let who;
  try {
    who = await api("/session/code", { method: "POST", body: { code }, quiet: true });
  } catch (err) {
    return showLogin(
      err.status === 401
        ? "That login link is used up or expired: ask for a new one (eqgw keys login-link)."
        : `Cannot log in: ${err.message}`,
    );
  }
  let current = null;
  try {
    current = await api("/session", { quiet: true });
  } catch {
    current = null;
  }
  stopSession();
  topbar.hidden = true;
  banner.hidden = true;
  const scope = who.scope
    ? [...who.scope.groups.map((g) => `depot ${g}`), ...who.scope.vehicles].join(", ")
    : "the whole fleet";
  main.innerHTML = `
    <section class="login" id="code-login">
      <h1>eqgw depot dashboard</h1>
      <p>This login link signs you in as <strong id="code-name">${esc(who.name)}</strong>
      (${esc(who.role)}, ${esc(scope)}).</p>
      ${
        current
          ? `<p>You are signed in as <strong>${esc(current.name)}</strong>
             (${esc(current.role)}); that session ends if you continue.</p>`
          : ""
      }
      <p>Continue only if you asked for this link yourself.</p>
      <div class="dialog-buttons">
        <button type="button" class="btn btn-quiet" id="code-cancel">Cancel</button>
        <button type="button" class="btn btn-primary" id="code-ok">Sign in</button>
      </div>
      <p class="error" id="login-error" role="alert"></p>
    </section>`;
  document.getElementById("code-cancel").addEventListener("click", () => start());
  const ok = document.getElementById("code-ok");
  ok.focus();
  ok.addEventListener("click", async () => {
    ok.disabled = true;
    try {
      if (current) {
        setCsrf(current.csrf_token);
        await api("/session", { method: "DELETE", quiet: true }).catch(() => {});
        setCsrf(null);
      }
      await api("/session", { method: "POST", body: { code }, quiet: true });
    } catch (err) {
      ok.disabled = false;
      document.getElementById("login-error").textContent =
        err.status === 401
          ? "That login link is used up or expired: ask for a new one."
          : `Cannot log in: ${err.message}`;
      return;
    }
    start();
  });
}

function stopSession() {
  if (cleanup) cleanup();
  cleanup = null;
  if (session.live) session.live.stop();
  session.live = null;
  clearInterval(alertsTimer);
  session.me = null;
}

async function logout(message) {
  // Ends the session on the server too (a copied cookie is then worth nothing).
  if (session.me) await api("/session", { method: "DELETE", quiet: true }).catch(() => {});
  setCsrf(null);
  showLogin(message);
}

function setConnState(state, info) {
  conn.dataset.state = state;
  clearInterval(bannerTimer);
  const text = conn.querySelector(".conn-text");
  if (state === "live") {
    text.textContent = "Live";
    banner.hidden = true;
    return;
  }
  if (state === "connecting") {
    text.textContent = "Connecting…";
    return;
  }
  text.textContent = "Offline";
  const draw = () => {
    const s = Math.max(0, Math.ceil((info.retryAt - Date.now()) / 1000));
    banner.innerHTML = `<strong>Live connection lost.</strong> Values shown may be out of date.
      Reconnecting in ${s} s… <button type="button" class="btn btn-small" id="retry-now">
      Retry now</button>`;
    banner.querySelector("#retry-now").addEventListener("click", () => session.live.retryNow());
  };
  banner.hidden = false;
  draw();
  bannerTimer = setInterval(() => {
    if (document.activeElement?.id !== "retry-now") draw();
  }, 1000);
}

function route() {
  if (cleanup) cleanup();
  cleanup = null;
  const hash = location.hash.replace(/^#/, "") || "/";
  const parts = hash.split("/").filter(Boolean).map(decodeURIComponent);
  for (const a of document.querySelectorAll("[data-nav]")) {
    const active = (parts[0] || "fleet") === a.dataset.nav;
    if (active) a.setAttribute("aria-current", "page");
    else a.removeAttribute("aria-current");
  }
  if (parts[0] === "vehicle" && parts[1]) {
    cleanup = renderVehicle(main, parts[1], session);
  } else if (parts[0] === "alerts" && session.features.alerts) {
    cleanup = renderAlerts(main, session);
  } else {
    cleanup = renderOverview(main, session);
  }
}

async function start() {
  stopSession();
  let me;
  try {
    me = await api("/session", { quiet: true });
  } catch (err) {
    if (err.status === 401) return showLogin();
    main.innerHTML = `<p class="error">Cannot reach the gateway: ${esc(err.message)}</p>`;
    return;
  }
  setCsrf(me.csrf_token);
  session.me = me;
  document.body.dataset.role = me.role;
  document.getElementById("who").textContent = `${me.name} · ${me.role}`;
  topbar.hidden = false;
  session.features.alerts = await hasEndpoint("/alerts");
  document.getElementById("nav-alerts").hidden = !session.features.alerts;
  try {
    await loadFleet();
    if (session.features.alerts) await loadAlerts();
  } catch (err) {
    if (err.status === 401) return;
  }
  if (session.features.alerts) {
    alertsTimer = setInterval(() => loadAlerts().catch(() => {}), ALERTS_REFRESH_MS);
  }
  session.live = new LiveConnection({
    onMessage: applyMessage,
    onState: setConnState,
    onUnauthorized: () => logout("Your session ended or your key was revoked; log in again."),
  });
  session.live.start();
  route();
}

setUnauthorizedHandler(() => logout("Your key is unknown or was revoked; log in again."));
document.getElementById("logout").addEventListener("click", () => logout());
window.addEventListener("hashchange", () => {
  const code = takeLoginCode();
  if (code) {
    confirmLoginCode(code);
    return;
  }
  if (session.me) {
    route();
    main.focus({ preventScroll: true });
  }
});

// A login link's code is asked about first; else whether there is a session is asked of the
// server.
const code = takeLoginCode();
if (code) confirmLoginCode(code);
else start();

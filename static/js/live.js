// The websocket: one connection for the whole page, reconnecting by itself with backoff.
// Listeners get every message; the state ("connecting", "live", "lost") drives the banner.

const MIN_DELAY_S = 1;
const MAX_DELAY_S = 30;
const CLOSE_UNAUTHORIZED = 4401;

export class LiveConnection {
  constructor({ onMessage, onState, onUnauthorized }) {
    this.onMessage = onMessage;
    this.onState = onState;
    this.onUnauthorized = onUnauthorized;
    this.attempt = 0;
    this.ws = null;
    this.timer = null;
    this.stopped = false;
    this.retryAt = null;
  }

  start() {
    this.stopped = false;
    this.connect();
  }

  stop() {
    this.stopped = true;
    clearTimeout(this.timer);
    if (this.ws) this.ws.close(1000, "logged out");
    this.ws = null;
  }

  /** Retry at once (the user asked), skipping what is left of the backoff. */
  retryNow() {
    if (this.ws || this.stopped) return;
    clearTimeout(this.timer);
    this.connect();
  }

  connect() {
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    // Authenticated by the session cookie the browser sends with the handshake. Protocol 2:
    // each value as what changed (the store merges it).
    const url = `${proto}//${location.host}/api/v1/ws?v=2`;
    this.onState("connecting", { attempt: this.attempt });
    let ws;
    try {
      ws = new WebSocket(url);
    } catch {
      this.scheduleRetry();
      return;
    }
    this.ws = ws;
    ws.onmessage = (ev) => {
      let msg;
      try {
        msg = JSON.parse(ev.data);
      } catch {
        return;
      }
      if (msg.type === "snapshot" && this.attempt !== 0) this.attempt = 0;
      if (msg.type === "snapshot") this.onState("live", {});
      this.onMessage(msg);
    };
    ws.onopen = () => {
      this.onState("live", {});
    };
    ws.onclose = (ev) => {
      if (this.ws !== ws) return;
      this.ws = null;
      if (this.stopped) return;
      if (ev.code === CLOSE_UNAUTHORIZED) {
        this.onUnauthorized();
        return;
      }
      this.scheduleRetry(ev.reason);
    };
  }

  scheduleRetry(reason) {
    // Exponential backoff with jitter, so a depot full of tablets does not reconnect in step.
    const base = Math.min(MAX_DELAY_S, MIN_DELAY_S * 2 ** this.attempt);
    const delay = base * (0.75 + Math.random() * 0.5);
    this.attempt += 1;
    this.retryAt = Date.now() + delay * 1000;
    this.onState("lost", { retryAt: this.retryAt, reason });
    this.timer = setTimeout(() => this.connect(), delay * 1000);
  }
}

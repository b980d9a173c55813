// The page's one websocket to the game server, with reconnect and exponential backoff.
//
// States: "connecting" (first attempt), "open" (welcome received), "reconnecting" (waiting
// out a backoff delay: `retryIn` seconds), "offline" (the browser says it has no network;
// it retries when the network comes back). A server restart is survived: the delay goes
// 0.5, 1, 2, 4, 8 s, then stays at 10 s (each +-20%), and resets after a welcome.
//
// A `redirect` reply (the room lives on another server process or host; docs/protocol.md)
// moves the connection to the address it names: the request's promise resolves with the
// redirect, and the new connection's welcome lets the page send it again there. A lost
// connection retries at the page's own address (the process that had the room may be gone);
// when the lost one was such a move, `onHostGone(url)` tells the page first.

import { decodeJson, hello } from "./protocol.js";

export const BACKOFF = { first: 0.5, factor: 2, max: 10, jitter: 0.2 };

export function backoffDelay(attempt, rand = Math.random) {
  const base = Math.min(BACKOFF.max, BACKOFF.first * BACKOFF.factor ** Math.max(0, attempt - 1));
  return base * (1 + BACKOFF.jitter * (2 * rand() - 1));
}

export class Connection {
  /**
   * url: the websocket URL. handlers: onState(state, detail), onWelcome(msg), onJson(msg),
   * onBinary(ArrayBuffer). `name` goes in the hello.
   */
  constructor(url, handlers, name = "spectator") {
    this.url = url;
    this.home = url;
    this.h = handlers;
    this.name = name;
    this.ws = null;
    this.state = "idle";
    this.attempt = 0;
    this.retryAt = 0;
    this._timer = 0;
    this._countdown = 0;
    this._nextId = 1;
    this._pending = new Map();
    this._stopped = false;
    window.addEventListener("online", () => { if (this.state !== "open") this._connectNow(); });
    window.addEventListener("offline", () => this._setState("offline"));
  }

  start() { this._stopped = false; this._connect(); }

  stop() {
    this._stopped = true;
    clearTimeout(this._timer);
    clearInterval(this._countdown);
    if (this.ws) this.ws.close(1000, "bye");
  }

  _setState(state, detail = {}) {
    this.state = state;
    if (this.h.onState) this.h.onState(state, detail);
  }

  _connectNow() {
    clearTimeout(this._timer);
    clearInterval(this._countdown);
    this._connect();
  }

  _connect() {
    if (this._stopped) return;
    this._setState(this.attempt === 0 ? "connecting" : "reconnecting", { attempt: this.attempt, retryIn: 0 });
    let ws;
    try {
      ws = new WebSocket(this.url);
    } catch (e) {
      this._scheduleRetry();
      return;
    }
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    ws.onopen = () => ws.send(hello({ name: this.name, role: "lobby" }));
    ws.onmessage = (ev) => {
      if (typeof ev.data !== "string") {
        if (this.h.onBinary) this.h.onBinary(ev.data);
        return;
      }
      let msg;
      try { msg = decodeJson(ev.data); } catch (e) { console.warn("bad message from server", e); return; }
      if (msg.type === "welcome") {
        this.attempt = 0;
        this._setState("open");
        if (this.h.onWelcome) this.h.onWelcome(msg);
        return;
      }
      if (msg.re !== undefined && this._pending.has(msg.re)) {
        const { resolve } = this._pending.get(msg.re);
        this._pending.delete(msg.re);
        resolve(msg);
        if (msg.type === "redirect") this.moveTo(msg.url);
        return;
      }
      if (this.h.onJson) this.h.onJson(msg);
    };
    ws.onclose = (ev) => {
      if (this.ws !== ws) return;
      this.ws = null;
      for (const { resolve } of this._pending.values()) resolve({ type: "error", code: "closed", message: "connection closed" });
      this._pending.clear();
      if (this.h.onClose) this.h.onClose(ev);
      // Sent to another host for a room, and that host is gone: the page says so.
      // (1006: no close frame, it died; 1001: it stopped. Other codes are its word to us.)
      const gone = ev.code === 1006 || ev.code === 1001;
      if (gone && this.url !== this.home && !this._stopped && this.h.onHostGone) this.h.onHostGone(this.url);
      if (!this._stopped) this._scheduleRetry();
    };
    ws.onerror = () => { /* onclose follows; the state shows it */ };
  }

  /** Reconnect at `url` (a redirect): the old connection closes without a retry. */
  moveTo(url) {
    const old = this.ws;
    this.ws = null;  // its close is not a loss: onclose sees it is no longer current
    if (old) old.close(1000, "moved");
    for (const { resolve } of this._pending.values()) resolve({ type: "error", code: "closed", message: "moved" });
    this._pending.clear();
    this.url = url;
    this.attempt = 0;
    this._connectNow();
  }

  _scheduleRetry() {
    this.url = this.home;
    this.attempt += 1;
    if (navigator.onLine === false) { this._setState("offline"); return; }
    const delay = backoffDelay(this.attempt);
    this.retryAt = performance.now() + delay * 1000;
    const tick = () => {
      const left = Math.max(0, (this.retryAt - performance.now()) / 1000);
      this._setState("reconnecting", { attempt: this.attempt, retryIn: left });
    };
    tick();
    clearInterval(this._countdown);
    this._countdown = setInterval(tick, 250);
    clearTimeout(this._timer);
    this._timer = setTimeout(() => { clearInterval(this._countdown); this._connect(); }, delay * 1000);
  }

  get open() { return this.ws !== null && this.ws.readyState === WebSocket.OPEN && this.state === "open"; }

  send(msg) {
    if (!this.open) return false;
    this.ws.send(JSON.stringify(msg));
    return true;
  }

  /** Send a control message with an id and resolve with the reply that echoes it. */
  request(msg, timeoutMs = 10000) {
    const id = this._nextId++;
    return new Promise((resolve) => {
      if (!this.send({ ...msg, id })) {
        resolve({ type: "error", code: "closed", message: "not connected" });
        return;
      }
      this._pending.set(id, { resolve });
      setTimeout(() => {
        if (this._pending.has(id)) {
          this._pending.delete(id);
          resolve({ type: "error", code: "timeout", message: "no reply from the server" });
        }
      }, timeoutMs);
    });
  }
}

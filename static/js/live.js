// The page's one connection to /ws/client/: authenticates with the session, reconnects, routes frames.

let counter = 0;
const prefix = Math.random().toString(36).slice(2, 10);
const newId = () => `web-${prefix}-${(++counter).toString(36)}`;

const CLOSE_AUTH_FAILED = 4001;

class LiveSocket {
  constructor() {
    this.listeners = new Map(); // event name (or "*") -> Set of functions
    this.resyncs = new Set();
    this.waiting = new Map(); // request id -> {resolve, reject, timer}
    this.queue = [];
    this.ready = false;
    this.everReady = false;
    this.attempt = 0;
    // The robots whose live metrics the page asked for, and what to do if refused (null: every robot).
    this.metrics = null;
    this.ws = null;
    this.statusNode = document.getElementById("live-status");
  }

  /** Listen to frames of one event ("*" for all but metrics); return a function that stops listening. */
  on(event, fn) {
    if (!this.listeners.has(event)) this.listeners.set(event, new Set());
    this.listeners.get(event).add(fn);
    return () => this.listeners.get(event).delete(fn);
  }

  /** Call fn after every reconnection: frames may have been missed, so the page reloads its state. */
  onResync(fn) {
    this.resyncs.add(fn);
  }

  /**
   * Be sent the live metrics of these robots only, now and after every reconnection; the cloud
   * refuses a list naming a robot the user may not see (deleted meanwhile, say): refused(error).
   */
  subscribeMetrics(robots, refused = () => {}) {
    this.metrics = { robots: [...robots], refused };
    // Before the socket is up, the list goes out right after authentication.
    if (this.ready) this.sendSubscription();
  }

  sendSubscription() {
    const { robots, refused } = this.metrics;
    this.request("metrics_subscribe", { robots }).catch((error) => {
      // A socket that closed subscribes again when it is back.
      if (error.code !== "closed") refused(error);
    });
  }

  /** Send a request (a *_get or a command) and resolve with its answer; reject with an error_message. */
  request(event, data, { timeout = 10000 } = {}) {
    const id = newId();
    const frame = JSON.stringify({ event, id, reply_to: null, data, ts: Date.now() / 1000 });
    return new Promise((resolve, reject) => {
      const timer = setTimeout(() => {
        this.waiting.delete(id);
        reject(Object.assign(new Error(`no answer to ${event} within ${timeout / 1000} s`), { code: "timeout" }));
      }, timeout);
      this.waiting.set(id, { resolve, reject, timer });
      if (this.ready) this.ws.send(frame);
      else this.queue.push(frame);
    });
  }

  connect() {
    if (this.statusNode) this.statusNode.hidden = false;
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    const ws = new WebSocket(`${scheme}://${location.host}/ws/client/`);
    this.ws = ws;
    this.status("connecting", "connecting…");
    ws.addEventListener("open", () => {
      // No token: the cloud uses the session cookie of the logged-in page.
      ws.send(JSON.stringify({ event: "authentication_client", id: newId(), reply_to: null, data: {}, ts: Date.now() / 1000 }));
    });
    ws.addEventListener("message", (message) => this.receive(message.data));
    ws.addEventListener("close", (close) => this.closed(close.code));
  }

  receive(text) {
    let frame;
    try {
      frame = JSON.parse(text);
    } catch {
      return;
    }
    const { event } = frame;
    if (event === "authentication_success") {
      this.ready = true;
      this.attempt = 0;
      this.status("live", "live");
      // A new connection streams every robot: narrow it first.
      if (this.metrics) this.sendSubscription();
      for (const queued of this.queue.splice(0)) this.ws.send(queued);
      if (this.everReady) for (const fn of this.resyncs) fn();
      this.everReady = true;
      return;
    }
    if (event === "authentication_failure") {
      this.status("offline", "signed out");
      return;
    }
    const waiter = frame.reply_to ? this.waiting.get(frame.reply_to) : undefined;
    if (waiter) {
      this.waiting.delete(frame.reply_to);
      clearTimeout(waiter.timer);
      if (event === "error_message") {
        waiter.reject(Object.assign(new Error(frame.data.message), frame.data));
      } else {
        waiter.resolve(frame);
      }
      return;
    }
    this.emit(event, frame);
    if (event !== "metrics") this.emit("*", frame);
  }

  emit(event, frame) {
    const listeners = this.listeners.get(event);
    if (!listeners) return;
    for (const fn of listeners) {
      try {
        fn(frame);
      } catch (error) {
        // One broken listener must not starve the others of live frames.
        setTimeout(() => {
          throw error;
        });
      }
    }
  }

  closed(code) {
    this.ready = false;
    for (const [id, waiter] of this.waiting) {
      clearTimeout(waiter.timer);
      waiter.reject(Object.assign(new Error("the live connection closed"), { code: "closed" }));
      this.waiting.delete(id);
    }
    this.attempt += 1;
    // Signed out: retry slowly (a login in another tab revives it); otherwise back off to 10 s.
    const base = code === CLOSE_AUTH_FAILED ? 15000 : Math.min(10000, 500 * 2 ** (this.attempt - 1));
    const delay = base * (0.8 + Math.random() * 0.4);
    this.status("offline", code === CLOSE_AUTH_FAILED ? "signed out" : `reconnecting in ${Math.ceil(delay / 1000)} s`);
    setTimeout(() => this.connect(), delay);
  }

  status(state, text) {
    if (!this.statusNode) return;
    this.statusNode.dataset.state = state;
    this.statusNode.textContent = text;
  }
}

/** The page's live connection, opened on first use. */
export const live = new LiveSocket();
let started = false;

export function startLive() {
  if (!started) {
    started = true;
    live.connect();
  }
  return live;
}

// One WebSocket to the server's /ws, kept open: hello, welcome, then the stream handed on in
// arrival order (binary frames decoded, text messages parsed and checked by decode.js).
//
// Nothing from the server can hang the page. A message that does not decode, a fatal error, a
// close, or no welcome within HELLO_TIMEOUT_MS end the connection with a message for the person
// (onStatus) and a new connection after a back-off (1 s doubling to 10 s); the new session
// starts from nothing (onReset), as the server's does. A refused hello (unknown scene or core,
// bad parameters, another protocol version, a token refused or not allowed the scene) is final:
// reconnecting with the same token cannot change the answer (onRefused lets the page ask for
// another).

import { decodeFrame, helloMessage, parseServerMessage, poseMessage } from "./decode.js";

const HELLO_TIMEOUT_MS = 15000;
const BACKOFF_MS = [1000, 2000, 4000, 8000, 10000];
/** Codes of a hello the server refuses for good (protocol/codes.py, fatal before welcome). */
const FINAL = new Set(["unknown_scene", "unknown_core", "bad_params", "unsupported_scene",
  "version_mismatch", "invalid_hello", "unauthorized", "forbidden"]);

export class Connection {
  /** `url`: the ws(s):// URL of /ws; `hello`: helloMessage's fields; handlers: onWelcome(w),
   * onMessage(msg), onFrame(decoded), onStatus({text, level}), onReset(), onRefused(msg) (a
   * final refusal of the hello, optional); `protocols`: the
   * subprotocols to offer (token.js wsProtocols: how a browser presents a token). */
  constructor(url, hello, handlers, protocols = []) {
    this.url = url;
    this.protocols = protocols;
    this.hello = hello;
    this.h = handlers;
    this.ws = null;
    this.welcome = null;
    this.attempt = 0;
    this.connections = 0;
    this.bytes = 0;
    this.chain = Promise.resolve();
    this.stopped = false;
    this.timer = null;
  }

  get open() { return this.welcome !== null && this.ws !== null && this.ws.readyState === WebSocket.OPEN; }

  connect() {
    if (this.stopped) return;
    this.welcome = null;
    this.h.onReset();
    this.connections += 1;
    this.h.onStatus({ text: `connecting to ${this.url}`, level: "info" });
    const ws = new WebSocket(this.url, this.protocols);
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    this.chain = Promise.resolve();
    const helloTimer = setTimeout(() => this.fail(ws, `no welcome from the server in ${HELLO_TIMEOUT_MS / 1000} s`), HELLO_TIMEOUT_MS);
    ws.onopen = () => ws.send(helloMessage(this.hello));
    ws.onmessage = (ev) => {
      if (ws !== this.ws) return;
      this.bytes += typeof ev.data === "string" ? ev.data.length : ev.data.byteLength;
      // One message at a time, in order: a cubemap decodes asynchronously, and its cell_end
      // must not overtake it.
      this.chain = this.chain.then(() => this.handle(ws, ev.data)).catch((e) => this.fail(ws, `bad message from the server: ${e.message}`));
    };
    ws.onclose = (ev) => {
      clearTimeout(helloTimer);
      if (ws !== this.ws) return;
      const why = ev.reason ? `${ev.code} ${ev.reason}` : `${ev.code}`;
      this.retry(`connection lost (close ${why})`);
    };
    ws.onerror = () => {}; // onclose follows and says it
    this.helloTimer = helloTimer;
  }

  async handle(ws, data) {
    if (ws !== this.ws) return;
    if (typeof data !== "string") {
      if (this.welcome === null) throw new Error("a binary frame before the welcome");
      const frame = await decodeFrame(data);
      if (ws === this.ws) this.h.onFrame(frame);
      return;
    }
    const msg = parseServerMessage(data);
    if (msg.type === "error" && msg.fatal) {
      const final = this.welcome === null && FINAL.has(msg.code);
      this.h.onMessage(msg);
      if (final) {
        this.stop(`the server refused: ${msg.code}: ${msg.message}`);
        if (this.h.onRefused) this.h.onRefused(msg);
        return;
      }
      this.fail(ws, `the server ended the session: ${msg.code}: ${msg.message}`);
      return;
    }
    if (this.welcome === null) {
      if (msg.type !== "welcome") throw new Error(`expected welcome, got ${msg.type}`);
      clearTimeout(this.helloTimer);
      this.welcome = msg;
      this.attempt = 0;
      this.h.onStatus({ text: `connected: session ${msg.session}`, level: "ok" });
      this.h.onWelcome(msg);
      return;
    }
    this.h.onMessage(msg);
  }

  /** End the connection after a problem and try again (the message stays on screen). */
  fail(ws, why) {
    if (ws !== this.ws || this.stopped) return;
    this.retry(why);
  }

  retry(why) {
    const ws = this.ws;
    this.ws = null;
    this.welcome = null;
    if (ws && ws.readyState <= WebSocket.OPEN) ws.close(1000, "client reconnects");
    if (this.stopped) return;
    const wait = BACKOFF_MS[Math.min(this.attempt, BACKOFF_MS.length - 1)];
    this.attempt += 1;
    this.h.onStatus({ text: `${why}; reconnecting in ${wait / 1000} s (attempt ${this.attempt})`, level: "error" });
    clearTimeout(this.timer);
    this.timer = setTimeout(() => this.connect(), wait);
  }

  /** Stop for good with a message. */
  stop(why) {
    this.stopped = true;
    clearTimeout(this.timer);
    const ws = this.ws;
    this.ws = null;
    if (ws && ws.readyState <= WebSocket.OPEN) ws.close(1000, "bye");
    this.h.onStatus({ text: why, level: "error" });
  }

  /** Send a pose (no-op while not connected); true when sent. */
  sendPose(seq, t, position, forward, velocity) {
    if (!this.open) return false;
    this.ws.send(poseMessage(seq, t, position, forward, velocity));
    return true;
  }
}

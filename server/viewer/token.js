// The page's bearer token: where it comes from, where it is kept, how it is sent.
//
// It comes from the URL fragment (#token=...: a browser never sends the fragment, so the token
// is in no server or proxy log) or from the form the page shows when the server wants one. It
// leaves the address bar as soon as it is read (history.replaceState), so a bookmark or a copied
// link does not carry it. It is kept in sessionStorage: that tab only, gone when the tab closes,
// never sent by the browser on its own (as a cookie would be), and it survives the page's own
// reloads (choosing another scene or core opens the page again). It is sent as the server
// accepts it (protocol/auth.py): Authorization: Bearer on HTTP, the subprotocols "pvs" and
// "pvs.bearer.<token>" on the WebSocket; never in a URL.

const KEY = "pvs.token";
const SUBPROTOCOL = "pvs";
const PREFIX = "pvs.bearer.";
/** protocol.auth.TOKEN_CHARS. */
const TOKEN_CHARS = /^[A-Za-z0-9._~+-]{16,512}$/;

/** Whether `text` has the form of a token. */
export function isToken(text) { return TOKEN_CHARS.test(text); }

/** Read a token from the URL fragment into storage and take it out of the address bar (the
 * rest of the fragment stays); the token held, or null. */
export function takeToken() {
  const parts = window.location.hash.replace(/^#/, "").split("&");
  const found = parts.filter((p) => p.startsWith("token="));
  if (!found.length) return currentToken();
  // Not URLSearchParams: it reads "+" as a space, and "+" is one of a token's characters.
  const token = decodeFragment(found[0].slice("token=".length)).trim();
  const rest = parts.filter((p) => p && !p.startsWith("token=")).join("&");
  history.replaceState(history.state, "",
    window.location.pathname + window.location.search + (rest ? `#${rest}` : ""));
  if (token) setToken(token);
  return currentToken();
}

/** A fragment's value percent-decoded ("+" kept), or as it is when it does not decode. */
function decodeFragment(text) {
  try { return decodeURIComponent(text); } catch { return text; }
}

// The token in memory too: with storage turned off (a browser setting) the page still works
// until it is opened again.
let held = null;

/** The token held, or null. */
export function currentToken() {
  try { return sessionStorage.getItem(KEY) ?? held; } catch { return held; }
}

/** Keep `token` for this tab (sessionStorage, and memory where storage is off). */
export function setToken(token) {
  held = token;
  try { sessionStorage.setItem(KEY, token); } catch { /* storage off: memory only */ }
}

/** Drop the token held (the server refused it). */
export function forgetToken() {
  held = null;
  try { sessionStorage.removeItem(KEY); } catch { /* storage off */ }
}

/** fetch() options presenting the token held (none: no header). */
export function authorized(token = currentToken()) {
  return token ? { headers: { Authorization: `Bearer ${token}` } } : {};
}

/** The WebSocket subprotocols presenting the token held to `url` (none without a token, or
 * when `url` is on another host than the page: the token is for this server only). */
export function wsProtocols(url, token = currentToken()) {
  if (!token || new URL(url).host !== window.location.host) return [];
  return [SUBPROTOCOL, PREFIX + token];
}

/** Show the token form with `why`; a token typed there is kept and the page opened again. */
export function askForToken(why) {
  const form = document.getElementById("token-form");
  const input = document.getElementById("token-input");
  document.getElementById("token-why").textContent = why;
  form.hidden = false;
  input.focus();
  form.onsubmit = (ev) => {
    ev.preventDefault();
    const token = input.value.trim();
    if (!isToken(token)) {
      document.getElementById("token-why").textContent =
        "that is not a token: 16 to 512 characters of A-Z a-z 0-9 - . _ ~ +";
      return;
    }
    input.value = "";
    setToken(token);
    window.location.reload();
  };
}

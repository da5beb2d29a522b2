// Key capture for the Kinetix playground, injected into viser's own page by server/http.py.
// viser sends no key events to Python (and its hotkeys have no keyup), so this script listens for keydown and
// keyup in the capture phase, drops auto-repeat, and sends each event over the /keys websocket, paired to the
// tab's session by the nonce the session put in the page (<div id="kinetix-session" data-nonce=...>).
// All keys are released when the window loses focus, so a thruster never stays on.
(function () {
  "use strict";
  const config = window.__KINETIX__ || {};
  // Point viser's client at its internal port (the documented ?websocket= parameter), on the same host.
  const params = new URLSearchParams(location.search);
  if (config.viserPort && !params.has("websocket")) {
    params.set("websocket", "ws://" + location.hostname + ":" + config.viserPort);
    history.replaceState(null, "", location.pathname + "?" + params.toString() + location.hash);
  }

  // Keys we own: play keys, Space, editor shortcuts. viser's camera also listens to WASD/QE/arrows; we stop those.
  const OWN = new Set(["ArrowLeft", "ArrowRight", "ArrowUp", "ArrowDown", "KeyW", "KeyA", "KeyS", "KeyD",
    "KeyQ", "KeyE", "Digit1", "Digit2", "Numpad1", "Numpad2", "Space", "Delete", "Backspace", "Escape",
    "Enter", "KeyR"]);
  const SHORTCUT = new Set(["KeyZ", "KeyY", "KeyC", "KeyV", "KeyD", "KeyX"]);
  const held = new Set();
  let socket = null, ready = false, nonce = null, seq = 0;
  const queue = [];
  window.__kinetixKeys = { sent: [], held, ready: () => ready };  // for tests and the benchmark

  function send(message) {
    if (socket && ready) socket.send(JSON.stringify(message));
    else if (queue.length < 64) queue.push(message);
  }

  // The gallery author token lives in localStorage (shared with /gallery); a save that issued a new one puts it
  // in the page as <div id="kinetix-token" data-token=...>, and we keep it from there.
  const TOKEN_KEY = "kinetix.author_token";
  function keepToken() {
    const el = document.getElementById("kinetix-token");
    const token = el && el.getAttribute("data-token");
    if (token && localStorage.getItem(TOKEN_KEY) !== token) localStorage.setItem(TOKEN_KEY, token);
  }

  function connect() {
    keepToken();
    const el = document.getElementById("kinetix-session");
    if (!el) return false;
    const found = el.getAttribute("data-nonce");
    if (!found || found === nonce) return true;
    nonce = found;
    ready = false;
    if (socket) socket.close();
    socket = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/keys");
    socket.onopen = () => socket.send(JSON.stringify({ type: "hello", nonce, query: location.search,
      token: localStorage.getItem(TOKEN_KEY) }));
    socket.onmessage = (ev) => {
      if (JSON.parse(ev.data).type === "ready") {
        ready = true;
        while (queue.length) socket.send(JSON.stringify(queue.shift()));
      }
    };
    socket.onclose = () => { ready = false; };
    return true;
  }
  // The nonce element arrives with viser's GUI messages after load; watch the DOM until it appears (and again
  // after a reconnect gives the tab a new session).
  new MutationObserver(connect).observe(document.documentElement, { childList: true, subtree: true });

  function typing(target) {
    const tag = target && target.tagName;
    return tag === "INPUT" || tag === "TEXTAREA" || tag === "SELECT" || (target && target.isContentEditable);
  }

  function handle(kind, e) {
    if (typing(e.target)) return;
    const mod = e.ctrlKey || e.metaKey;
    const ours = OWN.has(e.code) || (mod && SHORTCUT.has(e.code));
    if (!ours) return;
    e.preventDefault();
    e.stopImmediatePropagation();
    if (kind === "down") {
      if (e.repeat || held.has(e.code)) return;
      held.add(e.code);
    } else {
      if (!held.has(e.code)) return;
      held.delete(e.code);
    }
    seq += 1;
    const message = { type: kind, code: e.code, key: e.key, ctrl: e.ctrlKey, shift: e.shiftKey, alt: e.altKey,
      meta: e.metaKey, seq, t: performance.now() };
    window.__kinetixKeys.sent.push({ seq, t: message.t, code: e.code, type: kind });
    if (window.__kinetixKeys.sent.length > 1000) window.__kinetixKeys.sent.shift();
    send(message);
  }
  window.addEventListener("keydown", (e) => handle("down", e), true);
  window.addEventListener("keyup", (e) => handle("up", e), true);
  window.addEventListener("blur", () => {
    for (const code of Array.from(held)) {
      held.delete(code);
      seq += 1;
      send({ type: "up", code, key: "", ctrl: false, shift: false, alt: false, meta: false, seq, t: performance.now() });
    }
  });
})();

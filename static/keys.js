// Key capture for the Kinetix playground, injected into viser's own page by server/web/http.py.
// viser sends no key events to Python (and its hotkeys have no keyup), so this script listens for keydown and
// keyup in the capture phase, drops auto-repeat, and sends each event over the /keys websocket, paired to the
// tab's session by the nonce the session put in the page (<div id="kinetix-session" data-nonce=...>).
// All keys are released when the window loses focus, so a thruster never stays on.
(function () {
  "use strict";
  // viser's client connects to the page's own URL (ws: or wss: as the page) unless ?websocket= names another
  // server. The side server relays that socket to viser, so the app needs no second port: drop the parameter
  // that older versions wrote (an internal port that changed at every start) from bookmarks and copied links,
  // before viser's code reads it.
  const params = new URLSearchParams(location.search);
  if (params.has("websocket")) {
    params.delete("websocket");
    const query = params.toString();
    history.replaceState(null, "", location.pathname + (query ? "?" + query : "") + location.hash);
  }

  // Keys we own: play keys, Space, editor shortcuts. viser's camera also listens to WASD/QE/arrows; we stop those.
  const OWN = new Set(["ArrowLeft", "ArrowRight", "ArrowUp", "ArrowDown", "KeyW", "KeyA", "KeyS", "KeyD",
    "KeyQ", "KeyE", "Digit1", "Digit2", "Numpad1", "Numpad2", "Space", "Delete", "Backspace", "Escape",
    "Enter", "KeyR"]);
  const SHORTCUT = new Set(["KeyZ", "KeyY", "KeyC", "KeyV", "KeyD", "KeyX"]);
  const RETRY_MS = 1000;
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

  // The tab's own key, in sessionStorage: per tab, and kept across reloads and reconnects (through any server
  // process), so the server finds the tab's last play again for its Recordings folder. Made here, not by the
  // server, so the first hello has it; crypto.getRandomValues works on plain http too (randomUUID does not).
  const TAB_KEY = "kinetix.tab";
  function tabKey() {
    try {
      let key = sessionStorage.getItem(TAB_KEY);
      if (!key || !/^[0-9a-f]{32}$/.test(key)) {
        const bytes = crypto.getRandomValues(new Uint8Array(16));
        key = Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
        sessionStorage.setItem(TAB_KEY, key);
      }
      return key;
    } catch (e) {
      return null;  // storage turned off: the tab's last play stays with its session
    }
  }

  // The address bar names what the tab shows (?level=<gallery id> or ?draft=<id>): the session puts the query in
  // <div id="kinetix-address" data-query=...> and we show it, so a reload or a copied link reopens the same thing.
  function showAddress() {
    const el = document.getElementById("kinetix-address");
    const query = el && el.getAttribute("data-query");
    if (query && query !== location.search) history.replaceState(null, "", location.pathname + query + location.hash);
  }

  // The /keys socket, relative to the page (ws: or wss: as the page).
  function keysUrl() {
    const url = new URL("keys", location.href);
    url.protocol = location.protocol === "https:" ? "wss:" : "ws:";
    url.search = "";
    url.hash = "";
    return url.href;
  }

  function connect() {
    keepToken();
    showAddress();
    const el = document.getElementById("kinetix-session");
    if (!el) return false;
    const found = el.getAttribute("data-nonce");
    if (!found || found === nonce) return true;
    nonce = found;
    ready = false;
    if (socket) socket.close();
    const own = new WebSocket(keysUrl());
    socket = own;
    // The query names what this tab had open: after a reconnect (a new session) the server reopens it.
    own.onopen = () => own.send(JSON.stringify({ type: "hello", nonce, query: location.search,
      token: localStorage.getItem(TOKEN_KEY), tab: tabKey() }));
    own.onmessage = (ev) => {
      const message = JSON.parse(ev.data);
      if (message.type === "ready") {
        ready = true;
        while (queue.length) own.send(JSON.stringify(queue.shift()));
      } else if (message.type === "fields_ack") {
        releaseClick(message.id);
      }
    };
    own.onclose = () => {
      if (socket !== own) return;
      ready = false;
      // A dropped key socket (a network blip) is opened again; a server restart gives the tab a new session and
      // nonce, which the observer below picks up instead.
      setTimeout(() => { if (socket === own) { nonce = null; connect(); } }, RETRY_MS);
    };
    return true;
  }
  // The nonce element arrives with viser's GUI messages after load; watch the DOM until it appears (and again
  // after a reconnect gives the tab a new session).
  new MutationObserver(connect).observe(document.documentElement, { childList: true, subtree: true });

  // A dialog's buttons (Save in "Save to gallery") send the dialog's text fields first. viser's client sends every
  // panel update through one throttled sender (50 ms) that keeps only the newest message: a field changed just
  // before another one (a paste, a scripted fill) was never sent, and the level was saved without its description
  // (issue 37). So a click on a button of a dialog with text fields is held here, the fields' values go over this
  // socket (the server sets them on its side), and the click goes on to viser once the server has them.
  const FIELDS = "input[data-gui-uuid]:not([type=checkbox]):not([type=radio]), textarea[data-gui-uuid]";
  const CLICK_HOLD_MS = 2000; // at most: a click is never lost, even if the answer does not come
  const heldClicks = new Map(); // id -> the held click, to replay
  let clickSeq = 0, replaying = false;
  function releaseClick(id) {
    const replay = heldClicks.get(id);
    if (!replay) return;
    heldClicks.delete(id);
    replaying = true;
    try { replay(); } finally { replaying = false; }
  }
  window.addEventListener("click", (e) => {
    if (replaying || !socket || !ready || !e.target || !e.target.closest) return;
    const button = e.target.closest("button");
    const dialog = button && button.closest("[role=dialog]");
    if (!dialog) return;
    const values = {};
    for (const field of dialog.querySelectorAll(FIELDS)) values[field.dataset.guiUuid] = field.value;
    if (!Object.keys(values).length) return;
    e.preventDefault();
    e.stopImmediatePropagation();
    const id = ++clickSeq;
    heldClicks.set(id, () => button.click());
    socket.send(JSON.stringify({ type: "fields", id, values }));
    setTimeout(() => releaseClick(id), CLICK_HOLD_MS);
  }, true);

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

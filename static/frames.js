// Shows the server's frames on a 2D canvas over viser's WebGL canvas. Injected into viser's page by
// server/web/http.py, before viser's own code runs.
//
// The server sends every frame as viser's BackgroundImageMessage (one JPEG per frame, in the same message batch
// as the key acknowledgement). viser would load each through an <img> and a new WebGL texture, drop a frame
// whose decode finishes after the next frame arrived, and re-render its 3D scene for 250 ms after each one. On
// a slow machine (measured: headless Chromium with software WebGL, 2 cores) that kept the GPU process at 120% CPU,
// showed about 7 of the 30 frames a second, and held every message batch ~20 ms behind a busy main thread.
// Here each frame is decoded off the main thread (createImageBitmap) and drawn with one drawImage; frames are shown
// in order and a frame is dropped only when a newer one is already on screen. viser's canvas stays underneath
// for pointer input (the overlay ignores the pointer), and every other message still goes to viser.
//
// Until the first frame arrives, the overlay shows the level the page's address names (?level=, ?draft=): the
// server puts its picture in the page (<img id="kinetix-preview">, server/web/http.py), which shows it until
// viser's canvas exists, and it is drawn on the canvas the moment it does. The first frame can only come after
// viser's client has started, connected and had its session built, about a second later; the canvas was blank
// until then (issue 37). And viser's websocket carries the page's query, so the session opens that level at once
// (server/web/relay.py) instead of first showing a new level and waiting for keys.js to tell it the address.
(function () {
  "use strict";
  const state = {
    overlay: null, // our <canvas>
    target: null, // viser's canvas it covers
    context: null,
    latest: 0, // sequence number of the newest frame received
    shown: 0, // ... and of the newest frame drawn
    drawn: 0, // frames drawn so far (tests and the benchmark read it)
    hidden: false,
    listeners: [], // callbacks (seq, acks) after each draw, for the benchmark
  };
  window.__kinetixFrames = state;

  function viserCanvas() {
    let best = null;
    for (const canvas of document.querySelectorAll("canvas")) {
      if (canvas === state.overlay) continue;
      if (!best || canvas.clientWidth * canvas.clientHeight > best.clientWidth * best.clientHeight) best = canvas;
    }
    return best;
  }

  function place() {
    const target = state.target;
    const overlay = state.overlay;
    if (!target || !overlay) return;
    overlay.style.left = target.offsetLeft + "px";
    overlay.style.top = target.offsetTop + "px";
    overlay.style.width = target.clientWidth + "px";
    overlay.style.height = target.clientHeight + "px";
    placeNotices(target.getBoundingClientRect());
  }

  // Notices (viser's notifications: "Saved to the gallery", errors, its own toasts) sit at the top LEFT of the
  // canvas by default, over the HUD line and the key legend the frames draw there. Keep them at the top RIGHT of
  // the canvas instead (levels are mostly sky there), at most 40% of its width so a long HUD line stays clear, and
  // in its upper half, above the banner the frames draw across the middle ("Press Space or an arrow key to start",
  // "You won!"; server.play.draw: at most BANNER_HALF pixels above the middle); more notices than fit scroll.
  const NOTICE_MARGIN = 12; // pixels from the canvas edges
  const NOTICE_WIDTH = 296; // viser's own width (20em)
  const BANNER_HALF = 44; // half the height of a two-line banner (28 pixels a line + 16), with a margin
  function placeNotices(box) {
    let style = document.getElementById("kinetix-notices");
    if (!style) {
      style = document.createElement("style");
      style.id = "kinetix-notices";
      document.head.appendChild(style);
    }
    const width = Math.max(160, Math.min(NOTICE_WIDTH, Math.round(0.4 * box.width)));
    const left = Math.max(box.left + NOTICE_MARGIN, box.right - width - NOTICE_MARGIN);
    const height = Math.max(80, Math.round(box.height / 2 - BANNER_HALF - NOTICE_MARGIN));
    style.textContent = ".mantine-Notifications-root { position: fixed !important; top: " +
      Math.round(box.top + NOTICE_MARGIN) + "px !important; left: " + Math.round(left) + "px !important; " +
      "right: auto !important; width: " + width + "px !important; max-width: " + width + "px !important; " +
      "max-height: " + height + "px !important; overflow-y: auto !important; }";
  }

  // The overlay sits right after viser's canvas in the same parent, so viser's own overlays (the box-select
  // rectangle) that come later in the page stay on top of it.
  const resizes = new ResizeObserver(() => {
    place();
    if (state.drawn === 0) drawPreview(); // the canvas changed size (the panel docks): no stretched preview
  });
  function attach() {
    if (state.overlay && state.overlay.isConnected && state.target && state.target.isConnected) return true;
    const target = viserCanvas();
    if (!target || !target.parentElement) return false;
    if (state.overlay) state.overlay.remove();
    if (state.target) resizes.unobserve(state.target);
    const overlay = document.createElement("canvas");
    overlay.id = "kinetix-frame";
    overlay.style.position = "absolute";
    overlay.style.pointerEvents = "none";
    overlay.style.display = state.hidden ? "none" : "block";
    target.insertAdjacentElement("afterend", overlay);
    state.overlay = overlay;
    state.target = target;
    state.context = overlay.getContext("2d", { alpha: false });
    resizes.observe(target);
    place();
    return true;
  }

  function draw(seq, bitmap, acks) {
    if (seq < state.shown || !attach()) {
      bitmap.close();
      return;
    }
    const overlay = state.overlay;
    if (overlay.width !== bitmap.width || overlay.height !== bitmap.height) {
      overlay.width = bitmap.width;
      overlay.height = bitmap.height;
      place();
    }
    state.context.drawImage(bitmap, 0, 0);
    bitmap.close();
    if (state.drawn === 0) hidePreview();
    state.shown = seq;
    state.drawn += 1;
    for (const listener of state.listeners) listener(seq, acks);
  }

  // The level's picture the page came with, letterboxed into the canvas as the server's frames are (the picture is
  // square, as the world is). Only until the first frame is drawn.
  function drawPreview() {
    const image = document.getElementById("kinetix-preview");
    if (image && !image.complete) image.addEventListener("load", drawPreview, { once: true }); // not decoded yet
    if (state.drawn > 0 || state.hidden || !image || !image.complete || !image.naturalWidth || !attach()) return;
    const width = Math.round(state.target.clientWidth);
    const height = Math.round(state.target.clientHeight);
    if (width < 1 || height < 1) return; // not laid out yet: the resize observer draws it then
    const overlay = state.overlay;
    overlay.width = width;
    overlay.height = height;
    const context = state.context;
    context.fillStyle = image.dataset.letterbox || "#e2e4e8";
    context.fillRect(0, 0, width, height);
    const scale = Math.min(width / image.naturalWidth, height / image.naturalHeight);
    const w = image.naturalWidth * scale;
    const h = image.naturalHeight * scale;
    context.drawImage(image, (width - w) / 2, (height - h) / 2, w, h);
    hidePreview(); // it stood in for the canvas until now (server/web/http.py: with_preview)
  }

  function hidePreview() {
    const image = document.getElementById("kinetix-preview");
    if (image) image.style.display = "none";
  }

  // viser creates its canvas a few hundred milliseconds after the page starts (and could replace it): draw the
  // preview on it in the same task, before the browser paints it blank. Watching ends with the first frame.
  const canvases = new MutationObserver(() => {
    if (state.drawn > 0) canvases.disconnect();
    else if (!state.overlay || !state.overlay.isConnected || !state.target || !state.target.isConnected) drawPreview();
  });
  canvases.observe(document, { childList: true, subtree: true });

  function setHidden(hidden) {
    state.hidden = hidden;
    if (state.overlay) state.overlay.style.display = hidden ? "none" : "block";
  }

  // The key acknowledgements in a batch (<div id="kinetix-ack" data-seq=N>), so the benchmark can time the
  // frame that carried them.
  function acksOf(messages) {
    const acks = [];
    for (const message of messages) {
      if (message.type !== "GuiUpdateMessage") continue;
      const content = message.updates && message.updates.content;
      const match = typeof content === "string" && content.match(/kinetix-ack" data-seq="([0-9]+)"/);
      if (match) acks.push(+match[1]);
    }
    return acks;
  }

  function take(data) {
    if (!data || data.type !== "message_batch" || !Array.isArray(data.messages)) return;
    const messages = data.messages;
    let frame = null;
    let cleared = false;
    for (let i = messages.length - 1; i >= 0; i--) {
      const message = messages[i];
      if (message.type !== "BackgroundImageMessage" || message.depth_data) continue;
      if (frame === null && !cleared) {
        if (message.rgb_data) frame = message;
        else cleared = true;
      }
      if (message.rgb_data) messages.splice(i, 1); // viser does not see the images we show
    }
    if (cleared) {
      state.shown = ++state.latest; // a clear supersedes every frame in flight
      setHidden(true);
      return;
    }
    if (frame === null) return;
    setHidden(false);
    const seq = ++state.latest;
    const acks = state.listeners.length ? acksOf(messages) : [];
    createImageBitmap(new Blob([frame.rgb_data], { type: "image/" + frame.format })).then(
      (bitmap) => draw(seq, bitmap, acks),
      (error) => console.warn("kinetix: a frame did not decode", error),
    );
  }

  // viser's websocket goes to the page's own address without its query; add it, so the session knows what the
  // address names when it starts (server/web/relay.py passes it on). A reconnect (viser's "retry", after a server
  // restart) names what the address shows by then: keys.js keeps it current (?draft=<id>, ?level=<id>).
  function withQuery(server) {
    return typeof server === "string" && server.indexOf("?") < 0 ? server + location.search : server;
  }

  // viser receives its message batches from a Web Worker; listen on each worker first (before viser's own
  // handler, which is set after construction) and take the frames out of the batch.
  const ViserWorker = window.Worker;
  function Worker(url, options) {
    const worker = new ViserWorker(url, options);
    const post = worker.postMessage.bind(worker);
    let server = null; // the address viser gave, without the query
    worker.postMessage = function (data, ...rest) {
      if (data && data.type === "set_server") {
        server = data.server;
        return post({ ...data, server: withQuery(server) }, ...rest);
      }
      if (data && data.type === "retry" && server !== null) {
        return post({ type: "set_server", server: withQuery(server) }); // what a retry does, with today's query
      }
      return post(data, ...rest);
    };
    worker.addEventListener("message", (event) => {
      try {
        take(event.data);
      } catch (error) {
        console.warn("kinetix: frame handling failed", error);
      }
    });
    return worker;
  }
  Worker.prototype = ViserWorker.prototype;
  window.Worker = Worker;
})();

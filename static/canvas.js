// WebGL settings for viser's canvas, injected into viser's page by server/http.py before viser's own code runs.
// The canvas shows one full-canvas image that the server has already anti-aliased, so the canvas's own
// multisampling changes nothing visible; it only costs the GPU. On machines without one (software WebGL, as in
// headless Chromium on the 2-core benchmark machine) it made the GPU process the bottleneck: key-to-frame
// p50 33.5 -> 27.7 ms and p90 51.5 -> 39.3 ms without it (docs/server.md).
(function () {
  "use strict";
  const getContext = HTMLCanvasElement.prototype.getContext;
  HTMLCanvasElement.prototype.getContext = function (type, attributes) {
    if (type === "webgl2" || type === "webgl") {
      attributes = Object.assign({}, attributes, { antialias: false });
    }
    return getContext.call(this, type, attributes);
  };
})();

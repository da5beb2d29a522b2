// Quiets one console error of viser's client without changing what it does. Injected into viser's page by
// server/web/http.py, before viser's own code runs.
//
// viser's scene (react-three-fiber) listens to pointer events with passive listeners, and its draggable nodes (the
// canvas-wide drag catcher of server/play/editing.py) call preventDefault() in them. In a passive listener that
// call does nothing, but Chromium logs "Unable to preventDefault inside passive event listener invocation." as a
// console error for it: 23 times per drag on the canvas (issue 37). Here a preventDefault() called on the event a
// passive listener is handling returns at once, as the browser would have ignored it anyway; everything else,
// including the same call from a non-passive listener (even on the same event), is untouched.
(function () {
  "use strict";
  const add = EventTarget.prototype.addEventListener;
  const remove = EventTarget.prototype.removeEventListener;
  const preventDefault = Event.prototype.preventDefault;
  const wrappers = new WeakMap(); // listener -> {"type capture": its wrapper}
  const handling = []; // the events passive listeners are handling now (nested dispatches stack)

  function passive(options) {
    return typeof options === "object" && options !== null && options.passive === true;
  }
  function capture(options) {
    return typeof options === "boolean" ? options : !!(options && options.capture);
  }

  EventTarget.prototype.addEventListener = function (type, listener, options) {
    if (!passive(options) || !listener) return add.call(this, type, listener, options);
    const key = type + " " + capture(options);
    let own = wrappers.get(listener);
    if (!own) wrappers.set(listener, (own = {}));
    if (!own[key]) {
      own[key] = function (event) {
        handling.push(event);
        try {
          return typeof listener === "function" ? listener.call(this, event) : listener.handleEvent(event);
        } finally {
          handling.pop();
        }
      };
    }
    return add.call(this, type, own[key], options);
  };

  EventTarget.prototype.removeEventListener = function (type, listener, options) {
    const own = listener && wrappers.get(listener);
    const wrapper = own && own[type + " " + capture(options)];
    if (wrapper) remove.call(this, type, wrapper, options);
    return remove.call(this, type, listener, options);
  };

  Event.prototype.preventDefault = function () {
    if (handling.length && handling[handling.length - 1] === this) return; // a passive listener: a no-op anyway
    return preventDefault.call(this);
  };
})();

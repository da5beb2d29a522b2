// Ties viser's panel labels to their inputs, for screen readers and label clicks. Injected into viser's page by
// server/web/http.py.
//
// viser draws each labelled input as <label for="<uuid>"> beside the input, but its text, textarea and dropdown
// components do not give the input that id (Mantine gives it one of its own), so the label names nothing: the save
// dialog's Name, Description and Tags fields had no accessible name. Whenever the panel changes, each label whose
// `for` names no element is pointed at the input of its row; a slider (a <div role="slider">, which a label cannot
// name) gets aria-labelledby instead. Each tied input also keeps its GUI element's uuid (data-gui-uuid), which
// keys.js sends with a dialog's values when one of its buttons is clicked.
(function () {
  "use strict";
  const CONTROL = "input:not([type=hidden]), textarea, select, [role=slider]";
  const ROW_DEPTH = 4; // label -> text -> label box -> the row holding the input (viser's LabeledInput)

  function controlOf(label) {
    let node = label.parentElement;
    for (let depth = 0; node && depth < ROW_DEPTH; depth += 1, node = node.parentElement) {
      const found = node.querySelector(CONTROL);
      if (found) return found;
    }
    return null;
  }

  function tie(label) {
    const named = label.htmlFor && document.getElementById(label.htmlFor);
    if (named && named.matches(CONTROL)) return; // already tied
    const control = controlOf(label);
    if (!control) return;
    if (label.htmlFor && !control.dataset.guiUuid) control.dataset.guiUuid = label.htmlFor; // viser's uuid
    if (control.getAttribute("role") === "slider") {
      if (!label.id) label.id = (label.htmlFor || "kinetix") + "-label";
      control.setAttribute("aria-labelledby", label.id);
      return;
    }
    if (!control.id) control.id = label.htmlFor;
    label.htmlFor = control.id;
  }

  let pending = false;
  function tieAll() {
    pending = false;
    for (const label of document.querySelectorAll("label[for]")) tie(label);
  }
  // Coalesce bursts of DOM changes (a GUI update message often touches many nodes) into one pass.
  new MutationObserver(() => {
    if (!pending) {
      pending = true;
      setTimeout(tieAll, 0);
    }
  }).observe(document.documentElement, { childList: true, subtree: true });
})();

// The gallery page: cards from GET /api/levels. User text is only ever set with textContent (never parsed as HTML),
// so names like <img onerror=...> show as text. The author/voter token lives in localStorage.
"use strict";
const TOKEN_KEY = "kinetix.author_token";
const VOTES_KEY = "kinetix.votes";
// `next` is the API's cursor of the page after the cards shown (null: they are all shown); `shown` holds the ids
// on the page, so a level never gets two cards; `request` numbers the loads, so only the newest one's answer is used.
const state = { sort: "newest", size: "", tag: "", q: "", next: null, shown: new Set(), request: 0 };
const grid = document.getElementById("grid");
const more = document.getElementById("more");
const statusLine = document.getElementById("status");

function token() { return localStorage.getItem(TOKEN_KEY); }
function myVotes() { try { return JSON.parse(localStorage.getItem(VOTES_KEY) || "{}"); } catch { return {}; } }
function percent(rate) { return rate === null ? "–" : Math.round(rate * 100) + "%"; }
function seconds(s) { return s === null ? "–" : s.toFixed(1) + " s"; }
// The status line says what went wrong (kind "error", in red) or what happened (kind "info", e.g. a copied link).
function setStatus(text, kind = "error") { statusLine.textContent = text || ""; statusLine.className = kind; }

// An error carries the answer's status and, for 503 "try again later", its Retry-After in seconds (or null).
async function api(path, options = {}) {
  const response = await fetch(path, options);
  const body = await response.json().catch(() => ({}));
  if (!response.ok) {
    const detail = typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail || response.status);
    const retryAfter = parseInt(response.headers.get("Retry-After") || "", 10);
    throw Object.assign(new Error(detail), { status: response.status,
      retryAfter: Number.isFinite(retryAfter) ? retryAfter : null });
  }
  return body;
}

// The page never stays wrong by itself: right after the server starts, the gallery may still be filling with the
// project's levels (the API answers 503 with Retry-After while it does, or an empty first page). The page then
// says so and loads again: after Retry-After (1-30 s), or every EMPTY_RETRY_MS while an unfiltered gallery is empty.
const EMPTY_RETRY_MS = 5000;
let retryTimer = null;
function retryLater(reset, ms) {
  clearTimeout(retryTimer);
  retryTimer = setTimeout(() => load(reset), ms);
}
function unfiltered() { return !state.size && !state.tag && !state.q; }

function card(level) {
  const node = document.getElementById("card").content.firstElementChild.cloneNode(true);
  const q = (selector) => node.querySelector(selector);
  const id = encodeURIComponent(level.id);
  q(".thumb").href = `./?level=${id}&mode=play`;
  q("img").src = level.thumbnail;
  q("img").alt = level.name;
  q(".name").textContent = level.name;
  q(".description").textContent = level.description || "";
  q(".author").textContent = level.author ? "author " + level.author.slice(0, 6) : "kinetix";
  const date = new Date(level.created);
  q(".date").textContent = date.toLocaleDateString();
  q(".date").dateTime = date.toISOString();
  q(".size").textContent = "size " + level.size;
  q(".tags").textContent = level.tags.map((t) => "#" + t).join(" ");
  q(".plays").textContent = String(level.stats.plays);
  q(".human").textContent = percent(level.stats.human_solve_rate);
  q(".agent").textContent = percent(level.stats.agent_solve_rate);
  q(".best").textContent = seconds(level.stats.best_human_seconds);
  q(".score").textContent = String(level.stats.score);
  q(".play").href = `./?level=${id}&mode=play`;
  q(".edit").href = `./?level=${id}`;
  // The recording of the fastest human solve, replayed in the editor tab (GET /api/levels/{id}/best-run.mcap).
  q(".best-run").disabled = !level.stats.has_best_run;
  q(".best-run").title = level.stats.has_best_run ? "Replay the fastest human solve" : "No recorded solve yet";
  q(".best-run").addEventListener("click", () => { location.href = `./?level=${id}&mode=replay`; });
  q(".watch").href = `./?level=${id}&mode=agent`;
  const mine = myVotes()[level.id] || 0;
  q(".up").classList.toggle("mine", mine === 1);
  q(".down").classList.toggle("mine", mine === -1);
  q(".up").addEventListener("click", () => vote(level, node, mine === 1 ? 0 : 1));
  q(".down").addEventListener("click", () => vote(level, node, mine === -1 ? 0 : -1));
  q(".share").addEventListener("click", async () => {
    const link = new URL(`./?level=${id}&mode=play`, location.href).href;
    try { await navigator.clipboard.writeText(link); setStatus("Link copied: " + link, "info"); }
    catch { setStatus("Share this link: " + link, "info"); }
  });
  return node;
}

async function vote(level, node, value) {
  const headers = { "Content-Type": "application/json" };
  if (token()) headers.Authorization = "Bearer " + token();
  try {
    let result;
    try {
      result = await api(`api/levels/${encodeURIComponent(level.id)}/vote`,
        { method: "POST", headers, body: JSON.stringify({ value }) });
    } catch (error) {
      if (error.status !== 401 || !token()) throw error;
      localStorage.removeItem(TOKEN_KEY);  // a token this gallery does not know (e.g. a reset database)
      delete headers.Authorization;
      result = await api(`api/levels/${encodeURIComponent(level.id)}/vote`,
        { method: "POST", headers, body: JSON.stringify({ value }) });
    }
    if (result.author_token) localStorage.setItem(TOKEN_KEY, result.author_token);
    const votes = myVotes();
    votes[level.id] = value;
    localStorage.setItem(VOTES_KEY, JSON.stringify(votes));
    level.stats.score = result.score;
    node.replaceWith(card(level));
  } catch (error) {
    setStatus("Vote failed: " + error.message);
  }
}

// reset: the first page for the current tabs and filters (replacing the cards); else the page after the shown ones.
async function load(reset) {
  if (!reset && !state.next) return;  // every level is shown already: nothing more to fetch
  clearTimeout(retryTimer);  // this load replaces a retry still waiting
  const request = ++state.request;
  const params = new URLSearchParams({ sort: state.sort, limit: "24" });
  if (state.size) params.set("size", state.size);
  if (state.tag) params.set("tag", state.tag);
  if (state.q) params.set("q", state.q);
  if (!reset) params.set("cursor", state.next);
  more.disabled = true;
  try {
    const page = await api("api/levels?" + params);
    if (request !== state.request) return;  // a newer load (a filter changed meanwhile) owns the grid
    if (reset) { grid.replaceChildren(); state.shown.clear(); }
    for (const level of page.items) {
      if (state.shown.has(level.id)) continue;
      state.shown.add(level.id);
      grid.append(card(level));
    }
    state.next = page.next;
    if (grid.children.length) setStatus("", "info");
    else if (!unfiltered()) setStatus("No levels match.", "info");
    else {
      setStatus("The gallery has no levels yet: this page looks again every few seconds.", "info");
      retryLater(true, EMPTY_RETRY_MS);
    }
  } catch (error) {
    if (request !== state.request) return;
    if (error.status === 503) {  // e.g. the server is still filling the gallery: try again when it says
      const wait = Math.min(30, Math.max(1, error.retryAfter || 2));
      setStatus(`The gallery is being prepared: loading it again in ${wait} s.`, "info");
      retryLater(reset, wait * 1000);
      return;
    }
    if (reset) state.next = null;  // the shown cards are another query's: no "more" of them
    setStatus("Could not load the gallery: " + error.message);
  } finally {
    if (request === state.request) {
      more.hidden = !state.next;
      more.disabled = false;
    }
  }
}

for (const tab of document.querySelectorAll("#tabs button")) {
  tab.addEventListener("click", () => {
    for (const other of document.querySelectorAll("#tabs button")) other.setAttribute("aria-selected", "false");
    tab.setAttribute("aria-selected", "true");
    state.sort = tab.dataset.sort;
    load(true);
  });
}
let typing = null;
function onFilter() {
  clearTimeout(typing);
  typing = setTimeout(() => {
    state.size = document.getElementById("size").value;
    state.tag = document.getElementById("tag").value.trim().toLowerCase();
    state.q = document.getElementById("search").value.trim();
    load(true);
  }, 250);
}
for (const id of ["size", "tag", "search"]) document.getElementById(id).addEventListener("input", onFilter);
more.addEventListener("click", () => load(false));
load(true);

/*
 * The grants page while a grant or a revocation waits for the chain: polls the grants
 * (GET /api/v1/grants/) and, once a status differs from the page's, fetches the page again
 * and swaps in its two lists (the server renders them; the grant form, and whatever is typed
 * in it, stays as it is). It stops once nothing is pending, waits while the tab is hidden,
 * and backs off after a failed answer. Without JavaScript the page's note says to reload.
 */
(function () {
  "use strict";

  var INTERVAL_MS = 2000;
  var MAX_WAIT_MS = 60000;
  var root = document.querySelector("[data-grants-refresh]");
  if (!root) { return; }
  var url = root.getAttribute("data-status-url");
  var WAITING = ["pending", "revoking"];
  var wait = INTERVAL_MS;
  var timer = null;

  function rows() {
    return Array.prototype.slice.call(document.querySelectorAll("[data-grant-key]"));
  }

  function waiting() {
    return rows().some(function (row) {
      return WAITING.indexOf(row.getAttribute("data-status")) !== -1;
    });
  }

  function changed(answer) {
    var now = {};
    answer.given.forEach(function (grant) { now["given:" + grant.grantee] = grant.status; });
    answer.received.forEach(function (grant) { now["received:" + grant.owner] = grant.status; });
    return rows().some(function (row) {
      var key = row.getAttribute("data-grant-key");
      return now[key] !== undefined && now[key] !== row.getAttribute("data-status");
    });
  }

  function swapLists() {
    return fetch(window.location.href, { credentials: "same-origin", headers: { "Accept": "text/html" } })
      .then(function (response) {
        if (!response.ok) { throw new Error("HTTP " + response.status); }
        return response.text();
      })
      .then(function (html) {
        var fresh = new DOMParser().parseFromString(html, "text/html");
        document.querySelectorAll("[data-grants-list]").forEach(function (list) {
          var other = fresh.getElementById(list.id);
          if (other) { list.replaceWith(document.importNode(other, true)); }
        });
      });
  }

  function schedule(after) {
    clearTimeout(timer);
    timer = (document.hidden || !waiting()) ? null : setTimeout(tick, after);
  }

  function tick() {
    fetch(url, { credentials: "same-origin", headers: { "Accept": "application/json" } })
      .then(function (response) {
        if (!response.ok) { throw new Error("HTTP " + response.status); }
        return response.json();
      })
      .then(function (answer) { return changed(answer) ? swapLists() : null; })
      .then(function () { wait = INTERVAL_MS; schedule(wait); })
      .catch(function () { wait = Math.min(wait * 2, MAX_WAIT_MS); schedule(wait); });
  }

  document.addEventListener("visibilitychange", function () {
    if (document.hidden) { clearTimeout(timer); timer = null; } else { schedule(0); }
  });
  schedule(INTERVAL_MS);
})();

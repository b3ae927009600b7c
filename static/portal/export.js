/*
 * An export's page while it runs: polls its status (GET /api/v1/exports/{id}/), moves the
 * progress bar and the summary, and reloads the page once the export is over (its files or
 * its error are rendered by the server). Without JavaScript the page refreshes itself.
 */
(function () {
  "use strict";

  var INTERVAL_MS = 1000;
  var box = document.querySelector("[data-export-progress]");
  if (!box) { return; }
  var state = box.getAttribute("data-state");
  if (state !== "queued" && state !== "running") { return; }
  var bar = document.getElementById("export-bar");
  var summary = document.getElementById("export-summary");
  var badge = document.getElementById("export-status");

  function show(status) {
    bar.value = status.percent;
    bar.textContent = status.percent + "%";
    summary.textContent = status.processed + " of " + status.total +
      " records checked against the chain, " + status.exported + " exported.";
    badge.textContent = status.status;
    badge.className = "badge " + status.status;
    box.setAttribute("data-state", status.status);
    box.setAttribute("data-percent", String(status.percent));
  }

  function tick() {
    fetch(box.getAttribute("data-status-url"), {
      credentials: "same-origin", headers: { "Accept": "application/json" }
    })
      .then(function (response) {
        if (!response.ok) { throw new Error("HTTP " + response.status); }
        return response.json();
      })
      .then(function (status) {
        show(status);
        if (status.status === "queued" || status.status === "running") {
          setTimeout(tick, INTERVAL_MS);
        } else {
          window.location.reload();
        }
      })
      .catch(function () { setTimeout(tick, INTERVAL_MS * 2); });
  }
  setTimeout(tick, INTERVAL_MS);
})();

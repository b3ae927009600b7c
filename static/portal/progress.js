/*
 * Follows on-chain work by polling the owner's status (account/status.json):
 *  - [data-registration-progress]: fills in the transaction hashes of the registration steps
 *    and announces the outcome (the summary is an aria-live region);
 *  - [data-key-progress]: reloads the page once the current key is confirmed on chain.
 * Without JavaScript the pages refresh themselves (meta refresh in <noscript>).
 */
(function () {
  "use strict";

  var INTERVAL_MS = 1500;

  function poll(url, onStatus) {
    function tick() {
      fetch(url, { credentials: "same-origin", headers: { "Accept": "application/json" } })
        .then(function (response) {
          if (!response.ok) { throw new Error("HTTP " + response.status); }
          return response.json();
        })
        .then(function (status) {
          if (onStatus(status) !== false) { setTimeout(tick, INTERVAL_MS); }
        })
        .catch(function () { setTimeout(tick, INTERVAL_MS * 2); });
    }
    setTimeout(tick, INTERVAL_MS);
  }

  var registration = document.querySelector("[data-registration-progress]");
  if (registration && registration.getAttribute("data-state") === "pending") {
    var summary = document.getElementById("progress-summary");
    poll(registration.getAttribute("data-status-url"), function (status) {
      ["fund", "enroll", "register"].forEach(function (step) {
        var tx = status[step + "_tx"];
        var item = document.getElementById("step-" + step);
        var hash = item && item.querySelector("[data-tx]");
        if (tx && hash) { hash.textContent = tx; }
        if (!tx && hash && step === "fund" && status.chain_state === "confirmed") {
          hash.textContent = "none needed (this chain charges no gas)";
        }
        if (item && (tx || status.chain_state === "confirmed")) { item.classList.add("done"); }
      });
      registration.setAttribute("data-state", status.chain_state);
      if (status.chain_state === "confirmed") {
        summary.textContent = "Your account is registered on chain at block " +
          status.registered_block + ".";
        return false;
      }
      if (status.chain_state === "failed") {
        summary.textContent = "Registration failed: " + (status.chain_error || "see the operator") + ".";
        return false;
      }
      if (status.chain_error) {
        // e.g. waiting for the funding budget: the worker tries again by itself.
        summary.textContent = "Not registered yet, " + status.chain_error + ". This page updates by itself.";
      }
      return true;
    });
  }

  var keyProgress = document.querySelector("[data-key-progress]");
  if (keyProgress) {
    poll(keyProgress.getAttribute("data-status-url"), function (status) {
      if (status.key && status.key.chain_state !== "pending") {
        window.location.reload();
        return false;
      }
      return true;
    });
  }
})();

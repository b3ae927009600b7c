/*
 * The export form: whenever the selection changes, asks how many records it holds
 * (GET /api/v1/exports/count/) and says so before the owner submits, or why it would be
 * refused (nothing in it, more than the limit). Without JavaScript the "Count records"
 * button asks the server for the same count.
 */
(function () {
  "use strict";

  var form = document.getElementById("export-form");
  var shown = document.getElementById("export-count");
  if (!form || !shown) { return; }
  var DELAY_MS = 300;
  var timer = null;
  var asked = 0;

  function utc(value) {
    // The form's times are UTC (its labels say so); the API wants a zone.
    return /[Zz]|[+-]\d\d:\d\d$/.test(value) ? value : value + "Z";
  }

  function query() {
    var parts = [];
    form.querySelectorAll("input[name=robots]:checked, input[name=topics]:checked")
      .forEach(function (box) {
        parts.push(encodeURIComponent(box.name) + "=" + encodeURIComponent(box.value));
      });
    ["since", "until"].forEach(function (name) {
      var field = form.querySelector("[name=" + name + "]");
      if (field && field.value) {
        parts.push(name + "=" + encodeURIComponent(utc(field.value)));
      }
    });
    return parts.join("&");
  }

  function say(text, refused) {
    shown.textContent = text;
    shown.classList.toggle("errorlist", refused);
  }

  function count() {
    var mine = ++asked;
    fetch(form.getAttribute("data-count-url") + "?" + query(), {
      credentials: "same-origin", headers: { "Accept": "application/json" }
    })
      .then(function (response) {
        return response.json().then(function (body) { return [response.ok, body]; });
      })
      .then(function (answer) {
        if (mine !== asked) { return; }  // a newer selection was asked for meanwhile
        var ok = answer[0], body = answer[1];
        if (!ok) {
          say(body.detail || "This selection cannot be exported.", true);
        } else if (!body.exportable) {
          say(body.refusal.charAt(0).toUpperCase() + body.refusal.slice(1) + ".", true);
        } else {
          say("This selection holds " + body.count.toLocaleString("en") + " record" +
            (body.count === 1 ? "" : "s") + " you may view (at most " +
            body.limit.toLocaleString("en") + " in one export).", false);
        }
        shown.setAttribute("data-count", String(ok ? body.count : ""));
      })
      .catch(function () {
        if (mine === asked) { say("The count could not be fetched; use Count records.", true); }
      });
  }

  form.addEventListener("change", function () {
    clearTimeout(timer);
    timer = setTimeout(count, DELAY_MS);
  });
  count();
})();

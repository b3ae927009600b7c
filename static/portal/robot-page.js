/*
 * The robot page's status keeps itself up to date: [data-robot-status] names the status API
 * (GET /api/v1/robots/{id}/status/) and how often to ask it. The answer replaces the "last
 * seen" text (worded by the server) and the table of messages per second per topic.
 * [data-robot-latest] (the latest verified pose and image) and #robot-completeness (is any record
 * of the last hour missing) are taken from the page loaded again every data-refresh-seconds:
 * the server checks the pose and image against the chain, and counts the hour, each time.
 * While the tab is hidden nothing is asked; it asks again at once when it is shown. After a
 * failed answer it waits twice as long each time (at most 2 minutes), then goes back to the
 * usual pace once an answer comes.
 */
(function () {
  "use strict";

  var box = document.querySelector("[data-robot-status]");
  if (!box) { return; }
  var url = box.getAttribute("data-status-url");
  var pace = 1000 * (parseFloat(box.getAttribute("data-poll-seconds")) || 5);
  var MAX_WAIT = 120000;
  var wait = pace;
  var timer = null;

  function field(name) { return box.querySelector('[data-field="' + name + '"]'); }

  function utc(iso) {
    // "2026-11-29T02:03:04.123456Z" -> "2026-11-29 02:03:04 UTC", as the page prints times.
    return iso ? iso.replace("T", " ").replace(/\.\d+/, "").replace(/(Z|\+00:00)$/, "") + " UTC" : "–";
  }

  function cell(label, text, help) {
    var td = document.createElement("td");
    td.setAttribute("data-label", label);
    td.textContent = text;
    if (help) {
      var span = document.createElement("span");
      span.className = "help";
      span.textContent = " (" + help + ")";
      td.appendChild(span);
    }
    return td;
  }

  function code(text) {
    var td = document.createElement("td");
    td.setAttribute("data-label", "Topic");
    var c = document.createElement("code");
    c.textContent = text;
    td.appendChild(c);
    return td;
  }

  function show(status) {
    field("last-seen").textContent = status.last_seen_at ? "last seen " + status.last_seen : "never seen";
    field("last-seen-at").textContent = status.last_seen_at ?
      "(newest upload received " + utc(status.last_seen_at) + ")" : "";
    field("last-captured-at").textContent = utc(status.last_captured_at);
    var body = field("rates");
    var rows = status.topics.map(function (rate) {
      var tr = document.createElement("tr");
      tr.setAttribute("data-topic", rate.topic);
      tr.setAttribute("data-testid", "topic-rate");
      tr.appendChild(code(rate.topic));
      tr.appendChild(cell("Type", rate.type));
      tr.appendChild(cell("Last minute", rate.per_second_minute.toFixed(2) + "/s", String(rate.last_minute)));
      tr.appendChild(cell("Last hour", rate.per_second_hour.toFixed(2) + "/s", String(rate.last_hour)));
      return tr;
    });
    if (!rows.length) {
      var tr = document.createElement("tr");
      var td = document.createElement("td");
      td.colSpan = 4;
      td.textContent = "Nothing captured in the last hour.";
      tr.appendChild(td);
      rows.push(tr);
    }
    body.replaceChildren.apply(body, rows);
    box.setAttribute("data-updated", status.now);
  }

  function schedule(after) {
    clearTimeout(timer);
    timer = document.hidden ? null : setTimeout(tick, after);
  }

  function tick() {
    fetch(url, { credentials: "same-origin", headers: { "Accept": "application/json" } })
      .then(function (response) {
        if (!response.ok) { throw new Error("HTTP " + response.status); }
        return response.json();
      })
      .then(function (status) {
        show(status);
        wait = pace;
        schedule(wait);
      })
      .catch(function () {
        wait = Math.min(wait * 2, MAX_WAIT);
        schedule(wait);
      });
  }

  var latest = document.querySelector("[data-robot-latest]");
  var latestPace = 1000 * (parseFloat(latest && latest.getAttribute("data-refresh-seconds")) || 30);
  var latestWait = latestPace;
  var latestTimer = null;

  function refreshLatest() {
    fetch(window.location.href, { credentials: "same-origin", headers: { "Accept": "text/html" } })
      .then(function (response) {
        if (!response.ok) { throw new Error("HTTP " + response.status); }
        return response.text();
      })
      .then(function (html) {
        var page = new DOMParser().parseFromString(html, "text/html");
        // The latest pose and image, and the last hour's completeness, as the server has them now.
        [latest.id, "robot-completeness"].forEach(function (id) {
          var fresh = page.getElementById(id);
          var now = document.getElementById(id);
          if (fresh && now) { now.replaceWith(document.importNode(fresh, true)); }
        });
        latestWait = latestPace;
        scheduleLatest(latestWait);
      })
      .catch(function () {
        latestWait = Math.min(latestWait * 2, MAX_WAIT * 5);
        scheduleLatest(latestWait);
      });
  }

  function scheduleLatest(after) {
    clearTimeout(latestTimer);
    latestTimer = (document.hidden || !latest) ? null : setTimeout(refreshLatest, after);
  }

  document.addEventListener("visibilitychange", function () {
    if (document.hidden) {
      clearTimeout(timer); timer = null;
      clearTimeout(latestTimer); latestTimer = null;
    } else {
      schedule(0);
      scheduleLatest(latestPace);
    }
  });
  schedule(pace);
  scheduleLatest(latestPace);
})();

/*
 * series-plot.js: plots of verified records from the series API (GET /api/v1/records/series/),
 * with no library. Every record in the range is checked against the chain by the portal; the
 * plot draws the verified ones and says how many are not anchored yet (drawn once they are)
 * and how many were refused (never drawn).
 *
 * Put an element on a page and load this file (<script src=".../series-plot.js" defer>):
 *
 *   <div data-series-plot
 *        data-robot="ROBOT-UUID"            required: the robot's id
 *        data-topic="/odom"                 required: the topic
 *        data-fields="position.x,position.y" required: dotted paths into the record's message
 *        data-mode="xy"                     "xy": first field against the second (a trajectory,
 *                                           same scale on both axes); "time" (default): each
 *                                           field over time; "both": the path x-y beside the
 *                                           time plot, from one answer
 *        data-shape="path"                  optional: how the API thins the points: "path" (the
 *                                           default of "xy" and "both", along the x-y path) or
 *                                           "time" (each field's extremes per time bucket)
 *        data-since="ISO 8601" data-until="ISO 8601"   the capture-time range; without them,
 *        data-minutes="10"                  the last N minutes (default 10) up to now
 *        data-points="1000"                 points asked for at most (default 1000)
 *        data-refresh-seconds="5"           optional: every N seconds ask only for the records
 *                                           after the newest point (`after`), append them and
 *                                           drop those out of a data-minutes window
 *        data-replot-seconds="600"          optional: with refreshes, plot the whole window
 *                                           again this often (default 600)
 *        data-title="..." data-units="m"    optional: the title, and the values' unit
 *        data-mark="1764380000.5"           optional: a capture time (Unix seconds) to ring
 *        data-url="/api/v1/records/series/" optional: another address of the series API
 *   ></div>
 *
 * An element added later is plotted by window.AuthROSSeriesPlot.start(element).
 * The browser's session authenticates the call (a GET: no CSRF token needed). The element gets
 * an <svg> that scales to its width (readable from 390 px up) and a status line; its
 * data-state becomes "loading", "ready" or "error", and data-verified / data-refused /
 * data-not-anchored the counts;
 * data-missing how many records of the range's streams are missing (the series' `streams`),
 * which the status line says, with how many were deleted; data-method how the points were
 * thinned (the answer's `method`) and data-points-shown how many are drawn. Legends sit above
 * the plot area, never over the curves.
 */
(function () {
  "use strict";

  var SVG = "http://www.w3.org/2000/svg";
  var COLOURS = ["#0969da", "#cf222e", "#1a7f37", "#8250df", "#bf8700", "#1b7c83", "#953800", "#57606a"];
  var MARGIN = { left: 64, right: 16, top: 40, bottom: 48 };
  var LEGEND_ROW = 18;

  function node(name, attributes, text) {
    var element = document.createElementNS(SVG, name);
    Object.keys(attributes || {}).forEach(function (key) {
      element.setAttribute(key, attributes[key]);
    });
    if (text !== undefined) {
      element.textContent = text;
    }
    return element;
  }

  /* Round axis values (1, 2 or 5 times a power of ten apart) within [low, high]. */
  function ticks(low, high, wanted) {
    if (!(high > low)) {
      return [low];
    }
    var raw = (high - low) / wanted;
    var power = Math.pow(10, Math.floor(Math.log10(raw)));
    var step = [1, 2, 5, 10].map(function (m) { return m * power; })
      .filter(function (s) { return s >= raw; })[0];
    var decimals = Math.max(0, -Math.floor(Math.log10(step)));
    var values = [];
    for (var n = Math.ceil(low / step); n * step <= high + step * 1e-9; n++) {
      values.push({ value: n * step, label: (n * step).toFixed(decimals) });
    }
    return values;
  }

  /* Time ticks: round seconds, minutes or hours within [low, high] (Unix seconds), as UTC. */
  function timeTicks(low, high, wanted) {
    var steps = [1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200, 10800, 21600, 43200, 86400];
    var raw = (high - low) / wanted;
    var step = steps.filter(function (s) { return s >= raw; })[0] || 86400;
    var values = [];
    for (var t = Math.ceil(low / step) * step; t <= high; t += step) {
      var iso = new Date(t * 1000).toISOString();
      values.push({ value: t, label: step >= 60 ? iso.slice(11, 16) : iso.slice(11, 19) });
    }
    return values;
  }

  function extent(values) {
    var low = Infinity;
    var high = -Infinity;
    values.forEach(function (v) {
      if (v !== null && v !== undefined) {
        low = Math.min(low, v);
        high = Math.max(high, v);
      }
    });
    if (low === Infinity) {
      return null;
    }
    if (high - low < 1e-9) {
      var pad = Math.abs(low) * 0.05 || 0.5;
      return [low - pad, high + pad];
    }
    var margin = (high - low) * 0.05;
    return [low - margin, high + margin];
  }

  function utc(seconds) {
    return new Date(seconds * 1000).toISOString().replace("T", " ").slice(0, 19);
  }

  function shapeOf(element) {
    var data = element.dataset;
    return data.shape || (data.mode === "xy" || data.mode === "both" ? "path" : "time");
  }

  /* The window asked for now: [since, until) in ms. */
  function windowOf(element) {
    var data = element.dataset;
    var until = data.until ? new Date(data.until) : new Date();
    var since = data.since ? new Date(data.since) : new Date(until.getTime() - (Number(data.minutes) || 10) * 60000);
    return { since: since, until: until };
  }

  /* The series API's address for the window; with `after` (the newest point's t, as the API
     wrote it), only the newer records, thinned to `points`. */
  function query(element, range, after, points) {
    var data = element.dataset;
    var parameters = new URLSearchParams({
      robot: data.robot || "",
      topic: data.topic || "",
      fields: data.fields || "",
      since: range.since.toISOString(),
      until: range.until.toISOString(),
      points: String(points || data.points || "1000"),
      shape: shapeOf(element)
    });
    if (after !== undefined) {
      parameters.set("after", after);
    }
    return (data.url || "/api/v1/records/series/") + "?" + parameters.toString();
  }

  /* The title, cut with an ellipsis to the characters that fit the plot's width. */
  function fitted(text, width, size) {
    var most = Math.floor(width / (size * 0.56));
    return text.length > most ? text.slice(0, Math.max(most - 1, 1)) + "\u2026" : text;
  }

  /* Legend entries laid out in rows from `left`, wrapping before `right`: [{x, y}] per entry,
     and the rows' height. Each entry is a short stroke (or a dot) and its label. */
  function legendLayout(entries, left, right, top) {
    var x = left;
    var row = 0;
    var places = entries.map(function (entry) {
      var width = 26 + entry.label.length * 7 + 16;
      if (x > left && x + width > right) {
        x = left;
        row += 1;
      }
      var place = { x: x, y: top + 13 + row * LEGEND_ROW };
      x += width;
      return place;
    });
    return { places: places, height: entries.length ? (row + 1) * LEGEND_ROW : 0 };
  }

  function legendDraw(svg, entries, places) {
    entries.forEach(function (entry, index) {
      var at = places[index];
      var group = node("g", { "class": "series-plot-legend-entry" });
      if (entry.dot) {
        group.appendChild(node("circle", { cx: at.x + 10, cy: at.y - 4, r: 4, fill: entry.colour }));
      } else {
        group.appendChild(node("line", { x1: at.x, x2: at.x + 20, y1: at.y - 4, y2: at.y - 4, stroke: entry.colour, "stroke-width": 2 }));
      }
      group.appendChild(node("text", { x: at.x + 26, y: at.y, "font-size": 12, fill: "#24292f" }, entry.label));
      svg.appendChild(group);
    });
  }

  /* One plot of the answer's points at `WIDTH` px: the path (first field against the second,
     the same scale on both axes) when `xy`, else each field over time. */
  function draw(element, answer, xy, WIDTH) {
    var data = element.dataset;
    var HEIGHT = Math.round(Math.min(Math.max(WIDTH * 0.75, 280), 480));
    var units = data.units ? " (" + data.units + ")" : "";
    var points = answer.points;
    var svg = node("svg", {
      viewBox: "0 0 " + WIDTH + " " + HEIGHT,
      width: "100%",
      role: "img",
      "class": "series-plot-svg",
      "data-plot": xy ? "path" : "time",
      preserveAspectRatio: "xMidYMid meet"
    });
    var title = data.title || answer.fields.join(", ");
    if (data.mode === "both") {
      // Each plot's own title, the short one where the long does not fit (a phone).
      var room = Math.floor((WIDTH - MARGIN.left - MARGIN.right) / (15 * 0.56));
      var long = xy ? "Path, " + answer.fields.slice(0, 2).join(" against ") : answer.fields.join(", ") + " over time";
      title = long.length <= room ? long : (xy ? "Path" : "Over time");
    }
    var titleText = node("text", {
      x: MARGIN.left, y: 22, "font-size": 15, "font-weight": "bold", fill: "#24292f", "class": "series-plot-title"
    }, fitted(title, WIDTH - MARGIN.left - MARGIN.right, 15));
    titleText.appendChild(node("title", {}, title));
    svg.appendChild(titleText);
    // The legend: above the plot area, clear of the curves.
    var entries = xy ?
      [{ label: "first", colour: "#1a7f37", dot: true }, { label: "last", colour: "#cf222e", dot: true }] :
      (answer.fields.length > 1 ? answer.fields.map(function (field, index) {
        return { label: field, colour: COLOURS[index % COLOURS.length] };
      }) : []);
    var legend = legendLayout(entries, MARGIN.left, WIDTH - MARGIN.right, MARGIN.top);
    var area = {
      left: MARGIN.left, right: WIDTH - MARGIN.right,
      top: MARGIN.top + legend.height, bottom: HEIGHT - MARGIN.bottom
    };
    svg.appendChild(node("rect", {
      x: area.left, y: area.top, width: area.right - area.left, height: area.bottom - area.top,
      fill: "#ffffff", stroke: "#d0d7de", "class": "series-plot-area"
    }));
    var xs;
    var series;
    if (xy) {
      xs = points.map(function (p) { return p[1]; });
      series = [points.map(function (p) { return p[2]; })];
    } else {
      xs = points.map(function (p) { return p[0]; });
      series = answer.fields.map(function (_f, i) { return points.map(function (p) { return p[i + 1]; }); });
    }
    var xRange = extent(xs);
    var yRange = extent([].concat.apply([], series));
    if (!xRange || !yRange) {
      svg.appendChild(node("text", { x: area.left + 12, y: area.top + 28, "font-size": 14, fill: "#57606a" },
        "No verified values to plot in this range."));
      return svg;
    }
    legendDraw(svg, entries, legend.places);
    if (xy) {
      // Same scale on both axes: a trajectory keeps its shape.
      var perX = (xRange[1] - xRange[0]) / (area.right - area.left);
      var perY = (yRange[1] - yRange[0]) / (area.bottom - area.top);
      var per = Math.max(perX, perY);
      var cx = (xRange[0] + xRange[1]) / 2;
      var cy = (yRange[0] + yRange[1]) / 2;
      xRange = [cx - per * (area.right - area.left) / 2, cx + per * (area.right - area.left) / 2];
      yRange = [cy - per * (area.bottom - area.top) / 2, cy + per * (area.bottom - area.top) / 2];
    }
    function sx(v) { return area.left + (v - xRange[0]) / (xRange[1] - xRange[0]) * (area.right - area.left); }
    function sy(v) { return area.bottom - (v - yRange[0]) / (yRange[1] - yRange[0]) * (area.bottom - area.top); }
    // Numbers are shorter than times: a narrow path plot takes more ticks than a time plot.
    var wantedX = WIDTH < 480 ? (xy ? 5 : 3) : 6;
    var xTicks = xy ? ticks(xRange[0], xRange[1], wantedX) : timeTicks(xRange[0], xRange[1], wantedX);
    xTicks.forEach(function (tick) {
      var x = sx(tick.value).toFixed(1);
      svg.appendChild(node("line", { x1: x, x2: x, y1: area.top, y2: area.bottom, stroke: "#eaeef2" }));
      svg.appendChild(node("text", { x: x, y: area.bottom + 16, "font-size": 12, "text-anchor": "middle", fill: "#57606a" }, tick.label));
    });
    ticks(yRange[0], yRange[1], WIDTH < 480 ? 4 : 6).forEach(function (tick) {
      var y = sy(tick.value).toFixed(1);
      svg.appendChild(node("line", { x1: area.left, x2: area.right, y1: y, y2: y, stroke: "#eaeef2" }));
      svg.appendChild(node("text", { x: area.left - 6, y: Number(y) + 4, "font-size": 12, "text-anchor": "end", fill: "#57606a" }, tick.label));
    });
    var xLabel = xy ? answer.fields[0] + units : "capture time (UTC)";
    var yLabel = xy ? answer.fields[1] + units : (answer.fields.length === 1 ? answer.fields[0] : "value") + units;
    svg.appendChild(node("text", { x: (area.left + area.right) / 2, y: HEIGHT - 8, "font-size": 12, "text-anchor": "middle", fill: "#24292f" }, xLabel));
    svg.appendChild(node("text", {
      x: 14, y: (area.top + area.bottom) / 2, "font-size": 12, "text-anchor": "middle", fill: "#24292f",
      transform: "rotate(-90 14 " + (area.top + area.bottom) / 2 + ")"
    }, yLabel));
    series.forEach(function (values, index) {
      var path = [];
      values.forEach(function (v, at) {
        if (v !== null && xs[at] !== null) {
          path.push((path.length ? "L" : "M") + sx(xs[at]).toFixed(1) + " " + sy(v).toFixed(1));
        }
      });
      svg.appendChild(node("path", {
        d: path.join(" "), fill: "none", stroke: COLOURS[index % COLOURS.length], "stroke-width": 1.5,
        "class": "series-plot-line", "data-field": xy ? answer.fields.slice(0, 2).join(",") : answer.fields[index],
        "data-points": path.length
      }));
    });
    if (xy && points.length) {
      var first = points[0];
      var last = points[points.length - 1];
      svg.appendChild(node("circle", { cx: sx(first[1]), cy: sy(first[2]), r: 4, fill: "#1a7f37" }));
      svg.appendChild(node("circle", { cx: sx(last[1]), cy: sy(last[2]), r: 4, fill: "#cf222e" }));
    }
    var mark = Number(data.mark);
    if (data.mark && points.length) {
      var nearest = points.reduce(function (best, p) { return Math.abs(p[0] - mark) < Math.abs(best[0] - mark) ? p : best; });
      var mx = xy ? nearest[1] : nearest[0];
      var my = xy ? nearest[2] : nearest[1];
      if (mx !== null && my !== null) {
        svg.appendChild(node("circle", { cx: sx(mx), cy: sy(my), r: 7, fill: "none", stroke: "#24292f", "stroke-width": 2, "class": "series-plot-mark" }));
      }
    }
    var description = title + ": " + answer.verified + " verified records" +
      (points.length ? ", " + utc(points[0][0]) + " to " + utc(points[points.length - 1][0]) + " UTC" : "");
    svg.setAttribute("aria-label", description);
    return svg;
  }

  /* The element's plots of the answer: one, or (data-mode "both") the path beside the time
     plot, each at the width it is shown at. */
  function figures(element, answer) {
    var box = document.createElement("div");
    box.className = "series-plot-figures";
    var both = element.dataset.mode === "both" && answer.fields.length >= 2;
    var xy = element.dataset.mode === "xy" && answer.fields.length >= 2;
    var full = Math.max(240, Math.min(element.clientWidth || 640, both ? 1400 : 960));
    if (both) {
      box.className += " series-plot-pair";
      // Side by side where two fit at 420 px or more (the CSS grid's rule), else one above the other.
      var width = full >= 2 * 420 + 16 ? Math.floor((full - 16) / 2) : full;
      box.appendChild(draw(element, answer, true, width));
      box.appendChild(draw(element, answer, false, width));
    } else {
      box.appendChild(draw(element, answer, xy, full));
    }
    return box;
  }

  var THINNED = {
    "largest-triangle-three-buckets": "points kept along the path (the largest-triangle method, each a record)",
    "min-max-per-time-bucket": "points keep each time bucket's lowest and highest values (each a record)"
  };

  function status(element, answer) {
    var text = answer.source_records + " record" + (answer.source_records === 1 ? "" : "s") +
      " in range, " + answer.verified + " verified against the chain";
    if (answer.not_anchored_yet) {
      text += ", " + answer.not_anchored_yet + " not anchored yet (not drawn)";
    }
    if (answer.refused) {
      text += ", " + answer.refused + " refused";
    }
    if (answer.without_values) {
      text += ", " + answer.without_values + " without these fields";
    }
    if (THINNED[answer.method]) {
      text += "; " + answer.points.length + " " + THINNED[answer.method];
    }
    var gone = gaps(answer);
    if (gone.missing) {
      text += "; " + gone.missing + " record" + (gone.missing === 1 ? "" : "s") +
        " of the robot's count missing (no deletion explains " + (gone.missing === 1 ? "it" : "them") + ")";
    }
    if (gone.deleted) {
      text += "; " + gone.deleted + " deleted";
    }
    var tail = [];
    if (answer.tailNotAnchored) {
      tail.push(answer.tailNotAnchored + " not anchored yet");
    }
    if (answer.tailRefused) {
      tail.push(answer.tailRefused + " refused");
    }
    if (answer.refreshedAt && !answer.added && !tail.length) {
      text += "; no newer records at " + utc(answer.refreshedAt / 1000).slice(11) + " UTC";
    } else if (answer.refreshedAt) {
      text += "; since, " + answer.added + " newer record" + (answer.added === 1 ? "" : "s") +
        " verified and added (last refresh " + utc(answer.refreshedAt / 1000).slice(11) + " UTC" +
        (tail.length ? "; of the newest, not drawn: " + tail.join(", ") : "") + ")";
    }
    return text + ".";
  }

  // How many numbers of the range's streams (provenance v2's topic_seq) are missing, and how
  // many were deleted (by the owner or the retention policy): the series' `streams`.
  function gaps(answer) {
    var found = { missing: 0, deleted: 0 };
    (answer.streams || []).forEach(function (stream) {
      stream.gaps.forEach(function (gap) {
        found[gap.reason === "missing" ? "missing" : "deleted"] += gap.to - gap.from + 1;
      });
    });
    return found;
  }

  function ask(url) {
    return fetch(url, { credentials: "same-origin", headers: { Accept: "application/json" } })
      .then(function (response) {
        return response.json().then(function (body) {
          if (!response.ok) {
            throw new Error(body.detail || body.error || "the series could not be read (" + response.status + ")");
          }
          return body;
        });
      });
  }

  function show(element, answer) {
    var statusLine = element.querySelector(".series-plot-status");
    var old = element.querySelector(".series-plot-figures");
    var drawn = figures(element, answer);
    if (old) {
      element.replaceChild(drawn, old);
    } else {
      element.insertBefore(drawn, statusLine);
    }
    element.dataset.verified = answer.verified + (answer.added || 0);
    element.dataset.refused = answer.refused;
    element.dataset.notAnchored = answer.not_anchored_yet || 0;
    element.dataset.missing = gaps(answer).missing;
    element.dataset.method = answer.method;
    element.dataset.pointsShown = answer.points.length;
    element.dataset.state = "ready";
    statusLine.textContent = status(element, answer);
  }

  /* The whole window: every record in it checked, thinned by the API. */
  function load(element) {
    var statusLine = element.querySelector(".series-plot-status");
    element.dataset.state = "loading";
    statusLine.textContent = "Checking the records of this range against the chain\u2026";
    var range = windowOf(element);
    return ask(query(element, range))
      .then(function (answer) {
        element.seriesHeld = { answer: answer, plottedAt: Date.now(), range: range };
        show(element, answer);
      })
      .catch(function (error) {
        element.seriesHeld = null;
        element.dataset.state = "error";
        statusLine.textContent = "No plot: " + (typeof error.message === "string" ? error.message : "the series could not be read") + ".";
      });
  }

  /* Only the records after the newest point: appended, and those out of the window dropped.
     Their counts are added to the plot's; the portal logs them under the plot's access line. */
  function refresh(element, every) {
    var held = element.seriesHeld;
    var answer = held.answer;
    var range = windowOf(element);
    var most = Number(element.dataset.points) || 1000;
    var seconds = Math.max((range.until - range.since) / 1000, 1);
    var points = Math.min(most, Math.max(8, Math.ceil(most * every / seconds)));
    element.dataset.refreshing = "1";
    var newest = answer.points[answer.points.length - 1][0];
    return ask(query(element, range, String(newest), points))
      .then(function (chunk) {
        var since = range.since.getTime() / 1000;
        // The whole plot's counts stay those of its whole answer; a refresh tells how many
        // records it verified and added (thinned like the rest). Records after the newest
        // point not verified (not anchored yet, most often) are asked for again by the next
        // refresh, and drawn once they pass.
        var added = chunk.points.filter(function (p) { return p[0] > newest; });
        var merged = {
          fields: answer.fields,
          points: answer.points.concat(added).filter(function (p) { return p[0] >= since; }),
          source_records: answer.source_records,
          verified: answer.verified,
          refused: answer.refused,
          not_anchored_yet: answer.not_anchored_yet,
          without_values: answer.without_values,
          streams: (answer.streams || []).concat(chunk.streams || []),
          method: answer.method === "all" ? chunk.method : answer.method,
          added: (answer.added || 0) + chunk.verified,
          tailRefused: chunk.refused,
          tailNotAnchored: chunk.not_anchored_yet,
          refreshedAt: Date.now()
        };
        held.answer = merged;
        element.dataset.refreshes = Number(element.dataset.refreshes || 0) + 1;
        show(element, merged);
      })
      .catch(function (error) {
        var statusLine = element.querySelector(".series-plot-status");
        statusLine.textContent = status(element, answer).replace(/\.$/, "") + "; the last refresh failed: " +
          (typeof error.message === "string" ? error.message : "the series could not be read") + ".";
      })
      .then(function () { delete element.dataset.refreshing; });
  }

  function start(element) {
    var statusLine = document.createElement("p");
    statusLine.className = "series-plot-status help";
    statusLine.setAttribute("role", "status");
    element.appendChild(statusLine);
    load(element);
    var every = Number(element.dataset.refreshSeconds);
    var replot = 1000 * (Number(element.dataset.replotSeconds) || 600);
    var most = Number(element.dataset.points) || 1000;
    if (every > 0) {
      every = Math.max(every, 1);
      window.setInterval(function () {
        if (document.hidden || element.dataset.state === "loading" || element.dataset.refreshing) {
          return;
        }
        var held = element.seriesHeld;
        // The whole window again now and then (records uploaded late, gaps across refreshes),
        // or when the appended points outgrow what was asked for.
        if (!held || !held.answer.points.length || Date.now() - held.plottedAt >= replot ||
            held.answer.points.length > 2 * most) {
          load(element);
        } else {
          refresh(element, every);
        }
      }, every * 1000);
    }
  }

  function startAll() {
    Array.prototype.forEach.call(document.querySelectorAll("[data-series-plot]"), start);
  }

  // For elements added after the page loaded: window.AuthROSSeriesPlot.start(element).
  window.AuthROSSeriesPlot = { start: start };

  if (document.readyState === "loading") {
    document.addEventListener("DOMContentLoaded", startAll);
  } else {
    startAll();
  }
})();

// cubecal's live page: draws the station's events (src/live/mod.rs). It decides nothing: every
// figure, reason and verdict shown comes from an event as the station emitted it.
"use strict";
(function () {
  var $ = function (id) { return document.getElementById(id); };
  var body = document.body;
  var SVG = "http://www.w3.org/2000/svg";
  var frames = 0, latencies = [], prompts = 0, errors = 0, connectedAt = 0;
  var angles = {}, total = null, lastSeen = Date.now(), source = null;
  var faceColours = ["#00e676", "#ff9100", "#40c4ff", "#ea80fc", "#ffff00", "#ff5252"];

  window.addEventListener("error", function () { errors += 1; body.dataset.errors = String(errors); });

  function text(el, s) { el.textContent = s; return el; }
  function el(tag, cls, s) {
    var e = document.createElement(tag);
    if (cls) { e.className = cls; }
    if (s !== undefined) { e.textContent = s; }
    return e;
  }
  function svg(tag, attrs) {
    var e = document.createElementNS(SVG, tag);
    Object.keys(attrs).forEach(function (k) { e.setAttribute(k, attrs[k]); });
    return e;
  }
  function num(x, digits) {
    if (x === null || x === undefined || !isFinite(x)) { return String(x); }
    if (Math.abs(x) >= 1e-3 && Math.abs(x) < 1e6) { return x.toFixed(digits === undefined ? 4 : digits).replace(/\.?0+$/, ""); }
    return x.toExponential(2);
  }
  function status(s) { text($("status"), s); }
  function pose(i) { return "pose " + (i + 1) + (total ? "/" + total : ""); }

  function reset() {
    frames = 0; latencies = []; window.cubecalLatencies = latencies; prompts = 0; total = null; angles = {};
    body.dataset.frames = "0"; body.dataset.prompts = "0"; body.dataset.verdict = "";
    body.dataset.coverage = ""; body.dataset.latencyMaxMs = ""; body.dataset.latencyMeanMs = "";
    body.dataset.latencyP95Ms = ""; body.dataset.latencyCount = "0";
    ["poses", "checks", "sigma"].forEach(function (id) { $(id).tBodies[0].textContent = ""; });
    text($("notes"), ""); text($("prompt"), ""); $("overlay").textContent = "";
    $("coverage").textContent = ""; text($("coveragetext"), ""); text($("sigmasource"), "");
    var v = text($("verdict"), "no verdict yet"); v.className = "";
    $("report").className = ""; $("report").removeAttribute("src");
    text($("reportmsg"), "the run's report appears here when it is done");
  }

  function onFrame(d) {
    var now = Date.now();
    $("frame").src = "data:image/jpeg;base64," + d.jpeg;
    var latency = now - d.grabbed_unix_ms;
    frames += 1;
    body.dataset.frames = String(frames);
    body.dataset.lastSequence = String(d.sequence);
    // The latest frame replayed to a page that just connected is not a live one: not counted.
    if (d.sent_unix_ms >= connectedAt) {
      latencies.push(latency);
      window.cubecalLatencies = latencies;
      var sorted = latencies.slice().sort(function (a, b) { return a - b; });
      var sum = sorted.reduce(function (a, b) { return a + b; }, 0);
      body.dataset.latencyCount = String(sorted.length);
      body.dataset.latencyMaxMs = sorted[sorted.length - 1].toFixed(1);
      body.dataset.latencyMeanMs = (sum / sorted.length).toFixed(1);
      body.dataset.latencyP95Ms = sorted[Math.min(sorted.length - 1, Math.floor(0.95 * sorted.length))].toFixed(1);
    }
    var o = $("overlay");
    o.setAttribute("viewBox", "-0.5 -0.5 " + d.width + " " + d.height);
    if (o.dataset.sequence !== String(d.sequence)) { o.textContent = ""; }
    text($("frameinfo"), pose(d.index) + ", frame " + d.sequence + " (" + d.width + "×" + d.height +
      "), grab to screen " + latency.toFixed(0) + " ms");
  }

  function onDetected(d) {
    var o = $("overlay");
    o.setAttribute("viewBox", "-0.5 -0.5 " + d.width + " " + d.height);
    o.dataset.sequence = String(d.sequence);
    o.textContent = "";
    var r = Math.max(d.width, d.height) / 250;
    d.faces.forEach(function (f, i) {
      var g = svg("g", { fill: "none", stroke: faceColours[i % faceColours.length], "stroke-width": r / 2 });
      var t = svg("title", {}); t.textContent = f.face + ": " + f.corners.length + " corners"; g.appendChild(t);
      f.corners.forEach(function (c) { g.appendChild(svg("circle", { cx: c[0], cy: c[1], r: r })); });
      o.appendChild(g);
    });
  }

  function onCoverage(d) {
    var c = $("coverage"), cols = d.grid[0], rows = d.grid[1];
    c.setAttribute("viewBox", "0 0 " + cols + " " + rows);
    c.textContent = "";
    var max = Math.max.apply(null, d.counts.concat([1]));
    d.counts.forEach(function (n, i) {
      var x = i % cols, y = Math.floor(i / cols);
      var a = n > 0 ? 0.25 + 0.75 * n / max : 0;
      c.appendChild(svg("rect", { x: x + 0.04, y: y + 0.04, width: 0.92, height: 0.92,
        fill: n > 0 ? "rgba(46,125,50," + a.toFixed(3) + ")" : "#eceff1", "data-count": n }));
    });
    body.dataset.coverage = String(d.fraction);
    text($("coveragetext"), Math.round(100 * d.fraction) + " % (" + d.cells_covered + "/" + d.cells_total +
      " cells, " + d.views + " view(s))");
  }

  function sigmaRows(rows, from) {
    var tb = $("sigma").tBodies[0];
    tb.textContent = "";
    rows.forEach(function (s) {
      var tr = el("tr");
      var ok = s.value <= s.target;
      tr.appendChild(el("td", "", s.name));
      tr.appendChild(el("td", "num", num(s.value)));
      tr.appendChild(el("td", "num", num(s.target)));
      tr.appendChild(el("td", ok ? "ok" : "bad", ok ? "reached" : "above"));
      tb.appendChild(tr);
    });
    text($("sigmasource"), "(" + from + ")");
  }

  function poseRow(d, result, cls) {
    var tb = $("poses").tBodies[0];
    var tr = el("tr");
    tr.appendChild(el("td", "num", String(d.index + 1)));
    tr.appendChild(el("td", "", d.name));
    var a = angles[d.index];
    tr.appendChild(el("td", "num", a === null || a === undefined ? "" : num(a, 1) + "°"));
    tr.appendChild(el("td", cls, result));
    tb.appendChild(tr);
  }

  function onVerdict(v) {
    var b = text($("verdict"), v.pass ? "PASS" : "FAIL");
    b.className = v.pass ? "pass" : "fail";
    body.dataset.verdict = v.pass ? "pass" : "fail";
    var tb = $("checks").tBodies[0];
    tb.textContent = "";
    var sigmas = [];
    v.checks.forEach(function (c) {
      var tr = el("tr");
      tr.appendChild(el("td", "", c.name));
      tr.appendChild(el("td", "num", num(c.value)));
      tr.appendChild(el("td", "num", num(c.threshold)));
      tr.appendChild(el("td", c.pass ? "ok" : "bad", c.pass ? "ok" : "FAIL" + (c.hint ? ": " + c.hint : "")));
      tb.appendChild(tr);
      if (c.name.indexOf("sigma_") === 0) { sigmas.push({ name: c.name.slice(6), value: c.value, target: c.threshold }); }
    });
    (v.fixed || []).forEach(function (f) {
      $("notes").appendChild(el("div", "", "fixed: " + f.name + " = " + num(f.value) + " (" + f.reason + ")"));
    });
    if (sigmas.length) { sigmaRows(sigmas, "the solve"); }
  }

  function onStation(d) {
    switch (d.event) {
      case "opened":
        status("camera " + d.source + " (" + d.width + "×" + d.height + "), turntable " + d.turntable); break;
      case "homing":
        status("homing the turntable");
        if (d.instruction) {
          prompts += 1; body.dataset.prompts = String(prompts);
          text($("prompt"), "homing: " + d.instruction);
        }
        break;
      case "pose_planned":
        total = d.total; angles[d.index] = d.angle_deg;
        status(pose(d.index) + (d.angle_deg !== null ? " at " + num(d.angle_deg, 1) + "°" : "") + " planned");
        if (d.instruction) {
          prompts += 1; body.dataset.prompts = String(prompts);
          text($("prompt"), pose(d.index) + ": " + d.instruction);
        } else { text($("prompt"), ""); }
        break;
      case "pose_chosen":
        sigmaRows(d.predicted.map(function (s) { return { name: s.name, value: s.sigma, target: s.target }; }),
          "predicted after " + pose(d.index));
        break;
      case "tilting": status(pose(d.index) + ": tilting to " + num(d.tilt_deg, 1) + "°"); break;
      case "moving": status(pose(d.index) + ": turning to " + num(d.angle_deg, 1) + "°"); break;
      case "settled": angles[d.index] = d.angle_deg; status(pose(d.index) + ": settled at " + num(d.angle_deg, 1) + "°"); break;
      case "frame_grabbed": status(pose(d.index) + ": frame " + d.sequence + " grabbed, detecting"); break;
      case "detected": onDetected(d); break;
      case "view_accepted":
        poseRow(d, "accepted: " + d.faces + " face(s), " + d.corners + " corners", "ok"); break;
      case "view_rejected": poseRow(d, "rejected: " + d.reason, "bad"); break;
      case "coverage": onCoverage(d); break;
      case "solving":
        text($("prompt"), "");
        status("solving from " + d.views + " view(s), " + d.points + " corners"); break;
      case "verdict": onVerdict(d.verdict); status("verdict: " + (d.verdict.pass ? "PASS" : "FAIL")); break;
      case "profile_spooled":
        $("notes").appendChild(el("div", "", "profile store " + d.store + " unreachable: the profile waits in " + d.path)); break;
      case "spool_drained":
        $("notes").appendChild(el("div", "", "spool: " + (d.committed + d.already_stored) + " committed to " + d.store)); break;
      default: break;
    }
  }

  function onRun(d) {
    body.dataset.state = d.state;
    if (d.state === "running") { reset(); body.dataset.state = "running"; status("run " + d.run + " started"); return; }
    if (d.error) { status("run " + d.run + " ended: " + d.error); }
    else if (!body.dataset.verdict) { status("run " + d.run + " ended (exit " + d.exit_code + ")"); }
    if (d.report) {
      var f = $("report"); f.src = "/report?run=" + d.run; f.className = "on";
      text($("reportmsg"), "report of run " + d.run + ":");
      body.dataset.report = "shown";
    }
  }

  function connect() {
    if (source) { source.close(); }
    lastSeen = Date.now();
    source = new EventSource("/events");
    var on = function (name, f) {
      source.addEventListener(name, function (e) {
        lastSeen = Date.now();
        var d;
        try { d = JSON.parse(e.data); } catch (err) { return; }
        f(d);
      });
    };
    on("hello", function (d) {
      reset();
      connectedAt = d.now_unix_ms;
      body.dataset.state = d.running ? "running" : (d.run ? "done" : "waiting");
      if (d.control) { $("control").className = "on"; }
      if (!d.run) { status("waiting for a run"); }
    });
    on("frame", onFrame);
    on("station", onStation);
    on("run", onRun);
    source.onopen = function () { lastSeen = Date.now(); };
  }
  // A stream silent for longer than three keep-alives is dead: open a new one (it replays the run).
  setInterval(function () { if (Date.now() - lastSeen > 45000) { connect(); } }, 5000);

  function post(path) {
    var msg = $("controlmsg");
    text(msg, "…");
    fetch(path, { method: "POST", headers: { "Authorization": "Bearer " + $("token").value } })
      .then(function (r) { return r.text().then(function (t) { text(msg, r.ok ? "ok" : r.status + ": " + t); }); })
      .catch(function (e) { text(msg, String(e)); });
  }
  $("start").addEventListener("click", function () { post("/api/start"); });
  $("stop").addEventListener("click", function () { post("/api/stop"); });
  connect();
})();

/* canopy-kit report: table search and sort; with the embedded explorer data and plotly.js,
   the orchard map, volume histogram, per-tree drill-down and downloads. Loads nothing. */
(function () {
  "use strict";

  // -- sortable tables (click a header) ------------------------------------------------
  document.querySelectorAll("table.sortable").forEach(function (table) {
    table.querySelectorAll("th").forEach(function (th, col) {
      th.addEventListener("click", function () {
        var body = table.tBodies[0];
        var rows = Array.prototype.slice.call(body.rows);
        var asc = !th.classList.contains("asc");
        table.querySelectorAll("th").forEach(function (h) { h.classList.remove("asc", "desc"); });
        th.classList.add(asc ? "asc" : "desc");
        rows.sort(function (a, b) {
          var x = a.cells[col], y = b.cells[col];
          var xv = x.dataset.v, yv = y.dataset.v;
          var xn = xv !== undefined && xv !== "", yn = yv !== undefined && yv !== "";
          var r;
          if (xn && yn) { r = parseFloat(xv) - parseFloat(yv); }
          else if (xn !== yn && (xv !== undefined || yv !== undefined)) { return xn ? -1 : 1; } // blanks last
          else { r = x.textContent.localeCompare(y.textContent, undefined, {numeric: true}); }
          return asc ? r : -r;
        });
        rows.forEach(function (r) { body.appendChild(r); });
      });
    });
  });

  // -- search the per-tree table --------------------------------------------------------
  var treeTable = document.getElementById("trees");
  var search = document.getElementById("tree-search");
  var count = document.getElementById("tree-count");
  function filterTrees() {
    if (!treeTable) { return; }
    var terms = (search ? search.value : "").toLowerCase().split(/\s+/).filter(Boolean);
    var rows = treeTable.tBodies[0].rows, shown = 0;
    for (var i = 0; i < rows.length; i++) {
      var text = rows[i].textContent.toLowerCase();
      var ok = terms.every(function (t) { return text.indexOf(t) >= 0; });
      rows[i].style.display = ok ? "" : "none";
      if (ok) { shown++; }
    }
    if (count) { count.textContent = shown + " of " + rows.length + " trees shown"; }
  }
  if (search) { search.addEventListener("input", filterTrees); }

  var dataEl = document.getElementById("explorer-data");
  if (!dataEl || typeof Plotly === "undefined") { return; }
  var D = JSON.parse(dataEl.textContent);
  var byId = {}, recIndex = {};
  D.trees.forEach(function (t, i) { byId[t.tree_id] = t; recIndex[t.tree_id] = i; });
  var label = {};
  D.columns.forEach(function (c) { label[c.key] = c.label; });
  var config = {displaylogo: false, responsive: true, scrollZoom: true};

  function fmt(v, digits) {
    if (v === null || v === undefined || v === "") { return "–"; }
    if (typeof v === "number") { return v.toFixed(digits === undefined ? 2 : digits); }
    return String(v);
  }
  function decode(b64, Type) {
    var bin = atob(b64), bytes = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) { bytes[i] = bin.charCodeAt(i); }
    return new Type(bytes.buffer);
  }
  function xyz(b64) { // int16 centimetres -> three arrays of metres
    var a = decode(b64, Int16Array), n = a.length / 3, x = [], y = [], z = [];
    for (var i = 0; i < n; i++) { x.push(a[3 * i] / 100); y.push(a[3 * i + 1] / 100); z.push(a[3 * i + 2] / 100); }
    return [x, y, z];
  }

  // -- colours -----------------------------------------------------------------------------
  var VIRIDIS = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];
  function viridis(f) {
    if (!(f >= 0)) { return "rgb(180,180,180)"; }
    f = Math.min(1, f) * (VIRIDIS.length - 1);
    var k = Math.min(Math.floor(f), VIRIDIS.length - 2), u = f - k, a = VIRIDIS[k], b = VIRIDIS[k + 1];
    return "rgb(" + [0, 1, 2].map(function (j) { return Math.round(a[j] + u * (b[j] - a[j])); }).join(",") + ")";
  }
  var FLAG_COLOURS = {"no flag": "#2e7d32", "segment flag": "#ef6c00", "volume flag": "#c62828",
                      "drone crown flag": "#6a1b9a"};
  function flagOf(t) {
    if (t.volume_flags) { return "volume flag"; }
    if (t.segment_flags) { return "segment flag"; }
    if (t.aerial_flag) { return "drone crown flag"; }
    return "no flag";
  }
  // The recommended estimator's volume leads: the map's colours, the hover, the histogram.
  var VOL = D.recommended && D.recommended.column in (D.trees[0] || {}) ? D.recommended.column : "volume_alpha_m3";
  var VOLUMES = [VOL].concat(["volume_alpha_m3", "volume_convex_hull_m3", "aerial_sphere_volume_m3"]
    .filter(function (k) { return k !== VOL; }));
  var vols = D.trees.map(function (t) { return t[VOL]; }).filter(function (v) { return v !== null; });
  var vmin = vols.length ? Math.min.apply(null, vols) : 0, vmax = vols.length ? Math.max.apply(null, vols) : 1;
  function volumeColour(t) {
    var v = t[VOL];
    return v === null || v === undefined ? viridis(NaN) : viridis(vmax > vmin ? (v - vmin) / (vmax - vmin) : 0.5);
  }
  function hoverText(t) {
    var lines = ["<b>" + t.tree_id + "</b> (row " + t.row + ")"];
    VOLUMES.concat(["crown_diameter_m", "height_m"])
      .forEach(function (k) { if (k in t) { lines.push(label[k] + ": " + fmt(t[k])); } });
    ["volume_flags", "segment_flags", "aerial_flag"].forEach(function (k) {
      if (t[k]) { lines.push(label[k] + ": " + t[k]); } });
    return lines.join("<br>");
  }

  // -- the map ---------------------------------------------------------------------------------
  var mapEl = document.getElementById("map");
  var mode = "volume";
  var MAX_LABELS = 60; // more tree IDs than this on the map overlap: hover tells them then
  var crownIds = Object.keys(D.map.footprints).filter(function (id) { return id in byId; });
  function mapTraces() {
    var traces = [];
    if (D.map.drive.length) {
      traces.push({type: "scatter", mode: "lines", name: "drive", hoverinfo: "skip",
                   x: D.map.drive.map(function (p) { return p[0]; }), y: D.map.drive.map(function (p) { return p[1]; }),
                   line: {color: "rgba(90,90,90,0.5)", width: 1}});
    }
    D.map.rows.forEach(function (r, k) {
      traces.push({type: "scatter", mode: "lines", name: "fitted rows", legendgroup: "rows", showlegend: k === 0,
                   hoverinfo: "skip", x: r.xy.map(function (p) { return p[0]; }), y: r.xy.map(function (p) { return p[1]; }),
                   line: {color: "#555", width: 1, dash: "dash"}});
    });
    crownIds.forEach(function (id) {
      var ring = D.map.footprints[id].concat([D.map.footprints[id][0]]), t = byId[id];
      traces.push({type: "scatter", mode: "lines", fill: "toself", name: id, showlegend: false,
                   meta: {crown: id}, hoveron: "fills", hoverinfo: "text", text: hoverText(t),
                   x: ring.map(function (p) { return p[0]; }), y: ring.map(function (p) { return p[1]; }),
                   line: {color: "rgba(30,30,30,0.7)", width: 1}, fillcolor: crownColour(t)});
    });
    traces.push(markerTrace());
    return traces;
  }
  function crownColour(t) {
    var c = mode === "flag" ? FLAG_COLOURS[flagOf(t)] : volumeColour(t);
    return c.replace(/^rgb\((.*)\)$/, "rgba($1,0.55)").replace(/^#(..)(..)(..)$/, function (_, r, g, b) {
      return "rgba(" + parseInt(r, 16) + "," + parseInt(g, 16) + "," + parseInt(b, 16) + ",0.55)"; });
  }
  function markerTrace() {
    var marker = {size: 9, line: {color: "white", width: 1}};
    if (mode === "flag") {
      marker.color = D.trees.map(function (t) { return FLAG_COLOURS[flagOf(t)]; });
    } else {
      marker.color = D.trees.map(function (t) { return t[VOL]; });
      marker.colorscale = "Viridis"; marker.cmin = vmin; marker.cmax = vmax; marker.showscale = true;
      marker.colorbar = {title: {text: label[VOL] || VOL, side: "right"}, thickness: 14};
    }
    return {type: "scatter", mode: D.trees.length <= MAX_LABELS ? "markers+text" : "markers", name: "trees", meta: {markers: true}, showlegend: mode !== "flag",
            x: D.trees.map(function (t) { return t.x; }), y: D.trees.map(function (t) { return t.y; }),
            text: D.trees.map(function (t) { return t.tree_id; }), textposition: "top center",
            textfont: {size: 10, color: "#222"}, customdata: D.trees.map(function (t) { return t.tree_id; }),
            hovertext: D.trees.map(hoverText), hoverinfo: "text", marker: marker};
  }
  function flagLegend() {
    if (mode !== "flag") { return []; }
    var present = {};
    D.trees.forEach(function (t) { present[flagOf(t)] = true; });
    return Object.keys(FLAG_COLOURS).filter(function (k) { return present[k]; }).map(function (k) {
      return {type: "scatter", mode: "markers", x: [null], y: [null], name: k, hoverinfo: "skip",
              marker: {color: FLAG_COLOURS[k], size: 10}};
    });
  }
  function drawMap() {
    var layout = {margin: {l: 55, r: 10, t: 10, b: 45}, hovermode: "closest", dragmode: "pan",
                  xaxis: {title: {text: "x east (local) [m]"}, zeroline: false},
                  yaxis: {title: {text: "y north (local) [m]"}, scaleanchor: "x", scaleratio: 1, zeroline: false},
                  legend: {orientation: "h", y: 1.02, x: 0, yanchor: "bottom"}, plot_bgcolor: "#fbfcfa",
                  annotations: [{text: "N ↑", xref: "paper", yref: "paper", x: 0.99, y: 0.99, showarrow: false,
                                 font: {size: 16}, bgcolor: "rgba(255,255,255,0.8)"}]};
    if (mapEl.layout && mapEl.layout.shapes) { layout.shapes = mapEl.layout.shapes; }
    Plotly.react(mapEl, mapTraces().concat(flagLegend()), layout, config);
  }
  if (mapEl) {
    drawMap();
    mapEl.on("plotly_click", function (ev) {
      var p = ev.points && ev.points[0];
      if (!p) { return; }
      var id = p.customdata || (p.data.meta && p.data.meta.crown);
      if (id) { showTree(id); }
    });
    var sel = document.getElementById("map-colour");
    if (sel && sel.options.length) { sel.options[0].textContent = (label[VOL] || VOL).replace(/ \[m³\]$/, ""); }
    if (sel) { sel.addEventListener("change", function () { mode = sel.value; drawMap(); }); }
  }

  // -- histogram -------------------------------------------------------------------------------
  var histEl = document.getElementById("hist");
  if (histEl && !vols.length) { histEl.parentNode.style.display = "none"; }
  if (histEl && vols.length) {
    var hist = [], series = [], all = [];
    VOLUMES.forEach(function (k) {
      if (!(k in (D.trees[0] || {}))) { return; }
      var v = D.trees.filter(function (t) { return k !== "aerial_sphere_volume_m3" || !t.aerial_flag; })
        .map(function (t) { return t[k]; }).filter(function (x) { return x !== null && x !== undefined; });
      series.push([k, v]); all = all.concat(v);
    });
    var lo = Math.min.apply(null, all), hi = Math.max.apply(null, all);
    var raw = hi > lo ? (hi - lo) / Math.min(20, Math.max(5, 2 * Math.ceil(Math.sqrt(D.trees.length)))) : 1;
    var pow = Math.pow(10, Math.floor(Math.log10(raw)));
    var size = [1, 2, 5, 10].map(function (m) { return m * pow; }).find(function (v) { return v >= raw; });
    var start = Math.floor(lo / size) * size, end = (Math.floor(hi / size) + 1) * size;  // round bin edges
    series.forEach(function (kv) { // one set of bins for every method, so the bars compare
      var name = (label[kv[0]] || kv[0]) + (kv[0] === "aerial_sphere_volume_m3" ? " (flagged crowns left out)" : "");
      hist.push({type: "histogram", name: name, opacity: 0.85, x: kv[1],
                 xbins: {start: start, end: end, size: size}});
    });
    Plotly.newPlot(histEl, hist, {barmode: "group", bargap: 0.15, margin: {l: 50, r: 10, t: 50, b: 70},
      title: {text: "Volume per tree", font: {size: 14}, x: 0, xref: "paper", xanchor: "left",
              y: 1, yref: "paper", yanchor: "bottom", pad: {b: 6}},  // below the mode bar xaxis: {title: {text: "volume [m³]"}, dtick: 2 * size, tick0: 0},
      yaxis: {title: {text: "trees"}}, legend: {orientation: "h", y: -0.32}}, config);
  }

  // -- downloads: Blobs made from the embedded text --------------------------------------
  var dl = document.getElementById("downloads");
  if (dl) {
    D.downloads.forEach(function (f) {
      var a = document.createElement("a");
      a.href = URL.createObjectURL(new Blob([f.text], {type: f.mime}));
      a.download = f.name; a.textContent = f.name; a.dataset.name = f.name;
      dl.appendChild(a);
    });
  }

  // -- drill-down --------------------------------------------------------------------------------
  var GROUPS = ["Flags", "Volumes", "Against the drone and the truth", "Tree"];
  function groupOf(key) { // the drill-down's sections: what to look at first, first
    if (/flag/.test(key)) { return "Flags"; }
    if (/^(error_|true_|truth_|aerial_)/.test(key)) { return "Against the drone and the truth"; }
    if (/volume/.test(key)) { return "Volumes"; }
    return "Tree";
  }
  function showTree(id, quiet) { // quiet: do not scroll the panel into view
    var t = byId[id], d = D.details[id];
    if (!t) { return; }
    document.getElementById("drill-title").textContent = "Tree " + id;
    document.getElementById("drill-hint").textContent = "Click another tree on the map or a row of the table.";
    if (mapEl) { // ring the shown tree on the map
      var r = Math.max(0.5, (t.crown_diameter_m || 2) / 2 + 0.4);
      Plotly.relayout(mapEl, {shapes: [{type: "circle", xref: "x", yref: "y", x0: t.x - r, x1: t.x + r,
        y0: t.y - r, y1: t.y + r, line: {color: "#d32f2f", width: 3}}]});
    }
    var summary = document.getElementById("drill-summary");
    summary.dataset.tree = id;
    summary.dataset.points = d ? d.n_points : "";
    summary.textContent = d ? (d.n_points.toLocaleString("en") + " LiDAR points (" + d.n_shown.toLocaleString("en") +
      " shown; metres from the tree's centre and lowest point); surfaces as the volume stage measured them: " + d.surfaces.map(function (s) {
        return s.name + " " + s.volume_m3.toFixed(2) + " m³"; }).join(", ")) : "no points for this tree";
    if (treeTable) {
      Array.prototype.forEach.call(treeTable.tBodies[0].rows, function (r) {
        r.classList.toggle("selected", r.dataset.id === id); });
    }
    if (d) { draw3d(d); drawOrtho(id, d); }
    var body = document.querySelector("#drill-values tbody");
    body.innerHTML = "";
    GROUPS.forEach(function (g) {
      var cols = D.columns.filter(function (c) {
        var v = t[c.key];
        return groupOf(c.key) === g && v !== null && v !== undefined && v !== ""; });
      if (!cols.length) { return; }
      var head = document.createElement("tr"), th = document.createElement("th");
      th.colSpan = 2; th.textContent = g; head.appendChild(th); body.appendChild(head);
      cols.forEach(function (c) {
        var v = t[c.key];
        var tr = document.createElement("tr"), k = document.createElement("td"), val = document.createElement("td");
        k.textContent = c.label; k.title = c.key; val.textContent = c.numeric ? fmt(v, c.digits) : String(v);
        val.dataset.key = c.key; if (c.numeric) { val.className = "num"; val.dataset.v = v; }
        tr.appendChild(k); tr.appendChild(val); body.appendChild(tr);
      });
    });
    var drill = document.getElementById("drill");
    if (!quiet && drill.scrollIntoView) { drill.scrollIntoView({block: "nearest"}); }
  }
  function draw3d(d) {
    var p = xyz(d.points);
    var traces = [{type: "scatter3d", mode: "markers", name: "points", x: p[0], y: p[1], z: p[2],
                   marker: {size: 1.6, color: p[2], colorscale: "Greens", reversescale: true, opacity: 0.9},
                   hoverinfo: "skip"}];
    var colours = ["#1565c0", "#ef6c00"];
    d.surfaces.forEach(function (s, k) {
      var v = xyz(s.vertices), f = decode(s.faces, s.index_bytes === 4 ? Uint32Array : Uint16Array), i = [], j = [], kk = [];
      for (var n = 0; n < f.length; n += 3) { i.push(f[n]); j.push(f[n + 1]); kk.push(f[n + 2]); }
      traces.push({type: "mesh3d", name: s.name + " (" + s.volume_m3.toFixed(2) + " m³)", showlegend: true,
                   x: v[0], y: v[1], z: v[2], i: i, j: j, k: kk, color: colours[k % 2], opacity: 0.25,
                   flatshading: true, hoverinfo: "name",
                   visible: s.name.indexOf("convex") === 0 ? "legendonly" : true});
    });
    Plotly.react("drill-3d", traces, {margin: {l: 0, r: 0, t: 0, b: 0}, legend: {x: 0, y: 1},
      scene: {aspectmode: "data", xaxis: {title: {text: "east [m]"}}, yaxis: {title: {text: "north [m]"}},
              zaxis: {title: {text: "up [m]"}}}}, config);
  }
  function drawOrtho(id, d) {
    var el = document.getElementById("drill-ortho");
    if (!d.ortho) { el.style.display = "none"; return; }
    el.style.display = "";
    var o = d.ortho, traces = [], ring = D.map.footprints[id], t = byId[id];
    if (ring) {
      ring = ring.concat([ring[0]]);
      traces.push({type: "scatter", mode: "lines", name: "LiDAR crown footprint", hoverinfo: "skip",
                   x: ring.map(function (q) { return q[0]; }), y: ring.map(function (q) { return q[1]; }),
                   line: {color: "#ffeb3b", width: 2}});
    }
    traces.push({type: "scatter", mode: "markers", name: "LiDAR tree position", x: [t.x], y: [t.y],
                 hoverinfo: "skip", marker: {color: "#ffeb3b", size: 8, symbol: "x"}});
    // The title sits just above the plot, below the mode bar's row (centred, they overlapped).
    Plotly.react(el, traces, {margin: {l: 45, r: 10, t: 48, b: 35}, showlegend: false,
      title: {text: "Drone orthomosaic around " + id + " (yellow: LiDAR crown)", font: {size: 13},
              x: 0, xref: "paper", xanchor: "left", y: 1, yref: "paper", yanchor: "bottom",
              pad: {b: 6}},
      xaxis: {range: [o.x0, o.x1], title: {text: "x east [m]"}, showgrid: false},
      yaxis: {range: [o.y0, o.y1], scaleanchor: "x", scaleratio: 1, showgrid: false},
      images: [{source: o.uri, xref: "x", yref: "y", x: o.x0, y: o.y1, sizex: o.x1 - o.x0,
                sizey: o.y1 - o.y0, sizing: "stretch", layer: "below"}]}, config);
  }
  if (treeTable) {
    treeTable.tBodies[0].addEventListener("click", function (ev) {
      var tr = ev.target.closest("tr");
      if (tr && tr.dataset.id) { showTree(tr.dataset.id); }
    });
  }
  // Open the first flagged tree (else the first one), so the panel starts with something to read.
  var first = D.trees.filter(function (t, k) { return D.flagged[k]; })[0] || D.trees[0];
  if (first) { showTree(first.tree_id, true); }
  window.canopyReport = {data: D, showTree: showTree, crowns: crownIds.length};
})();

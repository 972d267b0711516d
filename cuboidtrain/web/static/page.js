// The page: send a mask (a file's bytes, an example's name, or a generated one's seed) with infer's
// options, and draw the answer: the mask with the fit, the box in 3D, the record, the explanation panel.
"use strict";

const $ = (id) => document.getElementById(id);
const FRONT = "#ff7f0e", BACK = "#17becf";
let info = null, source = null, last = null;

function fill(select, values, chosen) {
  select.innerHTML = "";
  for (const v of values) select.add(new Option(v, v, false, String(v) === String(chosen)));
}

async function start() {
  info = await (await fetch("/api/info")).json();
  fill($("shape"), info.shapes, info.shape);
  fill($("example"), info.examples, info.examples[0]);
  fill($("gen-shape"), info.generated_shapes, "mix");
  fill($("gen-scene"), info.scenes, "paper");
  fill($("gen-size"), info.sizes, 256);
  const drop = $("drop");
  drop.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (e) => {
    e.preventDefault(); drop.classList.remove("over");
    if (e.dataTransfer.files.length) useFile(e.dataTransfer.files[0]);
  });
  $("file").addEventListener("change", () => { if ($("file").files.length) useFile($("file").files[0]); });
  $("fit-example").addEventListener("click", () => { source = {kind: "example", name: $("example").value}; fit(); });
  $("generate").addEventListener("click", () => {
    source = {kind: "generated", gen_shape: $("gen-shape").value, scene: $("gen-scene").value,
              size: $("gen-size").value, seed: $("gen-seed").value};
    fit();
  });
  $("truth-camera").addEventListener("click", () => {
    if (!last || !last.truth) return;
    const cam = last.truth.camera;
    $("focal").value = cam.focal_px; $("cx").value = cam.principal_px[0]; $("cy").value = cam.principal_px[1];
    document.querySelector("input[name=camera][value=given]").checked = true;
    fit();
  });
  $("refit").addEventListener("click", fit);
  for (const id of ["shape", "invert", "no-classifier"]) $(id).addEventListener("change", fit);
  for (const r of document.querySelectorAll("input[name=camera]")) r.addEventListener("change", fit);
  document.body.dataset.ready = "1";
}

function useFile(file) {
  if (file.size > info.max_upload_bytes) {  // the server says the same; no need to send it
    showError(`upload of ${(file.size / 1e6).toFixed(1)} MB: over the page's limit of ${info.max_upload_bytes / 1e6} MB; ` +
              "expected a smaller file (cuboidtrain serve --max-upload-mb raises it; cuboidtrain infer has none)");
    return;
  }
  source = {kind: "file", file: file, name: file.name};
  fit();
}

function query() {
  const q = new URLSearchParams({shape: $("shape").value, invert: $("invert").checked ? "1" : "0",
                                 no_classifier: $("no-classifier").checked ? "1" : "0"});
  if ($("threshold").value.trim()) q.set("threshold", $("threshold").value.trim());
  if ($("label-id").value.trim()) q.set("label_id", $("label-id").value.trim());
  if (document.querySelector("input[name=camera]:checked").value === "given") {
    if ($("focal").value.trim()) q.set("focal_px", $("focal").value.trim());
    if ($("cx").value.trim() || $("cy").value.trim()) { q.set("principal_x", $("cx").value.trim()); q.set("principal_y", $("cy").value.trim()); }
  }
  return q;
}

function request(explain) {
  const q = query();
  q.set("explain", explain ? "1" : "0");
  if (source.kind === "file") { q.set("name", source.name); return ["/api/fit?" + q, source.file]; }
  if (source.kind === "example") return [`/api/example/${encodeURIComponent(source.name)}?` + q, null];
  for (const k of ["gen_shape", "scene", "size", "seed"]) q.set(k, source[k]);
  return ["/api/generated?" + q, null];
}

async function ask(explain) {
  const [url, body] = request(explain);
  try {
    return await (await fetch(url, {method: "POST", body: body})).json();
  } catch (err) {
    return {error: `no answer from the server (${err})`};
  }
}

let asked = 0;  // the latest fit asked for: an older answer arriving late is dropped

async function fit() {
  if (!source) return;
  const mine = ++asked;
  const name = source.kind === "generated" ? `generated ${source.scene} seed ${source.seed}` : source.name;
  $("status").textContent = `fitting ${name} ...`;
  document.body.dataset.state = "fitting";
  const t0 = performance.now();
  // The answer first, the explanation panel (10-30 times the fit to draw) in a second request.
  const answer = await ask(false);
  if (mine !== asked) return;
  const ms = performance.now() - t0;
  const error = answer.error || (answer.record && answer.record.error);
  if (error) { showError(error); $("status").textContent = `${name}: refused in ${ms.toFixed(0)} ms`; return; }
  last = answer;
  $("error").hidden = true;
  $("status").textContent = `${name}: answered in ${ms.toFixed(0)} ms; drawing the explanation ...`;
  show(answer);
  document.body.dataset.state = "answered";
  const explained = await ask(true);
  if (mine !== asked) return;
  $("panel").src = explained.panel ? `data:image/png;base64,${explained.panel}` : "";
  $("panel").alt = explained.panel ? "explanation panel" : "no explanation panel";
  $("status").textContent = `${name}: answered in ${ms.toFixed(0)} ms, explained in ${(performance.now() - t0).toFixed(0)} ms`;
  document.body.dataset.state = "explained";
}

function showError(message) {
  $("error").textContent = message;
  $("error").hidden = false;
  $("answer").hidden = true;
  document.body.dataset.state = "error";
}

// ---- the mask with the fit ---------------------------------------------------------------

function svgOf(view, maskPng, keypoints, scores, label) {
  const xs = keypoints.map((p) => p[0]).concat([-0.5, view.width - 0.5]);
  const ys = keypoints.map((p) => p[1]).concat([-0.5, view.height - 0.5]);
  const x0 = Math.min(...xs), x1 = Math.max(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
  const pad = 0.06 * Math.max(x1 - x0, y1 - y0), span = Math.max(x1 - x0, y1 - y0) + 2 * pad;
  const unit = span / 360;  // one screen pixel, in the mask's pixels
  const front = new Set(view.front);
  let s = `<svg xmlns="http://www.w3.org/2000/svg" viewBox="${x0 - pad} ${y0 - pad} ${span} ${span}">`;
  s += `<image href="data:image/png;base64,${maskPng}" x="-0.5" y="-0.5" width="${view.width}" height="${view.height}" style="image-rendering:pixelated"/>`;
  for (const [a, b] of view.edges) {
    const colour = front.has(a) && front.has(b) ? FRONT : BACK;
    s += `<line x1="${keypoints[a][0]}" y1="${keypoints[a][1]}" x2="${keypoints[b][0]}" y2="${keypoints[b][1]}" stroke="${colour}" stroke-width="${2 * unit}"/>`;
  }
  keypoints.forEach((p, k) => {
    const score = scores ? scores[k] : null;
    const colour = score === null ? "#ffdd00" : `hsl(${Math.round(120 * score)},90%,50%)`;
    s += `<circle cx="${p[0]}" cy="${p[1]}" r="${4 * unit}" fill="${colour}" stroke="black" stroke-width="${unit}"/>`;
    const text = score === null ? `${k}` : `${k}: ${score.toFixed(2)}`;
    s += `<text x="${p[0] + 5 * unit}" y="${p[1] - 5 * unit}" font-size="${12 * unit}" fill="white" stroke="black" stroke-width="${0.3 * unit}" font-weight="bold">${text}</text>`;
  });
  s += `<text x="${x0 - pad + 6 * unit}" y="${y0 - pad + 16 * unit}" font-size="${13 * unit}" fill="#fff">${label}</text>`;
  return s + "</svg>";
}

// ---- the numbers ---------------------------------------------------------------------------

function cell(value, digits) {
  if (value === null || value === undefined) return "<td>-</td>";
  if (typeof value === "number") return `<td data-value="${value}">${value.toFixed(digits)}</td>`;
  return `<td>${value}</td>`;
}

function row(name, value, sd, digits = 3, key = name) {
  const spread = sd === null || sd === undefined ? "" : ` ± ${sd.toFixed(digits)}`;
  const shown = typeof value === "number" ? (Number.isInteger(value) ? String(value) : value.toFixed(digits)) + spread
    : (value === null ? "-" : String(value));
  const data = typeof value === "number" ? ` data-value="${value}"` : "";
  const sdData = typeof sd === "number" ? ` data-sd="${sd}"` : "";
  return `<tr data-key="${key}"><td>${name}</td><td${data}${sdData}>${shown}</td></tr>`;
}

function nested(prefix, values, sds, rows) {
  for (const [k, v] of Object.entries(values)) {
    const sd = sds ? sds[k] : null;
    if (v !== null && typeof v === "object") nested(`${prefix}${k}.`, v, sd, rows);
    else rows.push(row(`${prefix}${k}`, v, sd, 3, `ratios.${prefix}${k}`));
  }
}

function show(answer) {
  const r = answer.record, c = r.cuboid, view = answer.view;
  $("answer").hidden = false;
  const scores = c ? c.corners.map((x) => x.score) : null;
  $("mask").innerHTML = svgOf(view, view.mask, r.keypoints, scores, `${r.shape} ${r.confidence.toFixed(2)}`);
  $("truth-figure").hidden = !answer.truth;
  if (answer.truth) $("truth").innerHTML = svgOf(view, view.mask, answer.truth.keypoints, null, `truth: ${answer.truth.shape}`);
  const rows = [row("shape", r.shape), row("confidence", r.confidence)];
  for (const [k, v] of Object.entries(r.candidates)) rows.push(row(`candidate ${k}`, v, null, 3, `candidates.${k}`));
  if (r.shape_call) {  // who called the class: the silhouettes, or the shape classifier on a rough mask
    const p = r.shape_call.twobox_probability;
    rows.push(row("shape called by", r.shape_call.by + (p === null ? "" : ` (P(twobox) ${p.toFixed(2)})`), null, 0, "shape_call"));
  }
  nested("", r.ratios, r.ratios_sd, rows);
  if (c) {
    rows.push(row("yaw (deg)", c.yaw_deg, c.yaw_sd_deg, 2, "yaw_deg"), row("pitch (deg)", c.pitch_deg, null, 2, "pitch_deg"),
              row("roll (deg)", c.roll_deg, null, 2, "roll_deg"), row("focal (px)", c.focal_px, c.focal_sd_px, 1, "focal_px"),
              row("principal (px)", c.principal_px ? c.principal_px.map((v) => v.toFixed(1)).join(", ") : null, null, 1, "principal_px"),
              row("intrinsics", `focal ${c.intrinsics.focal_px}, principal ${c.intrinsics.principal_px}`, null, 0, "intrinsics"),
              row("cuboid IoU", c.iou, null, 3, "iou"), row("outline rms (px)", c.outline_rms_px, null, 2, "outline_rms_px"));
  }
  rows.push(row("refine steps", r.refine_steps));
  for (const w of r.warnings) rows.push(`<tr><td>warning</td><td class="warn">${w}</td></tr>`);
  $("numbers").tBodies[0].innerHTML = rows.join("");
  $("corners").tBodies[0].innerHTML = r.keypoints.map((p, k) =>
    `<tr><td>${k}</td><td>${view.names[k]}</td>${cell(p[0], 1)}${cell(p[1], 1)}` +
    `<td>${c ? (c.corners[k].on_outline ? "yes" : "no") : "-"}</td>${cell(c ? c.corners[k].score : null, 2)}</tr>`).join("");
  $("errors").hidden = !answer.truth;
  if (answer.truth) {
    const e = answer.errors || {}, t = answer.truth;
    const erows = [row("drawn", `${t.shape}, ${t.scene}, seed ${t.seed}`)];
    if (e.mismatch) erows.push(row("corners", e.mismatch));
    else {
      erows.push(row("mean corner (px)", e.mean_corner_px, null, 2), row("hull corners (px)", e.hull_px, null, 2),
                 row("interior corners (px)", e.interior_px, null, 2),
                 row("depth/height rel.", e.depth_height.map((v) => v.toFixed(3)).join(", ")),
                 row("width/height rel.", e.width_height.map((v) => v.toFixed(3)).join(", ")),
                 row("yaw (deg)", e.yaw_deg, null, 2), row("3D IoU", e.iou3d, null, 3));
    }
    erows.push(row("true focal (px)", t.camera.focal_px, null, 1, "truth_focal"));
    $("errors").tBodies[0].innerHTML = erows.join("");
  }
  const stem = (r.input || "mask").replace(/\.[^.]*$/, "");
  link($("download-record"), JSON.stringify([r], null, 2) + "\n", "application/json", `${stem}.json`);
  $("download-mesh").hidden = !answer.mesh;
  if (answer.mesh) link($("download-mesh"), answer.mesh, "text/plain", `${stem}.obj`);
  $("panel").removeAttribute("src");
  draw3d(view.box3d);
}

function link(a, text, type, name) {
  if (a.href) URL.revokeObjectURL(a.href);
  a.href = URL.createObjectURL(new Blob([text], {type: type}));
  a.download = name;
}

// ---- the box in 3D: camera frame (x right, y down, z forward) drawn as (x, z, up) -------------

const show3 = (p) => [p[0], p[2], -p[1]];

function lines(points, pairs, style, name) {
  const x = [], y = [], z = [];
  for (const [a, b] of pairs) for (const p of [points[a], points[b], null]) {
    const q = p ? show3(p) : [null, null, null];
    x.push(q[0]); y.push(q[1]); z.push(q[2]);
  }
  return {type: "scatter3d", mode: "lines", x, y, z, line: style, name, hoverinfo: "skip"};
}

function faces(points, quads, colour, opacity, name) {
  const shown = points.map(show3), i = [], j = [], k = [];
  for (const q of quads) { i.push(q[0], q[0]); j.push(q[1], q[2]); k.push(q[2], q[3]); }
  return {type: "mesh3d", x: shown.map((p) => p[0]), y: shown.map((p) => p[1]), z: shown.map((p) => p[2]),
          i, j, k, color: colour, opacity, name, hoverinfo: "skip", flatshading: true};
}

function draw3d(box) {
  const div = $("view3d");
  if (!box) { Plotly.purge(div); div.textContent = "no cuboid: the networks' corners only"; return; }
  const P = box.corners, front = new Set(last.view.front), edges = last.view.edges;
  const frontQuads = box.faces.filter((f) => f[1] === "FRONT").map((f) => f[2]);
  const otherQuads = box.faces.filter((f) => f[1] !== "FRONT").map((f) => f[2]);
  const traces = [faces(P, frontQuads, FRONT, 0.45, "FRONT face"), faces(P, otherQuads, BACK, 0.12, "faces")];
  traces.push(lines(P, edges.filter(([a, b]) => front.has(a) && front.has(b)), {color: FRONT, width: 6}, "front edges"));
  traces.push(lines(P, edges.filter(([a, b]) => !(front.has(a) && front.has(b))), {color: BACK, width: 5}, "edges"));
  if (box.band) {
    const label = `depth x/ ${box.band.factor.toFixed(2)} (1 sd)`;
    traces.push(lines(box.band.shallower, edges, {color: "#555", width: 2, dash: "dash"}, label));
    traces.push(Object.assign(lines(box.band.deeper, edges, {color: "#555", width: 2, dash: "dash"}, label), {showlegend: false}));
  }
  // the camera: a pyramid at the origin on the image's outline, through the (drawn) focal length
  const view = last.view, f = box.focal, [cx, cy] = box.principal;
  const centre = P.reduce((s, p) => s.map((v, i) => v + p[i] / P.length), [0, 0, 0]);
  const depth = 0.2 * Math.hypot(...centre);
  const base = [[-0.5, -0.5], [view.width - 0.5, -0.5], [view.width - 0.5, view.height - 0.5], [-0.5, view.height - 0.5]]
    .map(([u, v]) => [(u - cx) / f * depth, (v - cy) / f * depth, depth]);
  const cam = [[0, 0, 0], ...base];
  traces.push(lines(cam, [[0, 1], [0, 2], [0, 3], [0, 4], [1, 2], [2, 3], [3, 4], [4, 1]], {color: "black", width: 3}, "camera"));
  const shown = P.map(show3);
  traces.push({type: "scatter3d", mode: "markers+text", x: shown.map((p) => p[0]), y: shown.map((p) => p[1]),
               z: shown.map((p) => p[2]), text: P.map((_, k) => String(k)), textposition: "top center",
               marker: {size: 3, color: "#ffdd00", line: {color: "black", width: 1}}, name: "corners", hoverinfo: "text"});
  const layout = {margin: {l: 0, r: 0, t: 0, b: 0}, showlegend: true, legend: {x: 0, y: 1, font: {size: 10}},
                  scene: {aspectmode: "data", xaxis: {title: {text: "x, right"}}, yaxis: {title: {text: "z, forward"}},
                          zaxis: {title: {text: "up"}}, camera: {eye: {x: 1.2, y: -1.6, z: 0.9}}}};
  Plotly.react(div, traces, layout, {displaylogo: false, responsive: true});
  const gap = box.nominal ? "weak perspective: drawn near a camera that is really infinitely far"
    : box.nearer < 1 ? `drawn nearer: ${box.distance.toFixed(1)} box heights away` : `${box.distance.toFixed(1)} box heights away`;
  $("view-caption").textContent = `the box in 3D and its camera (drag to turn, scroll to zoom): ${gap}; units: box height`;
}

start();

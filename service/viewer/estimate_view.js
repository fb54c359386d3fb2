// The estimate view: an image, a mask and optionally depth (dropped, chosen, or rendered as an
// example), the camera K, an initial pose typed or aligned with the mouse, then POST /v1/estimate and
// its answer: outlines at the start and at the result over the image, the loss plot, the pose, θ,
// the uncertainty and warnings where the server gives them, and the whole exchange as JSON.

import * as api from "./api.js";
import {
  axisAngle, boxCentre, compose, degrees, matrixToRpy, orbitPose, radians, rotateAbout,
  rpyToMatrix, split, transformPoint,
} from "./geometry.js";
import { bitmapFromBase64, channelOf, outline, outlineLayer } from "./images.js";
import { plotLoss } from "./plot.js";
import { decodePng, encodeGrayPng, fromBase64 } from "./png.js";
import { LatestOnly } from "./schedule.js";
import { clearError, formatJoint, gestures, jointSliders, logFrame, showError } from "./ui.js";

const DEFAULT_FOV_DEG = 60; // K guessed for a new image until the user types theirs
const EXAMPLE_CAMERA = { K: [[134.1, 0, 80], [0, 134.1, 60], [0, 0, 1]], width: 160, height: 120 };
const COLOURS = { start: [255, 140, 0], result: [0, 200, 83], mask: [224, 224, 224] };
const TURN_PER_PIXEL = 0.01; // radians
const PREVIEW_WIDTH = 320; // the model over the image is rendered at most this wide while aligning (then scaled up)
const RESULT_WIDTH = 640; // and the result's outline at most this wide

export class EstimateView {
  constructor(root, { onError }) {
    this.root = root;
    this.onError = onError;
    this.$ = (id) => root.querySelector(`#${id}`);
    this.info = null;
    this.files = { image: null, mask: null, depth: null };
    this.image = null; // ImageBitmap
    // Layers drawn over the image, each { layer: OffscreenCanvas, forSize: [w, h] of the image it belongs to }:
    this.mask = null; // the mask's outline
    this.start = null; // the model at the initial pose, translucent, and its outline (`edges`)
    this.result = null; // the result's outline
    this.T = null; // the initial pose, T_cam_obj
    this.groundTruth = null;
    this.kEdited = false;
    this.poseEdited = false;
    this.exchange = null;
    this.canvas = this.$("overlay");

    this.startScheduler = new LatestOnly(
      (params, signal) => api.render(params.request, signal),
      (result, params) => this.#showStart(result, params),
      (error) => this.#report(error),
    );
    for (const kind of ["image", "mask", "depth"]) this.#fileInput(kind);
    this.$("clear-depth").addEventListener("click", () => { this.$("depth").value = ""; this.#setFile("depth", null); });
    for (const id of ["fx", "fy", "cx", "cy"]) this.$(id).addEventListener("input", () => { this.kEdited = true; this.#renderStart(); });
    for (const id of ["px", "py", "pz", "roll", "pitch", "yaw"]) {
      this.$(id).addEventListener("input", (e) => { this.poseEdited = true; this.T = this.#poseFromFields(); this.#renderStart(e); });
    }
    for (const id of ["show-model", "show-start", "show-result", "show-mask"]) this.$(id).addEventListener("change", () => this.#draw());
    this.root.querySelectorAll('input[name="plot-x"]').forEach((r) => r.addEventListener("change", () => this.#plot()));
    this.$("est-mode").addEventListener("change", () => this.#renderStart());
    this.$("example").addEventListener("click", () => this.loadExample());
    this.$("run").addEventListener("click", () => this.run());
    this.$("cancel").addEventListener("click", () => this.controller?.abort());
    this.$("download").addEventListener("click", () => this.#download());
    this.$("use-result").addEventListener("click", () => {
      if (!this.exchange) return;
      this.setInitial(this.exchange.response.pose.matrix, this.exchange.response.joints);
    });
    gestures(this.canvas, { onDrag: (dx, dy, mods, e) => this.#drag(dx, dy, mods, e), onZoom: (f, e) => this.#push(f, e) });
    this.canvas.addEventListener("keydown", (e) => this.#key(e));
  }

  setModel(info) {
    this.startScheduler.cancel();
    this.info = info;
    this.joints = jointSliders(this.$("estimate-joints"), info.joints, (e) => this.#renderStart(e), "estimate-joint");
    this.$("est-mode").querySelector('option[value="parts"]').disabled = !info.modes.includes("parts");
    if (!info.modes.includes("parts") && this.$("est-mode").value === "parts") this.$("est-mode").value = "auto";
    this.groundTruth = null;
    this.$("gt-label").hidden = true;
    this.$("example").disabled = this.$("run").disabled = false;
    if (!this.poseEdited || !this.T) this.#framePose();
    this.#renderStart();
  }

  // ---- inputs --------------------------------------------------------------------------------

  #fileInput(kind) {
    const input = this.$(kind), zone = input.closest(".drop");
    input.addEventListener("change", () => this.#setFile(kind, input.files[0] || null));
    zone.addEventListener("dragover", (e) => { e.preventDefault(); zone.classList.add("over"); });
    zone.addEventListener("dragleave", () => zone.classList.remove("over"));
    zone.addEventListener("drop", (e) => {
      e.preventDefault();
      zone.classList.remove("over");
      const file = e.dataTransfer.files[0];
      if (!file) return;
      input.files = e.dataTransfer.files;
      this.#setFile(kind, file);
    });
  }

  async #setFile(kind, file, { fromExample = false } = {}) {
    const error = this.$(`${kind}-error`), input = this.$(kind);
    clearError(error, input);
    this.files[kind] = file;
    input.closest(".drop").querySelector(".file-name").textContent = file ? `${file.name || kind} (${file.size < 1024 ? `${file.size} B` : `${Math.round(file.size / 1024)} kB`})` : "";
    if (!fromExample) { this.groundTruth = null; this.$("gt-label").hidden = true; }
    if (!file) {
      if (kind === "image") this.image = null;
      if (kind === "mask") this.mask = null;
      this.#draw();
      return;
    }
    if (kind === "depth") return; // the server reads it; nothing to preview
    let bitmap;
    try {
      bitmap = await createImageBitmap(file);
    } catch {
      this.files[kind] = null;
      if (kind === "image") this.image = null;
      else this.mask = null;
      this.#draw();
      const what = kind === "image" ? "a PNG or JPEG image" : "a PNG mask";
      showError(error, `${kind}: this browser cannot read '${file.name || kind}' as ${what}`, input);
      return;
    }
    if (kind === "mask") {
      const { width, height } = bitmap;
      this.mask = { layer: outlineLayer(outline(channelOf(bitmap), width, height, 0), width, height, COLOURS.mask), forSize: [width, height] };
    } else {
      const resized = this.imageSize?.[0] !== bitmap.width || this.imageSize?.[1] !== bitmap.height;
      this.image = bitmap;
      this.imageSize = [bitmap.width, bitmap.height];
      this.$("camera-size").textContent = `Size: ${bitmap.width} × ${bitmap.height} (from the image).`;
      if (resized) this.kEdited = false; // a K typed for another image size is not this camera's
      if (!this.kEdited || !this.#fieldsK()) this.#setK(guessK(bitmap.width, bitmap.height));
      if (!this.poseEdited) this.#framePose();
      this.result = null;
    }
    this.#renderStart();
  }

  #setK(K) {
    [["fx", K[0][0]], ["fy", K[1][1]], ["cx", K[0][2]], ["cy", K[1][2]]].forEach(([id, v]) => { this.$(id).value = +v.toFixed(3); });
    clearError(this.$("camera-error"));
  }

  /** K from the fields, or null where one is not a finite number. */
  #fieldsK() {
    const [fx, fy, cx, cy] = ["fx", "fy", "cx", "cy"].map((id) => this.$(id).valueAsNumber);
    if (![fx, fy, cx, cy].every(Number.isFinite)) return null;
    return [[fx, 0, cx], [0, fy, cy], [0, 0, 1]];
  }

  /** The initial pose centring the model's box in the image, seen along the camera's axis. */
  #framePose() {
    if (!this.info) return;
    const { centre, radius } = boxCentre(this.info.bounds);
    const K = this.#fieldsK() || EXAMPLE_CAMERA.K;
    const height = this.image?.height ?? EXAMPLE_CAMERA.height;
    const z = (1.3 * radius * K[1][1]) / (height / 2);
    const R = rpyToMatrix([0, 0, 0]);
    const t = [0, 0, z].map((v, i) => v - R[i][0] * centre[0] - R[i][1] * centre[1] - R[i][2] * centre[2]);
    this.#setPose(compose(R, t));
  }

  #setPose(T) {
    this.T = T;
    const { R, t } = split(T);
    const rpy = matrixToRpy(R).map(degrees);
    [["px", t[0], 4], ["py", t[1], 4], ["pz", t[2], 4], ["roll", rpy[0], 2], ["pitch", rpy[1], 2], ["yaw", rpy[2], 2]]
      .forEach(([id, v, digits]) => { this.$(id).value = +v.toFixed(digits); });
    clearError(this.$("pose-error"));
  }

  #poseFromFields() {
    const v = ["px", "py", "pz", "roll", "pitch", "yaw"].map((id) => this.$(id).valueAsNumber);
    if (!v.every(Number.isFinite)) {
      showError(this.$("pose-error"), "initial pose: every field needs a number");
      return this.T;
    }
    clearError(this.$("pose-error"));
    return compose(rpyToMatrix(v.slice(3).map(radians)), v.slice(0, 3));
  }

  /** Use `T` (4x4 T_cam_obj) and `joints` as the next run's start. */
  setInitial(T, joints = {}) {
    this.poseEdited = true;
    this.#setPose(T);
    this.joints?.set(joints);
    this.#renderStart();
  }

  // ---- aligning the model with the mouse and keys -------------------------------------------

  #pivot() {
    return transformPoint(this.T, boxCentre(this.info.bounds).centre);
  }

  #drag(dx, dy, { turn, roll }, event) {
    if (!this.info || !this.T) return;
    const p = this.#pivot(), K = this.#fieldsK() || EXAMPLE_CAMERA.K;
    let T;
    if (roll) T = rotateAbout(this.T, axisAngle([0, 0, 1], dx * TURN_PER_PIXEL), p);
    else if (turn) {
      const R = [[0, 1, 0], [1, 0, 0]].map((axis, i) => axisAngle(axis, (i ? -dy : dx) * TURN_PER_PIXEL));
      T = rotateAbout(rotateAbout(this.T, R[0], p), R[1], p);
    } else {
      const { R, t } = split(this.T);
      T = compose(R, [t[0] + (dx * p[2]) / K[0][0], t[1] + (dy * p[2]) / K[1][1], t[2]]);
    }
    this.poseEdited = true;
    this.#setPose(T);
    this.#renderStart(event);
  }

  /** Move the model along the line of sight through its centre (factor > 1: farther). */
  #push(factor, event) {
    if (!this.info || !this.T) return;
    const p = this.#pivot();
    if (p[2] * factor < 0.02) return;
    const { R, t } = split(this.T);
    this.poseEdited = true;
    this.#setPose(compose(R, t.map((v, i) => v + p[i] * (factor - 1))));
    this.#renderStart(event);
  }

  #key(e) {
    const arrows = { ArrowLeft: [-1, 0], ArrowRight: [1, 0], ArrowUp: [0, -1], ArrowDown: [0, 1] };
    if (arrows[e.key]) {
      const [x, y] = arrows[e.key];
      if (e.shiftKey) this.#drag(x * 9, y * 9, { turn: true }, e); // 5 degrees
      else this.#drag(x * 2, y * 2, {}, e);
    } else if (e.key === "PageUp") this.#push(1 / 1.03, e);
    else if (e.key === "PageDown") this.#push(1.03, e);
    else if (e.key === "[" || e.key === "]") this.#drag(e.key === "[" ? -9 : 9, 0, { roll: true }, e);
    else return;
    e.preventDefault();
  }

  // ---- drawing --------------------------------------------------------------------------------

  /** The camera of the image, scaled down to at most `maxWidth` pixels wide. */
  #camera(maxWidth = Infinity) {
    const K = this.#fieldsK();
    if (!K || !this.image) return null;
    return scaleCamera({ K, width: this.image.width, height: this.image.height }, maxWidth);
  }

  /** Render the model at the initial pose (for its outline and the translucent overlay). */
  #renderStart(event = null) {
    const camera = this.#camera(PREVIEW_WIDTH);
    if (!this.info || !this.T || !camera) { this.#draw(); return; }
    const request = {
      model: this.info.name, pose: { matrix: this.T }, joints: this.joints.values(), camera,
      outputs: ["rgb", "opacity"], mode: this.$("est-mode").value,
    };
    const forSize = [this.image.width, this.image.height];
    this.startScheduler.submit({ request, forSize, t0: event?.timeStamp ?? performance.now(), input: event?.type ?? "view" });
  }

  async #showStart(result, params) {
    const [rgb, alpha] = await Promise.all([bitmapFromBase64(result.rgb), bitmapFromBase64(result.opacity)]);
    const a = channelOf(alpha), { width, height } = result;
    const layer = new OffscreenCanvas(width, height), ctx = layer.getContext("2d", { willReadFrequently: true });
    ctx.drawImage(rgb, 0, 0);
    const image = ctx.getImageData(0, 0, width, height);
    for (let i = 0; i < a.length; i++) image.data[4 * i + 3] = Math.round(a[i] * 0.6);
    ctx.putImageData(image, 0, 0);
    this.start = { layer, edges: outlineLayer(outline(a, width, height), width, height, COLOURS.start), forSize: params.forSize };
    clearError(this.$("pose-error"));
    this.#draw();
    await new Promise((resolve) => requestAnimationFrame(resolve));
    logFrame({ view: "estimate", mode: params.request.mode, input: params.input, width, height, serverMs: result.seconds * 1000, latencyMs: performance.now() - params.t0 });
  }

  #draw() {
    const empty = !this.image;
    this.$("overlay-empty").hidden = !empty;
    this.canvas.closest("figure").hidden = empty;
    if (empty) return;
    const { width, height } = this.image, ctx = this.canvas.getContext("2d");
    [this.canvas.width, this.canvas.height] = [width, height];
    ctx.imageSmoothingEnabled = false; // outlines stay crisp when a preview is scaled up
    ctx.drawImage(this.image, 0, 0);
    const over = (thing, layer, show) => {
      if (thing && thing.forSize[0] === width && thing.forSize[1] === height && this.$(show).checked) {
        ctx.drawImage(thing[layer], 0, 0, width, height);
      }
    };
    over(this.start, "layer", "show-model");
    over(this.mask, "layer", "show-mask");
    over(this.start, "edges", "show-start");
    over(this.result, "layer", "show-result");
  }

  // ---- the example ----------------------------------------------------------------------------

  /** Render the model at a known pose and fill every input from it; the start is that pose, perturbed. */
  async loadExample() {
    const error = this.$("example-error");
    clearError(error);
    if (!this.info) return;
    const { centre, radius } = boxCentre(this.info.bounds);
    const camera = EXAMPLE_CAMERA;
    const distance = (1.1 * radius) / Math.sin(Math.atan(camera.height / 2 / camera.K[1][1]));
    const T_true = orbitPose({ target: centre, azimuth: radians(-70), elevation: radians(55), distance });
    const joints = Object.fromEntries(this.info.joints.map((j) => [j.name, j.lower + 0.7 * (j.upper - j.lower)]));
    let result;
    try {
      result = await api.render({ model: this.info.name, pose: { matrix: T_true }, joints, camera, outputs: ["rgb", "depth", "opacity"] });
    } catch (e) {
      if (!this.onError(e)) showError(error, `example: ${e.message}`);
      return;
    }
    const opacity = await decodePng(fromBase64(result.opacity));
    const mask = opacity.data.map((v) => (v > 127 ? 255 : 0));
    const named = (bytes, name) => new File([bytes], name, { type: name.endsWith(".png") ? "image/png" : "" });
    const files = {
      image: named(fromBase64(result.rgb), "example-rgb.png"),
      mask: new File([await encodeGrayPng(mask, camera.width, camera.height)], "example-mask.png", { type: "image/png" }),
      depth: named(fromBase64(result.depth), "example-depth.png"),
    };
    for (const kind of ["image", "mask", "depth"]) {
      this.$(kind).value = "";
      await this.#setFile(kind, files[kind], { fromExample: true });
    }
    this.kEdited = true;
    this.#setK(camera.K);
    this.groundTruth = { pose: { matrix: T_true }, joints };
    this.$("gt-label").hidden = false;
    this.$("use-gt").checked = true;
    const p = transformPoint(T_true, centre);
    const turned = rotateAbout(T_true, axisAngle([0.3, 1, 0.2], radians(8)), p);
    const { R, t } = split(turned);
    const start = compose(R, [t[0] + 0.012, t[1] - 0.008, t[2] + 0.02]);
    const mid = Object.fromEntries(this.info.joints.map((j) => [j.name, (j.lower + j.upper) / 2]));
    this.result = null;
    this.setInitial(start, mid);
    await this.startScheduler.idle();
    logFrame({ view: "estimate", kind: "example" });
  }

  // ---- running the estimate ---------------------------------------------------------------

  #clearErrors() {
    for (const id of ["image", "mask", "depth", "camera", "pose", "options", "run", "model", "example"]) {
      clearError(this.$(`${id}-error`) || document.getElementById(`${id}-error`), this.$(id));
    }
    if (this.joints) clearError(this.joints.error);
  }

  /** Where an API error about `field` is shown: next to the control that caused it. */
  #errorSlot(field) {
    const f = field || "";
    const slots = [
      ["image", "image"], ["mask", "mask"], ["depth", "depth"], ["request.camera", "camera"],
      ["request.initial_pose", "pose"], ["request.iterations", "options"], ["request.options", "options"],
      ["request.ground_truth", "options"], ["camera", "camera"], ["pose", "pose"],
    ];
    if (f.startsWith("request.initial_joints") || f.startsWith("joints")) return { node: this.joints.error, control: null };
    if (f.startsWith("request.model")) return { node: document.getElementById("model-error"), control: document.getElementById("model") };
    for (const [prefix, id] of slots) {
      if (f === prefix || f.startsWith(`${prefix}.`)) return { node: this.$(`${id}-error`), control: this.$(id) };
    }
    return { node: this.$("run-error"), control: null };
  }

  #report(error) {
    if (this.onError(error)) return;
    const { node, control } = this.#errorSlot(error.field);
    const message = error.field && !error.message.startsWith(error.field) ? `${error.field}: ${error.message}` : error.message;
    showError(node, message, control);
  }

  #request() {
    const K = this.#fieldsK();
    const request = {
      model: this.info.name,
      camera: { K, width: this.image.width, height: this.image.height },
      initial_pose: { matrix: this.T },
      initial_joints: this.joints.values(),
      options: { preset: this.$("preset").value, mode: this.$("est-mode").value },
    };
    if (this.$("want-uncertainty").checked) request.options.uncertainty = true;
    const iterations = this.$("iterations").valueAsNumber;
    if (Number.isFinite(iterations)) request.iterations = iterations;
    if (this.groundTruth && this.$("use-gt").checked) request.ground_truth = this.groundTruth;
    return request;
  }

  async run() {
    this.#clearErrors();
    const status = this.$("run-status");
    if (!this.info) return showError(this.$("run-error"), "no model: choose one at the top");
    if (!this.files.image || !this.image) return showError(this.$("image-error"), "image: choose or drop an image first", this.$("image"));
    if (!this.files.mask) return showError(this.$("mask-error"), "mask: choose or drop a mask first", this.$("mask"));
    if (!this.#fieldsK()) return showError(this.$("camera-error"), "camera: fx, fy, cx and cy each need a number", this.$("fx"));
    if (this.$("iterations").value !== "" && !Number.isFinite(this.$("iterations").valueAsNumber)) return showError(this.$("options-error"), "iterations: a whole number is needed (or empty: the preset's)", this.$("iterations"));
    const request = this.#request();
    this.controller = new AbortController();
    this.$("run").disabled = true;
    this.$("cancel").disabled = false;
    status.textContent = "Estimating…";
    const started = performance.now();
    try {
      const response = await api.estimate(request, this.files, this.controller.signal);
      this.exchange = { request, response, files: Object.fromEntries(Object.entries(this.files).map(([k, f]) => [k, f?.name ?? null])) };
      status.textContent = `Done in ${((performance.now() - started) / 1000).toFixed(2)} s.`;
      await this.#showResult(response, request);
    } catch (error) {
      status.textContent = error.name === "AbortError" ? "Cancelled (the server stops the job)." : "Failed.";
      if (error.name !== "AbortError") this.#report(error);
    } finally {
      this.$("run").disabled = false;
      this.$("cancel").disabled = true;
    }
  }

  async #showResult(response, request) {
    const section = this.$("result");
    section.hidden = false;
    const { R } = split(response.pose.matrix);
    const rows = [
      ["status", `${response.status} after ${response.iterations} iterations${response.recovered_non_finite ? " (a non-finite step was undone)" : ""}`],
      ["loss", response.loss === null ? "not finite" : response.loss.toPrecision(4)],
      ["time", `${response.seconds.toFixed(2)} s refining, ${response.wall_seconds.toFixed(2)} s in the server`],
      ["preset", response.preset_reason === "requested" ? response.preset : `${response.preset} (auto: ${response.preset_reason})`],
      ["field", response.mode_reason === "requested" ? response.mode : `${response.mode} (auto: ${response.mode_reason})`],
      ["position", `${response.pose.position.map((v) => v.toFixed(4)).join(", ")} m`],
      ["orientation", `[${response.pose.orientation.map((v) => v.toFixed(4)).join(", ")}] (qx, qy, qz, qw)`],
      ["roll, pitch, yaw", `${matrixToRpy(R).map((v) => degrees(v).toFixed(2)).join("°, ")}°`],
    ];
    for (const joint of this.info.joints) {
      if (joint.name in response.joints) rows.push([`θ ${joint.name}`, formatJoint(joint, response.joints[joint.name])]);
    }
    for (const [name, value] of Object.entries(response.metrics || {})) rows.push([name, this.#metric(name, value)]);
    fillPairs(this.$("result-summary"), rows);
    this.#showUncertainty(response.uncertainty);
    const warnings = this.$("warnings");
    const list = Array.isArray(response.warnings) ? response.warnings : [];
    warnings.replaceChildren(...list.map((w) => Object.assign(document.createElement("li"), { textContent: typeof w === "string" ? w : JSON.stringify(w) })));
    warnings.hidden = !list.length;
    this.$("result-matrix").textContent = response.pose.matrix.map((row) => row.map((v) => v.toFixed(5).padStart(9)).join(" ")).join("\n");
    this.#plot();
    try {
      const rendered = await api.render({
        model: request.model, pose: { matrix: response.pose.matrix }, joints: response.joints, camera: scaleCamera(request.camera, RESULT_WIDTH),
        outputs: ["opacity"], mode: request.options.mode,
      });
      const alpha = channelOf(await bitmapFromBase64(rendered.opacity)), { width, height } = rendered;
      this.result = { layer: outlineLayer(outline(alpha, width, height), width, height, COLOURS.result), forSize: [request.camera.width, request.camera.height] };
    } catch (error) {
      this.#report(error);
    }
    this.#draw();
    logFrame({ view: "estimate", kind: "result", status: response.status, iterations: response.iterations });
  }

  /** A ground-truth metric with its unit: ADD and *_m in millimetres, *_deg in degrees, joint errors in the joint's. */
  #metric(name, value) {
    if (value === null || !Number.isFinite(value)) return "not finite";
    const joint = name.startsWith("joint_error/") && this.info.joints.find((j) => `joint_error/${j.name}` === name);
    if (joint) return formatJoint(joint, value);
    if (name === "add" || name === "add_s" || name.endsWith("_m")) return `${(value * 1000).toFixed(1)} mm`;
    if (name.endsWith("_deg")) return `${value.toFixed(2)}°`;
    return value.toPrecision(4);
  }

  /** The 1σ of the estimate (position per camera axis, rotation about them, each joint), where the server gives it. */
  #showUncertainty(u) {
    const box = this.$("uncertainty");
    box.hidden = !u;
    if (!u) return;
    const each = (v) => (Array.isArray(v) ? v : [v]).filter(Number.isFinite);
    const rows = [];
    const position = each(u.position_sigma_m), rotation = each(u.rotation_sigma_rad);
    if (position.length) rows.push(["position (x, y, z)", `${position.map((v) => (v * 1000).toFixed(1)).join(", ")} mm`]);
    if (rotation.length) rows.push(["rotation (about x, y, z)", `${rotation.map((v) => degrees(v).toFixed(2)).join("°, ")}°`]);
    for (const [name, sigma] of Object.entries(u.joint_sigma || {})) {
      const joint = this.info.joints.find((j) => j.name === name);
      if (Number.isFinite(sigma)) rows.push([`θ ${name}`, joint ? formatJoint(joint, sigma) : sigma.toPrecision(3)]);
    }
    if (Array.isArray(u.covariance)) rows.push(["covariance", `${u.covariance.length} × ${u.covariance[0]?.length ?? 0} (in the JSON download)`]);
    fillPairs(this.$("uncertainty-values"), rows);
  }

  #plot() {
    if (!this.exchange) return;
    const x = this.root.querySelector('input[name="plot-x"]:checked').value;
    plotLoss(this.$("loss-plot"), this.exchange.response.trace, x);
  }

  #download() {
    if (!this.exchange) return;
    const blob = new Blob([JSON.stringify(this.exchange, null, 1)], { type: "application/json" });
    const link = Object.assign(document.createElement("a"), { href: URL.createObjectURL(blob), download: `narf-estimate-${this.info.name}.json` });
    document.body.append(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(link.href), 1000);
  }
}

/** `camera` ({ K, width, height }) scaled down to at most `maxWidth` pixels wide (K scaled with it). */
function scaleCamera({ K, width, height }, maxWidth) {
  const s = Math.min(1, maxWidth / width);
  const scaled = [[K[0][0] * s, K[0][1] * s, K[0][2] * s], [0, K[1][1] * s, K[1][2] * s], [0, 0, 1]];
  return { K: scaled, width: Math.max(1, Math.round(width * s)), height: Math.max(1, Math.round(height * s)) };
}

function guessK(width, height) {
  const f = width / 2 / Math.tan(radians(DEFAULT_FOV_DEG) / 2);
  return [[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]];
}

function fillPairs(dl, rows) {
  dl.replaceChildren(...rows.flatMap(([k, v]) => [
    Object.assign(document.createElement("dt"), { textContent: k }),
    Object.assign(document.createElement("dd"), { textContent: v }),
  ]));
}


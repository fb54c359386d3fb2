// The model view: an orbit camera around the model's box, one slider per joint, RGB / depth /
// opacity, and the `narf` and `parts` fields side by side, each pane rendered through /v1/render.

import * as api from "./api.js";
import { boxCentre, intrinsics, orbitPose, radians, split, transformPoint } from "./geometry.js";
import { bitmapFromBase64, colourDepth, depthFromBase64, drawColourBar } from "./images.js";
import { LatestOnly } from "./schedule.js";
import { clearError, gestures, jointSliders, logFrame, showError } from "./ui.js";

const FOV_DEG = 60; // horizontal field of view of the view's camera
const ORBIT_PER_PIXEL = 0.01; // radians
const MAX_ELEVATION = radians(89);

export class ModelView {
  constructor(root, { onError }) {
    this.root = root;
    this.onError = onError; // (ApiError) -> bool: true if handled elsewhere (a 401 goes to the token field)
    this.info = null;
    this.camera = null;
    this.output = "rgb";
    this.panes = [...root.querySelectorAll(".pane")].map((figure) => this.#pane(figure));
    this.sizeSelect = root.querySelector("#size");
    this.poseText = root.querySelector("#camera-pose");
    this.scale = root.querySelector("#depth-scale");
    drawColourBar(root.querySelector("#colour-bar"));

    root.querySelectorAll('input[name="output"]').forEach((radio) =>
      radio.addEventListener("change", () => { this.output = radio.value; this.render(); }));
    root.querySelectorAll('input[name="mode"]').forEach((box) =>
      box.addEventListener("change", () => this.#layout()));
    this.sizeSelect.addEventListener("change", () => { this.panes.forEach((p) => p.scheduler.cancel()); this.render(); });
    root.querySelector("#reset-view").addEventListener("click", () => this.resetCamera());
  }

  #pane(figure) {
    const pane = {
      mode: figure.dataset.mode,
      figure,
      canvas: figure.querySelector("canvas"),
      timing: figure.querySelector(".timing"),
      error: figure.querySelector(".error"),
      seq: 0,
    };
    pane.scheduler = new LatestOnly(
      (params, signal) => api.render(params.request, signal),
      (result, params) => this.#show(pane, result, params),
      (error) => { if (!this.onError(error)) showError(pane.error, error.message); },
    );
    gestures(pane.canvas, {
      onDrag: (dx, dy, { pan }, event) => (pan ? this.pan(dx, dy, event) : this.orbit(dx, dy, event)),
      onZoom: (factor, event) => this.zoom(factor, event),
    });
    pane.canvas.addEventListener("keydown", (e) => this.#key(e));
    return pane;
  }

  /** Show `info` (GET /v1/models/{name}): its joints, its modes, a camera framing its box. */
  setModel(info) {
    this.panes.forEach((p) => p.scheduler.cancel());
    this.info = info;
    this.joints = jointSliders(this.root.querySelector("#model-joints"), info.joints, (e) => this.render(e), "model-joint");
    for (const box of this.root.querySelectorAll('input[name="mode"]')) {
      const available = info.modes.includes(box.value);
      box.disabled = !available;
      if (!available) box.checked = false;
    }
    const missing = ["narf", "parts"].filter((m) => !info.modes.includes(m));
    const modesError = this.root.querySelector("#modes-error");
    if (missing.length) showError(modesError, `model '${info.name}' has no ${missing.join(" or ")} field`);
    else clearError(modesError);
    this.resetCamera();
  }

  resetCamera() {
    if (!this.info) return;
    const { centre, radius } = boxCentre(this.info.bounds);
    const [w, h] = this.size();
    const halfFov = Math.atan((h / 2) / intrinsics(w, h, FOV_DEG)[1][1]);
    this.camera = { target: centre, azimuth: radians(-60), elevation: radians(50), distance: (1.15 * radius) / Math.sin(halfFov) };
    this.#layout();
  }

  size() { return this.sizeSelect.value.split("x").map(Number); }

  /** T_cam_obj of the view. */
  pose() { return orbitPose(this.camera); }

  orbit(dx, dy, event) {
    this.camera.azimuth -= dx * ORBIT_PER_PIXEL;
    this.camera.elevation = Math.max(-MAX_ELEVATION, Math.min(MAX_ELEVATION, this.camera.elevation + dy * ORBIT_PER_PIXEL));
    this.render(event);
  }

  /** Move the target so the model follows the pointer by (dx, dy) pixels. */
  pan(dx, dy, event) {
    const [w, h] = this.size();
    const { R } = split(this.pose());
    const metresPerPixel = this.camera.distance / intrinsics(w, h, FOV_DEG)[0][0] * (w / this.panes[0].canvas.width);
    this.camera.target = this.camera.target.map((v, i) => v - (R[0][i] * dx + R[1][i] * dy) * metresPerPixel);
    this.render(event);
  }

  zoom(factor, event) {
    const { radius } = boxCentre(this.info.bounds);
    this.camera.distance = Math.max(radius * 0.3, Math.min(radius * 40, this.camera.distance * factor));
    this.render(event);
  }

  #key(e) {
    const step = e.shiftKey ? 8 : 12;
    const moves = { ArrowLeft: [-step, 0], ArrowRight: [step, 0], ArrowUp: [0, -step], ArrowDown: [0, step] };
    if (moves[e.key]) (e.shiftKey ? this.pan(...moves[e.key], e) : this.orbit(...moves[e.key], e));
    else if (e.key === "+" || e.key === "=") this.zoom(1 / 1.15, e);
    else if (e.key === "-" || e.key === "_") this.zoom(1.15, e);
    else if (e.key === "0") this.resetCamera();
    else return;
    e.preventDefault();
  }

  #layout() {
    for (const pane of this.panes) {
      const on = this.root.querySelector(`input[name="mode"][value="${pane.mode}"]`).checked;
      pane.figure.hidden = !on;
      if (!on) pane.scheduler.cancel();
    }
    this.render();
  }

  /** Ask every shown pane for a new frame; `event` (the input that caused it) times the frame. */
  render(event = null) {
    if (!this.info || !this.camera) return;
    const t0 = event?.timeStamp ?? performance.now();
    const [width, height] = this.size();
    const T = this.pose();
    this.poseText.textContent = T.map((row) => row.map((v) => v.toFixed(4).padStart(8)).join(" ")).join("\n");
    const [lo, hi] = this.info.bounds; // the depth scale spans the model's box as seen from here
    const zs = [0, 1, 2, 3, 4, 5, 6, 7].map((i) => transformPoint(T, [i & 1 ? hi[0] : lo[0], i & 2 ? hi[1] : lo[1], i & 4 ? hi[2] : lo[2]])[2]);
    this.depthRange = [Math.max(0.01, Math.min(...zs)), Math.max(0.02, ...zs)];
    this.scale.hidden = this.output !== "depth";
    this.root.querySelector("#depth-near").textContent = `${this.depthRange[0].toFixed(3)} m`;
    this.root.querySelector("#depth-far").textContent = `${this.depthRange[1].toFixed(3)} m`;
    for (const pane of this.panes) {
      if (pane.figure.hidden) continue;
      const request = {
        model: this.info.name,
        pose: { matrix: T },
        joints: this.joints.values(),
        camera: { K: intrinsics(width, height, FOV_DEG), width, height },
        outputs: [this.output],
        mode: pane.mode,
      };
      pane.scheduler.submit({ request, t0, input: event?.type ?? "view", depthRange: this.depthRange, sent: performance.now() });
    }
  }

  async #show(pane, result, params) {
    const { width, height } = result;
    const ctx = pane.canvas.getContext("2d");
    if (params.request.outputs[0] === "depth") {
      const depth = await depthFromBase64(result.depth);
      [pane.canvas.width, pane.canvas.height] = [width, height];
      ctx.putImageData(colourDepth(depth, ...params.depthRange), 0, 0);
    } else {
      const bitmap = await bitmapFromBase64(result[params.request.outputs[0]]);
      [pane.canvas.width, pane.canvas.height] = [width, height];
      ctx.drawImage(bitmap, 0, 0);
    }
    clearError(pane.error);
    window.narfViewer.lastRequest[pane.mode] = params.request;
    const received = performance.now();
    await new Promise((resolve) => requestAnimationFrame(resolve));
    const painted = performance.now();
    const latency = painted - params.t0;
    pane.timing.textContent = `render ${(result.seconds * 1000).toFixed(0)} ms · on screen ${latency.toFixed(0)} ms after input`;
    logFrame({
      view: "model", mode: pane.mode, output: params.request.outputs[0], input: params.input, width, height,
      serverMs: result.seconds * 1000, roundTripMs: received - params.sent, latencyMs: latency, seq: ++pane.seq,
    });
  }
}

// Small pieces both views share: error messages beside their control, joint sliders, pointer and
// wheel gestures on a canvas, and the frame log the browser tests read.

import { degrees } from "./geometry.js";

/** Show `message` in the error element `node` and mark `control` (if any) invalid. */
export function showError(node, message, control = null) {
  node.textContent = message;
  node.hidden = false;
  control?.setAttribute("aria-invalid", "true");
}

/** Hide the error element `node` and unmark `control`. */
export function clearError(node, control = null) {
  node.textContent = "";
  node.hidden = true;
  control?.removeAttribute("aria-invalid");
}

/** A joint value with its unit: millimetres for prismatic joints, radians and degrees for revolute ones. */
export function formatJoint(joint, value) {
  if (joint.type === "prismatic") return `${(value * 1000).toFixed(1)} mm`;
  return `${value.toFixed(3)} rad (${degrees(value).toFixed(1)}°)`;
}

/**
 * One slider per joint in `fieldset` (its legend kept), labelled with name, type, value and limits.
 * `onInput(event)` runs on every change. Returns { values() -> {name: value}, set(values) }.
 */
export function jointSliders(fieldset, joints, onInput, idPrefix) {
  const legend = fieldset.querySelector("legend");
  fieldset.replaceChildren(legend);
  const inputs = new Map();
  if (!joints.length) fieldset.append(Object.assign(document.createElement("p"), { className: "hint", textContent: "No joints." }));
  for (const joint of joints) {
    const id = `${idPrefix}-${joint.name}`;
    const wrap = document.createElement("div");
    wrap.className = "joint";
    const label = document.createElement("label");
    label.htmlFor = id;
    const name = document.createElement("span");
    name.textContent = `${joint.name} (${joint.type})`;
    const value = document.createElement("output");
    value.htmlFor = id;
    label.append(name, value);
    const input = document.createElement("input");
    Object.assign(input, { type: "range", id, min: joint.lower, max: joint.upper, step: (joint.upper - joint.lower) / 200 });
    input.value = (joint.lower + joint.upper) / 2;
    input.dataset.joint = joint.name;
    const limits = document.createElement("div");
    limits.className = "limits";
    limits.innerHTML = "<span></span><span></span>";
    limits.children[0].textContent = formatJoint(joint, joint.lower);
    limits.children[1].textContent = formatJoint(joint, joint.upper);
    const update = () => {
      value.textContent = formatJoint(joint, Number(input.value));
      input.setAttribute("aria-valuetext", value.textContent);
    };
    input.addEventListener("input", (event) => { update(); onInput(event); });
    update();
    wrap.append(label, input, limits);
    fieldset.append(wrap);
    inputs.set(joint.name, { input, update });
  }
  const error = Object.assign(document.createElement("p"), { className: "error", hidden: true });
  error.setAttribute("role", "alert");
  fieldset.append(error);
  return {
    error,
    values: () => Object.fromEntries([...inputs].map(([name, { input }]) => [name, Number(input.value)])),
    set(values) {
      for (const [name, v] of Object.entries(values)) {
        const entry = inputs.get(name);
        if (entry) { entry.input.value = v; entry.update(); }
      }
    },
  };
}

/**
 * Mouse, pen and touch gestures on `canvas`, in canvas pixels:
 *   onDrag(dx, dy, { pan, turn, roll }) one pointer (pan: Shift, right or middle button; turn: Shift;
 *   roll: Alt), two pointers pan; onZoom(factor) wheel and pinch (factor > 1: farther).
 */
export function gestures(canvas, { onDrag, onZoom }) {
  const pointers = new Map();
  const scale = () => canvas.width / canvas.getBoundingClientRect().width;
  const centroid = () => {
    const ps = [...pointers.values()];
    return [ps.reduce((s, p) => s + p.x, 0) / ps.length, ps.reduce((s, p) => s + p.y, 0) / ps.length];
  };
  const spread = () => {
    const [a, b] = [...pointers.values()];
    return Math.hypot(a.x - b.x, a.y - b.y);
  };
  let last = null;
  canvas.addEventListener("pointerdown", (e) => {
    canvas.setPointerCapture(e.pointerId);
    pointers.set(e.pointerId, { x: e.clientX, y: e.clientY, button: e.button });
    last = { c: centroid(), spread: pointers.size === 2 ? spread() : 0 };
    canvas.focus({ preventScroll: true });
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!pointers.has(e.pointerId)) return;
    pointers.set(e.pointerId, { ...pointers.get(e.pointerId), x: e.clientX, y: e.clientY });
    const c = centroid(), s = scale();
    const dx = (c[0] - last.c[0]) * s, dy = (c[1] - last.c[1]) * s;
    if (pointers.size === 2) {
      const d = spread();
      if (last.spread > 0 && d > 0) onZoom(last.spread / d);
      onDrag(dx, dy, { pan: true, turn: false, roll: false }, e);
      last = { c, spread: d };
      return;
    }
    const button = pointers.get(e.pointerId).button;
    onDrag(dx, dy, { pan: e.shiftKey || button === 1 || button === 2, turn: e.shiftKey, roll: e.altKey }, e);
    last = { c, spread: 0 };
  });
  const end = (e) => {
    pointers.delete(e.pointerId);
    last = pointers.size ? { c: centroid(), spread: pointers.size === 2 ? spread() : 0 } : null;
  };
  canvas.addEventListener("pointerup", end);
  canvas.addEventListener("pointercancel", end);
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    onZoom(Math.exp(Math.max(-200, Math.min(200, e.deltaY)) * 0.0015), e);
  }, { passive: false });
}

/** Frames drawn so far, for people (the timing labels) and for the browser tests (window.narfViewer). */
export const frames = [];
window.narfViewer = { frames, lastRequest: {} }; // lastRequest: the request behind each pane's image

/** Log a drawn frame and announce it as a `narf:frame` event on the document. */
export function logFrame(detail) {
  frames.push(detail);
  document.dispatchEvent(new CustomEvent("narf:frame", { detail }));
}

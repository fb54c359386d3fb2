// A small SVG line plot of the refiner's loss, against iteration or elapsed time; log scale when the
// loss spans more than a decade. `trace` is the estimate's [[loss | null, seconds], ...].

const NS = "http://www.w3.org/2000/svg";
const W = 360, H = 200, PAD = { left: 56, right: 12, top: 12, bottom: 36 };

function el(name, attrs = {}, text = "") {
  const node = document.createElementNS(NS, name);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  if (text) node.textContent = text;
  return node;
}

function fmt(x) {
  if (x === 0) return "0";
  const a = Math.abs(x);
  return a >= 1000 || a < 0.01 ? x.toExponential(1) : x.toPrecision(3).replace(/\.?0+$/, "");
}

/** Draw `trace` into the <svg> `svg`, x = "iteration" or "seconds". */
export function plotLoss(svg, trace, x = "iteration") {
  svg.replaceChildren();
  svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  const points = trace
    .map(([loss, seconds], i) => [x === "seconds" ? seconds : i + 1, loss])
    .filter(([, loss]) => loss !== null && Number.isFinite(loss));
  if (!points.length) {
    svg.append(el("text", { x: W / 2, y: H / 2, "text-anchor": "middle", class: "plot-label" }, "no finite loss to plot"));
    svg.setAttribute("aria-label", "loss plot: no finite loss");
    return;
  }
  const xs = points.map((p) => p[0]), ys = points.map((p) => p[1]);
  const [x0, x1] = [Math.min(...xs), Math.max(...xs, Math.min(...xs) + 1e-9)];
  const positive = ys.every((y) => y > 0);
  const log = positive && Math.max(...ys) / Math.min(...ys) > 10;
  const f = log ? Math.log10 : (y) => y;
  let [y0, y1] = [Math.min(...ys.map(f)), Math.max(...ys.map(f))];
  if (y1 - y0 < 1e-12) [y0, y1] = [y0 - 1, y1 + 1];
  const px = (v) => PAD.left + ((v - x0) / (x1 - x0)) * (W - PAD.left - PAD.right);
  const py = (v) => H - PAD.bottom - ((f(v) - y0) / (y1 - y0)) * (H - PAD.top - PAD.bottom);
  const unf = (v) => (log ? 10 ** v : v);

  svg.append(el("rect", { x: PAD.left, y: PAD.top, width: W - PAD.left - PAD.right, height: H - PAD.top - PAD.bottom, class: "plot-frame" }));
  for (const t of [0, 0.5, 1]) {
    const yv = unf(y0 + t * (y1 - y0)), yy = py(yv);
    svg.append(el("text", { x: PAD.left - 6, y: yy + 4, "text-anchor": "end", class: "plot-tick" }, fmt(yv)));
    const xv = x0 + t * (x1 - x0);
    svg.append(el("text", { x: px(xv), y: H - PAD.bottom + 16, "text-anchor": "middle", class: "plot-tick" }, x === "seconds" ? fmt(xv) : String(Math.round(xv))));
  }
  svg.append(el("text", { x: (PAD.left + W - PAD.right) / 2, y: H - 4, "text-anchor": "middle", class: "plot-label" }, x === "seconds" ? "time (s)" : "iteration"));
  svg.append(el("text", { x: 12, y: (PAD.top + H - PAD.bottom) / 2, "text-anchor": "middle", class: "plot-label", transform: `rotate(-90 12 ${(PAD.top + H - PAD.bottom) / 2})` }, log ? "loss (log)" : "loss"));
  const d = points.map(([a, b], i) => `${i ? "L" : "M"}${px(a).toFixed(1)},${py(b).toFixed(1)}`).join("");
  svg.append(el("path", { d, class: "plot-line" }));
  svg.setAttribute("aria-label", `loss from ${fmt(ys[0])} to ${fmt(ys[ys.length - 1])} over ${points.length} iterations`);
}

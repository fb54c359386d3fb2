// Turning API images into pixels on a canvas: PNGs as sent, depth colour-mapped with a known scale,
// silhouettes as outlines. Depth is 16-bit millimetres with 0 = no return (the API's format).

import { decodePng, fromBase64 } from "./png.js";

// Turbo colour map (Google, Apache-2.0), sampled at 9 stops and interpolated linearly.
const TURBO = [
  [48, 18, 59], [70, 107, 227], [41, 187, 236], [49, 241, 157], [162, 252, 60],
  [237, 208, 58], [251, 128, 34], [208, 47, 5], [122, 4, 3],
];

/** [r, g, b] (0-255) of the colour map at `x` in [0, 1]. */
export function colormap(x) {
  const s = Math.max(0, Math.min(1, x)) * (TURBO.length - 1);
  const i = Math.min(TURBO.length - 2, Math.floor(s)), f = s - i;
  return TURBO[i].map((c, k) => Math.round(c + f * (TURBO[i + 1][k] - c)));
}

/** A base64 PNG from /v1/render as an ImageBitmap (rgb, opacity). */
export async function bitmapFromBase64(text) {
  return createImageBitmap(new Blob([fromBase64(text)], { type: "image/png" }));
}

/** A base64 16-bit depth PNG -> { width, height, mm: Uint16Array }. */
export async function depthFromBase64(text) {
  const png = await decodePng(fromBase64(text));
  if (png.bitDepth !== 16 || png.channels !== 1) throw new Error("depth is not a 16-bit single-channel PNG");
  return { width: png.width, height: png.height, mm: png.data };
}

/** ImageData of depth `mm` coloured over [near, far] metres; no return stays dark grey. */
export function colourDepth({ width, height, mm }, near, far) {
  const image = new ImageData(width, height), px = image.data;
  const span = Math.max(far - near, 1e-6);
  for (let i = 0; i < mm.length; i++) {
    const [r, g, b] = mm[i] ? colormap((mm[i] / 1000 - near) / span) : [24, 24, 24];
    px.set([r, g, b, 255], 4 * i);
  }
  return image;
}

/** Draw a colour bar for the depth scale into `canvas` (left = near, right = far). */
export function drawColourBar(canvas) {
  const ctx = canvas.getContext("2d"), { width, height } = canvas;
  for (let x = 0; x < width; x++) {
    const [r, g, b] = colormap(x / (width - 1));
    ctx.fillStyle = `rgb(${r},${g},${b})`;
    ctx.fillRect(x, 0, 1, height);
  }
}

/** Alpha (Uint8Array, width * height) of an ImageBitmap's red channel: opacity PNGs are greyscale. */
export function channelOf(bitmap) {
  const canvas = new OffscreenCanvas(bitmap.width, bitmap.height), ctx = canvas.getContext("2d", { willReadFrequently: true });
  ctx.drawImage(bitmap, 0, 0);
  const px = ctx.getImageData(0, 0, bitmap.width, bitmap.height).data, out = new Uint8Array(bitmap.width * bitmap.height);
  for (let i = 0; i < out.length; i++) out[i] = px[4 * i];
  return out;
}

/** The boundary pixels (inside pixels with an outside 4-neighbour) of `values > threshold`, as a Uint8Array mask. */
export function outline(values, width, height, threshold = 127) {
  const out = new Uint8Array(width * height);
  const inside = (x, y) => x >= 0 && y >= 0 && x < width && y < height && values[y * width + x] > threshold;
  for (let y = 0; y < height; y++) {
    for (let x = 0; x < width; x++) {
      if (inside(x, y) && !(inside(x - 1, y) && inside(x + 1, y) && inside(x, y - 1) && inside(x, y + 1))) out[y * width + x] = 1;
    }
  }
  return out;
}

/** A transparent OffscreenCanvas with the pixels set in `edge` painted `colour` [r, g, b]. */
export function outlineLayer(edge, width, height, colour) {
  const layer = new OffscreenCanvas(width, height), image = new ImageData(width, height);
  for (let i = 0; i < edge.length; i++) if (edge[i]) image.data.set([...colour, 255], 4 * i);
  layer.getContext("2d").putImageData(image, 0, 0);
  return layer;
}

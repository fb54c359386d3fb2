// The public API v1, as the viewer uses it: /v1/models, /v1/render, /v1/estimate, with the bearer
// token the user typed (kept in sessionStorage, so it is forgotten with the tab). Errors become an
// ApiError carrying the server's message and, where it names one, the offending field.

const TOKEN_KEY = "narf.token";

export class ApiError extends Error {
  constructor(status, message, field = null, code = null) {
    super(message);
    this.name = "ApiError";
    this.status = status;
    this.field = field;
    this.code = code;
  }
}

export function getToken() { return sessionStorage.getItem(TOKEN_KEY) || ""; }
export function setToken(token) {
  if (token) sessionStorage.setItem(TOKEN_KEY, token);
  else sessionStorage.removeItem(TOKEN_KEY);
}

async function call(path, { method = "GET", json, form, signal } = {}) {
  const headers = { Accept: "application/json" };
  const token = getToken();
  if (token) headers.Authorization = `Bearer ${token}`;
  let body;
  if (json !== undefined) {
    headers["Content-Type"] = "application/json";
    body = JSON.stringify(json);
  } else if (form) body = form;
  let response;
  try {
    response = await fetch(path, { method, headers, body, signal });
  } catch (e) {
    if (e.name === "AbortError") throw e;
    throw new ApiError(0, "the server cannot be reached (is `narf serve` still running?)");
  }
  if (response.ok) return response.json();
  let detail = {};
  try { detail = (await response.json()).error || {}; } catch { /* not JSON: keep the status line */ }
  if (response.status === 401) {
    throw new ApiError(401, "The server needs a bearer token: type it in the Token field (the server's NARF_TOKEN or --token-file).", "token", "unauthorized");
  }
  const message = detail.message || `${response.status} ${response.statusText}`;
  throw new ApiError(response.status, message, detail.field || null, detail.code || null);
}

export function listModels(signal) { return call("/v1/models", { signal }); }
export function getModel(name, signal) { return call(`/v1/models/${encodeURIComponent(name)}`, { signal }); }

/** POST /v1/render: `request` is a RenderRequest (model, pose, joints, camera, outputs, mode). */
export function render(request, signal) { return call("/v1/render", { method: "POST", json: request, signal }); }

/** POST /v1/estimate: `request` an EstimateRequest; `files` { image, mask, depth? } as Blobs. */
export function estimate(request, files, signal) {
  const form = new FormData();
  form.append("request", JSON.stringify(request));
  form.append("image", files.image, files.image.name || "image.png");
  form.append("mask", files.mask, files.mask.name || "mask.png");
  if (files.depth) form.append("depth", files.depth, files.depth.name || "depth.png");
  return call("/v1/estimate", { method: "POST", form, signal });
}

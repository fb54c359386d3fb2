// The viewer's entry point: the token, the model list, the two tabs, and the link between the views.

import * as api from "./api.js";
import { EstimateView } from "./estimate_view.js";
import { ModelView } from "./model_view.js";
import { clearError, showError } from "./ui.js";

const $ = (id) => document.getElementById(id);
const tokenInput = $("token"), tokenError = $("token-error");
const modelSelect = $("model"), modelError = $("model-error");

/** A 401 is about the token, wherever it happened: say so next to the token field. */
function onError(error) {
  if (error.status !== 401) return false;
  showError(tokenError, error.message, tokenInput);
  tokenInput.focus();
  return true;
}

const modelView = new ModelView($("view-model"), { onError });
const estimateView = new EstimateView($("view-estimate"), { onError });

async function chooseModel(name) {
  clearError(modelError, modelSelect);
  try {
    const info = await api.getModel(name);
    modelView.setModel(info);
    estimateView.setModel(info);
  } catch (error) {
    if (!onError(error)) showError(modelError, `model: ${error.message}`, modelSelect);
  }
}

async function loadModels() {
  clearError(modelError, modelSelect);
  let list;
  try {
    list = (await api.listModels()).models;
  } catch (error) {
    if (!onError(error)) showError(modelError, `models: ${error.message}`, modelSelect);
    return;
  }
  clearError(tokenError, tokenInput);
  const previous = modelSelect.value;
  modelSelect.replaceChildren(...list.map((m) => new Option(m.name, m.name)));
  if (!list.length) {
    showError(modelError, "this server serves no model (see `narf serve --models`)", modelSelect);
    return;
  }
  modelSelect.value = list.some((m) => m.name === previous) ? previous : list[0].name;
  await chooseModel(modelSelect.value);
}

modelSelect.addEventListener("change", () => chooseModel(modelSelect.value));
tokenInput.value = api.getToken();
$("token-form").addEventListener("submit", (e) => {
  e.preventDefault();
  api.setToken(tokenInput.value.trim());
  loadModels();
});

// Tabs (WAI-ARIA tabs pattern: arrow keys move between them).
const tabs = [$("tab-model"), $("tab-estimate")];
function select(tab) {
  for (const t of tabs) {
    const on = t === tab;
    t.setAttribute("aria-selected", String(on));
    t.tabIndex = on ? 0 : -1;
    $(t.getAttribute("aria-controls")).hidden = !on;
  }
}
tabs.forEach((tab, i) => {
  tab.addEventListener("click", () => select(tab));
  tab.addEventListener("keydown", (e) => {
    const next = { ArrowRight: 1, ArrowLeft: -1 }[e.key];
    if (!next) return;
    const target = tabs[(i + next + tabs.length) % tabs.length];
    select(target);
    target.focus();
  });
});

$("use-view").addEventListener("click", () => {
  estimateView.setInitial(modelView.pose(), modelView.joints.values());
  select(tabs[1]);
});

loadModels();

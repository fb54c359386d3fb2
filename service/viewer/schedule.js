// Latest-wins request scheduling, so that dragging a slider or the camera stays fluid: at most one
// request of a view is in flight; while it runs, newer requests replace each other and only the latest
// is sent when it returns (the superseded ones are cancelled before they cost the server anything).
// `cancel()` also aborts the one in flight (a new model or image size makes its answer useless).

export class LatestOnly {
  /**
   * @param {(params: object, signal: AbortSignal) => Promise<object>} run  the request
   * @param {(result: object, params: object) => Promise<void> | void} show  draws an answer
   * @param {(error: Error, params: object) => void} fail  reports a failed request
   */
  constructor(run, show, fail) {
    Object.assign(this, { run, show, fail });
    this.pending = null;
    this.controller = null;
    this.busy = false;
  }

  submit(params) {
    this.pending = params;
    if (!this.busy) this.#drain();
  }

  cancel() {
    this.pending = null;
    this.controller?.abort();
  }

  /** Resolves once nothing is pending or in flight. */
  async idle() {
    while (this.busy) await new Promise((resolve) => setTimeout(resolve, 10));
  }

  async #drain() {
    this.busy = true;
    while (this.pending) {
      const params = this.pending;
      this.pending = null;
      this.controller = new AbortController();
      try {
        const result = await this.run(params, this.controller.signal);
        await this.show(result, params);
      } catch (error) {
        if (error.name !== "AbortError") this.fail(error, params);
      }
    }
    this.controller = null;
    this.busy = false;
  }
}

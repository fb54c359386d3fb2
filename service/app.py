"""The HTTP API v1 (docs/design.md §8): render and estimate with the served models.

``create_app()`` builds the FastAPI app; models are loaded once, in the lifespan, from
``settings.models_dir``. Compute runs on a bounded :class:`~narf_service.workers.WorkQueue`; a full
queue answers 503 with ``Retry-After``; a client that disconnects cancels its job. A tracking
frame's job hands the frame on to a child process (:mod:`narf_service.processes`), so that
concurrent tracks use every worker's core instead of taking turns at this interpreter's lock.
Every error has the body ``{"error": {"code", "message", "field"?}}`` (see :mod:`narf_service.errors`). The token,
timeouts and body limits are enforced before a route runs (:mod:`narf_service.guards`,
:mod:`narf_service.limits`, :mod:`narf_service.bodies`).
"""

from __future__ import annotations

import asyncio
import pathlib
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Annotated, Any

import torch
from fastapi import APIRouter, Depends, FastAPI, File, Form, Header, Path, Request, UploadFile
from fastapi.responses import JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import Json

from narf_core.threads import AUTO, choose_threads
from narf_service import jobs, tracking
from narf_service.bodies import GuardedBodyRoute
from narf_service.engine import Engine
from narf_service.errors import install_error_handlers, invalid
from narf_service.guards import AuthGate, BodyDeadline, authorized
from narf_service.limits import BodySizeLimit
from narf_service.monitoring import MetricsMiddleware, ServiceMetrics
from narf_service.processes import ModelProcesses
from narf_service.registry import MODEL_NAME_MAX, MODEL_NAME_PATTERN, ModelRegistry
from narf_service.schemas import (
    EstimateRequest,
    EstimateResponse,
    Health,
    ModelInfo,
    ModelList,
    Readiness,
    RenderRequest,
    RenderResponse,
)
from narf_service.routing import check_pixels, error_responses, registry_of, require_token, run_job
from narf_service.settings import Settings
from narf_service.workers import WorkQueue

API_VERSION = "1"
VIEWER_DIR = pathlib.Path(__file__).resolve().parent / "viewer"
"""The web viewer's static files (plain HTML, CSS and JavaScript modules), served at ``/viewer``."""
PNG = "image/png"


def prefers_png(accept: str | None) -> bool:
    """Whether an ``Accept`` header ranks ``image/png`` above ``application/json`` (q-values honoured)."""
    if not accept:
        return False

    def quality(media_type: str) -> float:
        main = media_type.split("/")[0]
        best_specificity, best_q = -1, 0.0
        for item in accept.split(","):
            media_range, *params = (p.strip() for p in item.split(";"))
            media_range = media_range.lower()
            specificity = {media_type: 2, f"{main}/*": 1, "*/*": 0}.get(media_range, -1)
            if specificity <= best_specificity:
                continue
            q = 1.0
            for param in params:
                key, _, value = param.partition("=")
                if key.strip().lower() == "q":
                    try:
                        q = float(value)
                    except ValueError:
                        q = 0.0
            best_specificity, best_q = specificity, q
        return best_q

    png = quality(PNG)
    return png > 0 and png > quality("application/json")


v1 = APIRouter(
    prefix="/v1", dependencies=[Depends(require_token)], responses=error_responses(401), route_class=GuardedBodyRoute
)


@v1.get("/models", response_model=ModelList, summary="The served models")
async def list_models(registry: Annotated[ModelRegistry, Depends(registry_of)]) -> ModelList:
    return ModelList(models=[jobs.describe(name, registry.models[name], full=False) for name in registry])


@v1.get(
    "/models/{name}",
    response_model=ModelInfo,
    responses=error_responses(404, 422),
    summary="One model: links, joints and limits, bounds, metrics",
)
async def get_model(
    registry: Annotated[ModelRegistry, Depends(registry_of)],
    name: Annotated[str, Path(max_length=MODEL_NAME_MAX, pattern=MODEL_NAME_PATTERN)],
) -> Any:
    return jobs.describe(name, registry.get(name, field="name"), full=True)


@v1.post(
    "/render",
    response_model=RenderResponse,
    responses={
        200: {"content": {PNG: {"schema": {"type": "string", "format": "binary"}}}},
        **error_responses(400, 404, 413, 422, 503),
    },
    summary="Render a model at a pose and configuration",
    description="Images as base64 PNG in JSON; with `Accept: image/png` the one asked output as a PNG body "
    "(depth: 16-bit millimetres, 0 = no return).",
)
async def render(
    request: Request,
    body: RenderRequest,
    registry: Annotated[ModelRegistry, Depends(registry_of)],
    accept: Annotated[str | None, Header()] = None,
) -> Any:
    settings: Settings = request.app.state.settings
    model = registry.get(body.model)
    check_pixels(body.camera, settings, "camera")
    jobs.check_joints(model, body.joints, "joints")
    jobs.check_mode(model, body.mode, "mode")
    if prefers_png(accept):
        if len(body.outputs) != 1:
            raise invalid("outputs", f"'Accept: {PNG}' returns one image; ask for exactly one output")
        answer = await run_job(request, lambda stop: jobs.render_png(model, body, stop))
        if isinstance(answer, Response):
            return answer
        png, seconds = answer
        return Response(png, media_type=PNG, headers={"X-Render-Seconds": f"{seconds:.6f}"})
    return await run_job(request, lambda stop: jobs.render_json(body.model, model, body, stop))


@v1.post(
    "/estimate",
    response_model=EstimateResponse,
    responses=error_responses(400, 404, 413, 422, 503),
    summary="Estimate pose and configuration from an image and a mask",
    description="Multipart: `image` (PNG/JPEG), `mask` (PNG), optional `depth` (16-bit PNG millimetres or .npy "
    "float32 metres) files and the `request` form field holding an EstimateRequest as JSON (curl: "
    "`-F image=@rgb.png -F mask=@mask.png -F 'request=<request.json'`). With `ground_truth`, `metrics` carries "
    "ADD, ADD-S and the joint errors.",
)
async def estimate(
    request: Request,
    params: Annotated[Json[EstimateRequest], Form(alias="request", description="JSON: an EstimateRequest")],
    image: Annotated[UploadFile, File(description="RGB image, PNG or JPEG, the camera's size")],
    mask: Annotated[UploadFile, File(description="Object mask, single-channel PNG, non-zero = object")],
    registry: Annotated[ModelRegistry, Depends(registry_of)],
    depth: Annotated[UploadFile | None, File(description="16-bit PNG (mm, 0 = none) or .npy (float32 m)")] = None,
) -> Any:
    started = time.perf_counter()
    settings: Settings = request.app.state.settings
    model = registry.get(params.model, field="request.model")
    check_pixels(params.camera, settings, "request.camera")
    if params.iterations is not None and params.iterations > settings.max_iterations:
        raise invalid(
            "request.iterations", f"{params.iterations} exceeds this server's limit of {settings.max_iterations}"
        )
    jobs.check_joints(model, params.initial_joints, "request.initial_joints")
    jobs.check_mode(model, params.options.mode, "request.options.mode")
    if params.ground_truth is not None:
        jobs.check_joints(model, params.ground_truth.joints, "request.ground_truth.joints", complete=True)
    engine: Engine = request.app.state.engine
    uploads = {
        "image": await image.read(),
        "mask": await mask.read(),
        "depth": await depth.read() if depth is not None else None,
    }
    has_depth = bool(uploads["depth"])
    options, preset, preset_reason = jobs.refine_options(engine, params, "request.options", depth=has_depth)
    jobs.check_work(options, settings.max_work_rays, "request.options", depth=has_depth)
    return await run_job(
        request,
        lambda stop: jobs.estimate(
            engine,
            params.model,
            model,
            params,
            uploads,
            options=options,
            max_pixels=settings.max_image_pixels,
            started=started,
            should_stop=stop,
            preset=(preset, preset_reason),
        ),
    )


ops = APIRouter(tags=["operations"])


@ops.get("/healthz", response_model=Health, summary="Liveness: the process answers")
async def healthz() -> Health:
    return Health()


@ops.head("/healthz", include_in_schema=False)  # load balancers probe with HEAD
async def healthz_head() -> Response:
    return Response(media_type="application/json")


@ops.get(
    "/readyz",
    response_model=Readiness,
    responses={503: {"model": Readiness}},
    summary="Readiness: at least one model is loaded",
    description="`failed` names the bundles that were refused, with a one-line reason; when the server "
    "has a token, the reasons are shown only to requests that carry it.",
)
async def readyz(request: Request, registry: Annotated[ModelRegistry, Depends(registry_of)]) -> Any:
    ready = len(registry) > 0
    failed = registry.failed
    if not authorized(request.app.state.settings, request.headers.get("authorization")):
        failed = {name: "not loaded" for name in failed}
    body = Readiness(status="ready" if ready else "not_ready", models=list(registry), failed=failed)
    return body if ready else JSONResponse(body.model_dump(), status_code=503)


@ops.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}},
    summary="Prometheus metrics",
)
async def metrics(request: Request) -> Response:
    return Response(request.app.state.metrics.exposition(), media_type="text/plain; version=0.0.4")


def create_app(
    settings: Settings | None = None,
    *,
    engine: Engine | None = None,
    registry: ModelRegistry | None = None,
) -> FastAPI:
    """The service. ``engine`` defaults to narf_core's; ``registry`` to the bundles in ``settings.models_dir``.

    Both are resolved in the lifespan (at server start), so building the app is cheap and loads nothing.
    """
    settings = settings or Settings()
    metrics = ServiceMetrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        threads = settings.torch_threads or choose_threads(AUTO, share=settings.workers)
        torch.set_num_threads(threads)
        app.state.engine = engine if engine is not None else Engine.narf_core()
        if registry is not None:
            app.state.registry = registry
        else:
            app.state.registry = await asyncio.to_thread(
                ModelRegistry.load_folder, settings.models_dir, app.state.engine.load_bundle, settings.device
            )
        queue = WorkQueue(settings.workers, settings.queue_size, retry_after_max_s=settings.retry_after_max_s)
        app.state.queue = queue
        app.state.processes = None
        if settings.track_processes:  # a job's process outlives its budget only by a margin, then it is killed
            app.state.processes = ModelProcesses(app.state.registry.models, settings.workers, torch_threads=threads,
                                                 timeout_s=settings.max_seconds + 60)
        metrics.watch(queue, app.state.registry)
        try:
            yield
        finally:
            queue.shutdown()
            if app.state.processes is not None:
                app.state.processes.close()

    app = FastAPI(
        title="NARF",
        version=f"{API_VERSION}.0",
        summary="Render-and-compare pose and joint-configuration estimation for articulated objects.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.metrics = metrics
    install_error_handlers(app)
    app.include_router(v1)
    app.include_router(ops)
    tracking.install(app, settings)
    # The viewer needs the token like any route unless NARF_PUBLIC_ROUTES lists /viewer; its API calls carry it.
    app.mount("/viewer", StaticFiles(directory=VIEWER_DIR, html=True), name="viewer")
    app.add_middleware(BodyDeadline, seconds=settings.body_timeout_s)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(AuthGate, settings=settings)  # outside the body limit: no byte is read before the token
    app.add_middleware(MetricsMiddleware, metrics=metrics)
    return app


"""The seam between the HTTP layer and the library: how bundles load and how estimates are computed.

:meth:`Engine.narf_core` binds the real library (imported when the service starts, not when this
module is imported); tests may bind doubles that follow the same API.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from narf_core.bundle import NarfModel
    from narf_core.estimate import EstimateResult


@dataclass(frozen=True)
class Engine:
    """``load_bundle(path, device)``, ``refine(model, image, mask, camera, T_init, **kw)``, the
    refiner's options from a named preset and the request's other ``options`` fields and
    the exception type ``refine`` raises for unusable input (answered 422)."""

    load_bundle: Callable[[Path, str], NarfModel]
    refine: Callable[..., EstimateResult]
    options: Callable[..., Any]
    input_error: type[Exception]

    @classmethod
    def narf_core(cls) -> Engine:
        from narf_core.bundle import load_bundle
        from narf_core.estimate import EstimateInputError, EstimateOptions, refine

        def options(preset: str, **fields) -> EstimateOptions:
            return EstimateOptions.preset(preset, **fields)

        return cls(load_bundle=load_bundle, refine=refine, options=options, input_error=EstimateInputError)

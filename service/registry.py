"""The models a service instance serves, loaded once at start from one folder.

Names are the bundle file stems (``models/clamp.narf`` is ``clamp``) and must match
:data:`MODEL_NAME_PATTERN`. A request names a model; it is looked up in this registry's dict and
never turned into a path, so no request can reach a file outside the folder. Files whose real path
(symlinks resolved) lies outside the folder are refused at load time as well.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from narf_service.errors import ApiError

if TYPE_CHECKING:
    from narf_core.bundle import NarfModel

logger = logging.getLogger("narf_service")

MODEL_NAME_PATTERN = r"^[A-Za-z0-9_-]+(\.[A-Za-z0-9_-]+)*$"
"""Letters, digits, ``_``, ``-`` and single inner dots: no ``/``, no ``..``, nothing absolute."""
MODEL_NAME_MAX = 64

_NAME_RE = re.compile(MODEL_NAME_PATTERN)

BundleLoader = Callable[[Path, str], "NarfModel"]


def one_line_reason(error: BaseException, path: Path, limit: int = 300) -> str:
    """Why ``path`` was refused, on one line, with the file's name instead of its full path."""
    message = " ".join(str(error).replace(str(path), path.name).split()) or type(error).__name__
    message = message.removeprefix(f"{path.name}: ")
    return message if len(message) <= limit else message[: limit - 3] + "..."


def valid_model_name(name: str) -> bool:
    return len(name) <= MODEL_NAME_MAX and _NAME_RE.fullmatch(name) is not None


@dataclass
class ModelRegistry:
    """``name -> model``, plus the bundles that failed to load (``name -> reason``)."""

    models: dict[str, NarfModel] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)

    @classmethod
    def load_folder(cls, folder: Path, loader: BundleLoader, device: str = "cpu") -> ModelRegistry:
        """Load every ``*.narf`` directly inside ``folder`` with ``loader(path, device)``.

        A bundle the loader refuses (``ValueError``, which ``BundleError`` is, or ``OSError``) is
        logged and listed in ``failed``; the others are still served.
        """
        registry = cls()
        root = folder.resolve()
        if not root.is_dir():
            logger.error("models folder %s does not exist", folder)
            return registry
        for path in sorted(root.glob("*.narf")):
            name = path.stem
            if not valid_model_name(name):
                registry.failed[name] = f"file name {path.name!r} is not a valid model name"
            elif not path.resolve().is_relative_to(root):
                registry.failed[name] = f"{path.name} points outside the models folder"
            else:
                try:
                    registry.models[name] = loader(path, device)
                except (ValueError, OSError) as e:
                    registry.failed[name] = one_line_reason(e, path)
            if name in registry.failed:
                logger.error("model %s not loaded: %s", name, registry.failed[name])
            else:
                logger.info("model %s loaded from %s", name, path)
                if "checksum" not in registry.models[name].metadata:
                    logger.warning(
                        "model %s: %s has no checksum (saved before NARF wrote one); only its weights' finiteness "
                        "was checked. Load and save it again (narf_core.bundle) to add one.", name, path.name
                    )
        return registry

    def get(self, name: str, field: str = "model") -> NarfModel:
        """The model called ``name``; a 404 naming ``field`` and the served models if there is none."""
        try:
            return self.models[name]
        except KeyError:
            served = ", ".join(sorted(self.models)) or "none"
            raise ApiError(404, f"{field}: unknown model {name!r} (served: {served})", field=field) from None

    def __iter__(self) -> Iterator[str]:
        return iter(sorted(self.models))

    def __len__(self) -> int:
        return len(self.models)

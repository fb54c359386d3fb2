"""Radiance fields: a part field per rigid link and the configuration-conditioned field.

``make_field(field.config())`` rebuilds any field of this package (weights come separately, from
its ``state_dict``).
"""

from __future__ import annotations

from narf_core.fields.articulated import ArticulatedField
from narf_core.fields.base import RadianceField
from narf_core.fields.fastnerf import FastNeRFField
from narf_core.fields.kplanes import KPlanesField

ARCHITECTURES = ("kplanes", "fastnerf", "articulated")

__all__ = ["ARCHITECTURES", "ArticulatedField", "FastNeRFField", "KPlanesField", "RadianceField", "make_field"]


def make_field(config: dict) -> RadianceField:
    """A new (untrained) field from ``config``: ``{"arch": "kplanes" | "fastnerf" | "articulated", "aabb": ..., ...}``.

    The other keys are the architecture's keyword arguments; missing ones take their defaults.
    Raises ``ValueError`` for an unknown architecture or an unknown or invalid hyper-parameter.
    """
    kwargs = dict(config)
    arch = kwargs.pop("arch", None)
    if arch == "kplanes":
        cls: type[RadianceField] = KPlanesField
    elif arch == "fastnerf":
        cls = FastNeRFField
    elif arch == "articulated":
        cls = ArticulatedField
    else:
        raise ValueError(f"unknown field architecture {arch!r}; expected one of {', '.join(ARCHITECTURES)}")
    if "aabb" not in kwargs:
        raise ValueError(f"field config for {arch!r} needs an 'aabb' ([[xmin, ymin, zmin], [xmax, ymax, zmax]])")
    try:
        return cls(**kwargs)
    except TypeError as e:
        raise ValueError(f"invalid {arch!r} field config: {e}") from None

"""The input rules of the core, stated once: numbers, rigid poses, joint values.

Every check raises :class:`InputError` (or the subclass its caller names with ``error=``, such as
``EstimateInputError``), whose message starts with the argument it is about and whose ``field``
is that argument's dotted path (``joints_init.slide``). The outer floors only map it: the CLI to
one line ``narf <cmd>: error: <message>`` (exit 2), the service to a 422 naming ``field``.

A pose is ``T [4, 4]``: finite numbers, last row ``[0, 0, 0, 1]`` to :data:`BOTTOM_ROW_TOLERANCE`,
a rotation block with ``max |R^T R - I|`` at most :data:`ROTATION_TOLERANCE` (float32 writers and
poses printed with 4-6 digits pass) and ``det R > 0`` (no reflection).

Joint values are checked against joint specs: anything with ``name``, ``type``, ``lower`` and
``upper`` (a :class:`~narf_core.kinematics.Joint`, a :class:`JointSpec`): every name known,
every value a finite number within ``[lower, upper]`` widened by :data:`LIMIT_TOLERANCE`.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

ROTATION_TOLERANCE = 1e-3
"""Largest entry of ``|R^T R - I|`` accepted in a pose."""
BOTTOM_ROW_TOLERANCE = 1e-6
"""Largest deviation of a pose's last row from ``[0, 0, 0, 1]``."""
LIMIT_TOLERANCE = 1e-6
"""Joint values this far (radians or metres) outside their limits are still accepted: float32 round-off."""


class InputError(ValueError):
    """An argument the core cannot use. The message starts with the argument's name; ``field`` is
    its dotted path down to the offending entry (``joints_init.slide``) and ``reason`` what is wrong
    with that entry, without the names (for a floor that puts its own field before it)."""

    def __init__(self, message: str, field: str | None = None, reason: str | None = None) -> None:
        super().__init__(message)
        self.field = field
        self.reason = reason if reason is not None else message


class JointLike(Protocol):
    """What :func:`check_joints` reads of a joint."""

    name: str
    type: str
    lower: float
    upper: float


@dataclass(frozen=True)
class JointSpec:
    """A movable joint: its name, URDF type and limits (radians or metres)."""

    name: str
    type: str
    lower: float
    upper: float


def option_rule(options: Any, error: type[InputError] = InputError) -> Callable[[bool, str, str], None]:
    """``need(ok, name, what)`` for an options dataclass: unless ``ok``, raise ``error`` whose field is
    ``options.<name>`` and whose reason is ``what`` and the value the option holds."""

    def need(ok: bool, name: str, what: str) -> None:
        if not ok:
            reason = f"{what}, got {getattr(options, name)!r}"
            raise error(f"options.{name} {reason}", f"options.{name}", reason)

    return need


def check_option_types(options: Any, error: type[InputError] = InputError) -> None:
    """Every field of the options dataclass holds its declared type: ``bool`` a bool, ``int`` an
    integer (not a bool), ``float`` a finite number (not a bool); other types are the caller's."""
    need = option_rule(options, error)
    for spec in dataclasses.fields(options):
        value = getattr(options, spec.name)
        if spec.type == "bool":
            need(isinstance(value, bool), spec.name, "must be true or false")
        elif spec.type == "int":
            need(isinstance(value, int) and not isinstance(value, bool), spec.name, "must be an integer")
        elif spec.type == "float":
            need(isinstance(value, (int, float)) and not isinstance(value, bool), spec.name, "must be a number")
            need(math.isfinite(value), spec.name, "must be finite")


def check_number(value: Any, field: str, *, error: type[InputError] = InputError) -> float:
    """``value`` as a float if it is a finite real number (not a bool)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        reason = f"must be a finite number, got {_describe(value)}"
        raise error(f"{field} {reason}", field, reason)
    return float(value)


def check_pose(T: Any, field: str, *, error: type[InputError] = InputError) -> np.ndarray:
    """A copy of ``T`` as float64 ``[4, 4]`` if it is a rigid pose (see the module docstring)."""
    array = np.asarray(T) if not hasattr(T, "detach") else T.detach().cpu().numpy()
    reason = _pose_problem(array)
    if reason is not None:
        raise error(f"{field} {reason}", field, reason)
    return array.astype(np.float64)


def _pose_problem(T: np.ndarray) -> str | None:
    """What makes ``T`` not a rigid pose, or ``None``."""
    if T.shape != (4, 4):
        return f"must be a 4x4 pose matrix, got shape {tuple(T.shape)}"
    if not np.issubdtype(T.dtype, np.number) or np.iscomplexobj(T):
        return f"must be a 4x4 matrix of real numbers, got dtype {T.dtype}"
    if not np.isfinite(T).all():
        return f"must be finite numbers, got NaN or infinite values in {T.tolist()}"
    T = T.astype(np.float64)
    if np.abs(T[3] - [0, 0, 0, 1]).max() > BOTTOM_ROW_TOLERANCE:
        return f"must have the last row [0, 0, 0, 1], got {T[3].tolist()}"
    R = T[:3, :3]
    deviation = float(np.abs(R.T @ R - np.eye(3)).max())
    if deviation > ROTATION_TOLERANCE:
        return f"has a rotation block that is not orthonormal (max |R^T R - I| = {deviation:.3g} > {ROTATION_TOLERANCE:g})"
    if np.linalg.det(R) < 0:
        return "has a rotation block that is a reflection (determinant -1), not a rotation"
    return None


def check_joints(
    specs: Sequence[JointLike],
    joints: Mapping[str, Any] | None,
    field: str,
    *,
    complete: bool = False,
    error: type[InputError] = InputError,
) -> dict[str, float]:
    """``{name: value}`` checked against ``specs``, as floats in the order of ``specs``.

    ``None`` is ``{}``. Refused: a non-mapping, a name not in ``specs``, a value that is not a
    finite number or lies outside its limits by more than :data:`LIMIT_TOLERANCE` and, with
    ``complete``, a joint of ``specs`` left out.
    """
    joints = {} if joints is None else joints
    if not isinstance(joints, Mapping):
        raise error(f"{field} must be a mapping {{joint name: value}}, got {_describe(joints)}", field)
    by_name = {spec.name: spec for spec in specs}
    unknown = [name for name in joints if name not in by_name]
    if unknown:
        reason = f"unknown joint(s) {unknown}; this object's joints are {list(by_name) or 'none'}"
        raise error(f"{field}: {reason}", f"{field}.{unknown[0]}", reason)
    if complete:
        missing = [name for name in by_name if name not in joints]
        if missing:
            reason = f"missing value(s) for joint(s) {missing}"
            raise error(f"{field}: {reason}", field, reason)
    values = {}
    for name, spec in by_name.items():
        if name not in joints:
            continue
        value, reason = joints[name], None
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            reason = f"value must be a number, got {_describe(value)}"
        elif not math.isfinite(value):
            reason = f"value must be finite, got {float(value)}"
        elif not spec.lower - LIMIT_TOLERANCE <= value <= spec.upper + LIMIT_TOLERANCE:
            unit = "m" if spec.type == "prismatic" else "rad"
            reason = f"{float(value)} is outside its limits [{spec.lower}, {spec.upper}] ({unit})"
        if reason is not None:
            raise error(f"{field}: joint {name!r}: {reason}", f"{field}.{name}", reason)
        values[name] = float(value)
    return values


def _describe(value: object) -> str:
    text = repr(value)
    return f"{type(value).__name__} {text[:60] + '...' if len(text) > 60 else text}"

"""rclpy side of the typed node configs: declare parameters with descriptors, keep a snapshot.

`TypedParams(node, ConfigClass)` declares every field of the config as a ROS parameter (type,
description, range from the field metadata), reads back a validated immutable snapshot, and
revalidates every later change in the on-set callback: a bad value is refused with the reason
and the snapshot is unchanged.
"""

import math
from collections.abc import Callable

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.parameter import Parameter

from ros_nodes.params import ConfigError, flat_fields, from_flat

_TYPES = {bool: Parameter.Type.BOOL, int: Parameter.Type.INTEGER, float: Parameter.Type.DOUBLE,
          str: Parameter.Type.STRING, tuple: Parameter.Type.STRING_ARRAY}


def descriptor(spec) -> ParameterDescriptor:
    """A `ParameterDescriptor` for one flat field (ranges only where both ends are finite)."""
    text = spec.description
    if spec.choices:
        text += f" (one of: {', '.join(spec.choices)})"
    d = ParameterDescriptor(name=spec.name, type=_TYPES[spec.type].value, description=text)
    lo, hi = spec.min, spec.max
    if spec.type is float and lo is not None and hi is not None and math.isfinite(hi):
        d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi))]
    elif spec.type is int and lo is not None and hi is not None:
        d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
    return d


class TypedParams:
    """Declares a config class's parameters on `node` and tracks a validated snapshot."""

    def __init__(self, node, cls, on_change: Callable[[object], None] | None = None):
        self._cls = cls
        self._on_change = on_change
        self._specs = flat_fields(cls)
        for s in self._specs:
            default = list(s.default) if s.type is tuple else s.default
            node.declare_parameter(s.name, default, descriptor(s))
        values = {s.name: self._value(node.get_parameter(s.name)) for s in self._specs}
        try:
            self.config = from_flat(cls, values)
        except ConfigError as e:
            raise SystemExit(f"{node.get_name()}: invalid parameters: {e}") from None
        node.add_on_set_parameters_callback(self._on_set)

    @staticmethod
    def _value(p: Parameter):
        v = p.value
        return tuple(v) if isinstance(v, list) else v

    def _on_set(self, params: list[Parameter]) -> SetParametersResult:
        known = {s.name for s in self._specs}
        values = {p.name: self._value(p) for p in params if p.name in known}
        if not values:
            return SetParametersResult(successful=True)
        try:
            new = from_flat(self._cls, values, base=self.config)
        except ConfigError as e:
            return SetParametersResult(successful=False, reason=str(e))
        self.config = new
        if self._on_change is not None:
            self._on_change(new)
        return SetParametersResult(successful=True)

"""The range of every numeric option and field, declared beside it and checked in one loop.

A config dataclass states each number's range once, in its field (`number(default, ...)`,
kept in the field's metadata); its `validate()` calls `check_numbers`, which refuses a
wrong type, NaN, an infinity or a value out of range with a UsageError naming the option
(`--lr nan: expected a finite number > 0`). A new numeric field without a declared range is
caught by tests/test_checks.py, which walks every config's fields.
"""
from __future__ import annotations

import math
import numbers
import os
from dataclasses import MISSING, dataclass, field, fields, replace

from shared.errors import UsageError

MAX_SEED = 2**63 - 1  # numpy takes any seed >= 0, torch.manual_seed < 2**64; cuboidgen draws its own from 63 bits
WORKERS_PER_CORE = 4


def max_processes() -> int:
    """The most worker processes (or threads) either daemon starts: 4 per core. Workers are
    CPU-bound, so more than one per core only adds contention; the factor leaves room for
    workers that wait (--fsync, --max-rate, reading a slow disk). `os.cpu_count()`, as the
    defaults that start one worker per core."""
    return WORKERS_PER_CORE * (os.cpu_count() or 1)


PER_CORE = f"{WORKERS_PER_CORE} per core: {os.cpu_count() or 1} cores"  # the unit of max_processes() in errors


@dataclass(frozen=True)
class Bounds:
    """A number's range: [lo, hi], either end open or absent; `integer` refuses fractions."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    integer: bool = False
    optional: bool = False  # None is allowed (the option was not given)
    unit: str = ""  # said after the range: "px", "samples a second", why the bound

    def expected(self) -> str:
        unit = f" ({self.unit})" if self.unit else ""
        return self._range() + unit

    def _range(self) -> str:
        kind = "an integer" if self.integer else "a finite number"
        lo_op, hi_op = (">" if self.lo_open else ">="), ("<" if self.hi_open else "<=")
        if self.lo is not None and self.hi is not None:
            if not self.lo_open and not self.hi_open:
                return f"{kind} from {_num(self.lo)} to {_num(self.hi)}"
            return f"{kind} {lo_op} {_num(self.lo)} and {hi_op} {_num(self.hi)}"
        if self.lo is not None:
            return f"{kind} {lo_op} {_num(self.lo)}"
        if self.hi is not None:
            return f"{kind} {hi_op} {_num(self.hi)}"
        return kind

    def accepts(self, value) -> bool:
        if value is None:
            return self.optional
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            return False
        if self.integer and not isinstance(value, numbers.Integral):
            return False
        if not self.integer and not math.isfinite(value):
            return False
        if self.lo is not None and (value <= self.lo if self.lo_open else value < self.lo):
            return False
        if self.hi is not None and (value >= self.hi if self.hi_open else value > self.hi):
            return False
        return True

    def check(self, name: str, value):
        """`value`, if in range; else a UsageError naming `name`, the value and the range."""
        if not self.accepts(value):
            raise UsageError(f"{name} {_shown(value)}: expected {self.expected()}")
        return value


def number(default=MISSING, *, default_factory=MISSING, **bounds):
    """A dataclass field holding a number in `Bounds(**bounds)`."""
    return field(default=default, default_factory=default_factory, metadata={"bounds": Bounds(**bounds)})


def pair(default, **bounds):
    """A dataclass field holding a range (min, max): two numbers in `Bounds(**bounds)`, min <= max."""
    return field(default=default, metadata={"bounds": Bounds(**bounds), "pair": True})


def bounds_of(cls_or_obj) -> dict[str, Bounds]:
    """Each field's declared range, by field name."""
    return {f.name: f.metadata["bounds"] for f in fields(cls_or_obj) if "bounds" in f.metadata}


def is_pair(cls_or_obj, name: str) -> bool:
    return any(f.name == name and f.metadata.get("pair") for f in fields(cls_or_obj))


def check_pair(name: str, value, bounds: Bounds):
    """`value` if it is a range (min, max) of two numbers in `bounds` with min <= max (or None when
    `bounds.optional`); else a UsageError naming `name`."""
    if value is None and bounds.optional:
        return value
    one = replace(bounds, optional=False)
    if (not isinstance(value, (tuple, list)) or len(value) != 2 or not all(one.accepts(v) for v in value)
            or value[0] > value[1]):
        raise UsageError(f"{name} {_shown(value)}: expected a range (min, max) with min <= max, each {one.expected()}")
    return value


def option_name(field_name: str) -> str:
    return "--" + field_name.replace("_", "-")


def check_numbers(config, name=option_name) -> None:
    """Every declared range of `config`'s fields checked; the error names the option (`name(field)`)."""
    for key, bounds in bounds_of(config).items():
        if is_pair(config, key):
            check_pair(name(key), getattr(config, key), bounds)
        else:
            bounds.check(name(key), getattr(config, key))


def _shown(value) -> str:
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        return str(value)
    if isinstance(value, (tuple, list)) and all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in value):
        return "(" + ", ".join(str(v) for v in value) + ")"  # not [..]: the console reads [nan, 1] as markup
    return repr(value)


def _num(bound) -> str:
    return str(bound) if isinstance(bound, int) else f"{bound:g}"


def check_choice(option: str, value: str, choices) -> str:
    """`value` if it is one of `choices`, else a UsageError naming the option and the choices."""
    if not isinstance(value, str) or value not in choices:
        raise UsageError(f"{option} {value!r}: expected one of {', '.join(choices)}")
    return value

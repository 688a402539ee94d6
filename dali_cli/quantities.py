"""The kinds of number dali accepts: one table for every place a number enters, command-line
options (`dali_cli.commands.kinds` wraps each kind as a click type), sensors.toml, model.json and
manifests. A kind is a finite number within a range that means something physically (a car
dimension of 0.1-30 m, a learning rate in (0, 1], a scale factor of 0.01-100); NaN, ±inf and
values that only overflow later (1e308, 1e-300) are refused where they enter, with the option,
file or field named (docs/input-validation.md, "Parameter kinds").
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass


class QuantityError(ValueError):
    """A number that is not of its kind; the message names where it came from."""


@dataclass(frozen=True)
class Quantity:
    """A finite number in [low, high] (`low_open`: low excluded), in `unit`."""

    what: str  # what such a number is, for messages: "a scale factor"
    low: float
    high: float
    unit: str = ""
    low_open: bool = False

    def describe(self) -> str:
        """'a learning rate in (0, 1]', 'a distance in [0.1, 10000] m'."""
        unit = f" {self.unit}" if self.unit else ""
        opening = "(" if self.low_open else "["
        return f"{self.what} in {opening}{self.low:g}, {self.high:g}]{unit}"

    def problem(self, value) -> str | None:
        """Why `value` is not of this kind, None when it is."""
        if isinstance(value, bool) or not isinstance(value, int | float):
            return f"expected {self.describe()}, got {value!r}"[:200]
        try:
            number = float(value)
        except OverflowError:  # an integer beyond any float
            return f"expected {self.describe()}, got an integer of {len(str(value))} digits"
        if not math.isfinite(number):
            return f"{value!r} is not a finite number"
        below = number <= self.low if self.low_open else number < self.low
        if below or number > self.high:
            return f"expected {self.describe()}, got {value:g}"
        return None

    def check(self, value, where: str) -> float:
        """`value` as a float; QuantityError '<where>: <problem>' when it is not of this kind."""
        problem = self.problem(value)
        if problem is not None:
            raise QuantityError(f"{where}: {problem}")
        return float(value)


# sizes and distances (metres)
CAR_SIZE_M = Quantity("a car dimension (length, width or height)", 0.1, 30.0, "m")
SIZE_SPREAD_M = Quantity("a spread of car dimensions", 0.0, 10.0, "m")
SIZE_DELTA_M = Quantity("a change of a car dimension", -10.0, 10.0, "m")
DISTANCE_M = Quantity("a distance from the sensor", 0.1, 10_000.0, "m")
MARGIN_M = Quantity("a margin around a box", 0.0, 10.0, "m")
MOUNT_HEIGHT_M = Quantity("a sensor height above the ground", 0.0, 100.0, "m")
RANGE_NOISE_M = Quantity("a range noise (standard deviation)", 0.0, 1.0, "m")
# a CAD model's native length, in its file's units (metres, millimetres, inches...)
MODEL_LENGTH = Quantity("a CAD model's length in its file's units", 0.0, 1e6)
# scale factors (dimensionless): PTSN's s, ROS factors, self-training's scale
SCALE = Quantity("a scale factor", 0.01, 100.0)
# training budget and optimizer
LEARNING_RATE = Quantity("a learning rate", 0.0, 1.0, low_open=True)
EPOCHS = Quantity("a number of epochs", 0.0, 100_000.0, low_open=True)
MINUTES = Quantity("a time budget", 0.0, 525_600.0, "min", low_open=True)  # at most a year
# angles, intensities, fractions
VIEW_DEG = Quantity("a horizontal view angle", 0.0, 360.0, "deg", low_open=True)
INTENSITY_MAX = Quantity("the largest intensity of the data", 1e-3, 1e6)
INTENSITY = Quantity("an intensity", 0.0, 1.0)
FRACTION = Quantity("a fraction", 0.0, 1.0)
TOLERANCE = Quantity("a tolerance", 0.0, 10.0)


def check_triple(quantity: Quantity, values, where: str) -> tuple[float, float, float]:
    """Three numbers of `quantity` (l, w, h), as floats; QuantityError naming `where`."""
    if not isinstance(values, list | tuple) or len(values) != 3:
        raise QuantityError(f"{where}: expected 3 numbers [l, w, h], got {values!r}"[:200])
    return tuple(quantity.check(v, where) for v in values)  # type: ignore[return-value]


def is_profile_name(text: str) -> bool:
    """A sensors.toml profile name, the one name model.json carries: letters, digits, '_', '-',
    '.', '+', not starting with '.' (`../../etc/passwd` is not one), at most 100 characters."""
    return re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.+-]{0,99}", text) is not None

"""The parameter kinds of `dali_cli.quantities` as click types, for option declarations
(`type=SCALE`), and worker counts bounded by this machine's cores. A value of the wrong kind is a
usage error naming the option (exit 2), before any work."""

from __future__ import annotations

from pathlib import Path

import click

from dali_cli import quantities
from dali_cli.runtime.cores import available_cores


class QuantityType(click.ParamType):
    """A number of one `quantities.Quantity` kind."""

    name = "float"

    def __init__(self, quantity: quantities.Quantity):
        self.quantity = quantity

    def convert(self, value, param, ctx):
        number = value if isinstance(value, float) else click.FLOAT.convert(value, param, ctx)
        problem = self.quantity.problem(number)
        if problem is not None:
            self.fail(problem, param, ctx)
        return number


class FloatTuple(click.ParamType):
    """'a,b,c': `count` comma-separated numbers (None: one or more), each converted by the click
    type `each`; `increasing` asks for a strictly increasing sequence (a 'lo,hi' range)."""

    def __init__(self, count: int | None, each: click.ParamType, increasing: bool = False):
        self.count = count
        self.each = each
        self.increasing = increasing
        self.name = f"{count} numbers" if count is not None else "numbers"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        parts = str(value).split(",")
        if self.count is not None and len(parts) != self.count:
            self.fail(f"expected {self.count} comma-separated numbers, got '{value}'", param, ctx)
        numbers = []
        for part in parts:
            try:
                numbers.append(self.each.convert(part.strip(), param, ctx))
            except click.BadParameter as error:
                self.fail(f"'{value}': {error.message}", param, ctx)
        if self.increasing and any(b <= a for a, b in zip(numbers, numbers[1:], strict=False)):
            self.fail(f"'{value}': expected increasing numbers (lo < hi)", param, ctx)
        return tuple(numbers)


SCALE = QuantityType(quantities.SCALE)
CAR_SIZE = FloatTuple(3, QuantityType(quantities.CAR_SIZE_M))
"""'l,w,h' of a car in metres."""
SIZE_DELTA = FloatTuple(3, QuantityType(quantities.SIZE_DELTA_M))
"""'dl,dw,dh' in metres."""
SCALE_PAIR = FloatTuple(2, SCALE, increasing=True)
"""'lo,hi': two scale factors, lo < hi."""
SCALE_LIST = FloatTuple(None, SCALE, increasing=True)
"""'a,b,c': one or more scale factors, increasing."""
DISTANCE_M = QuantityType(quantities.DISTANCE_M)
MARGIN_M = QuantityType(quantities.MARGIN_M)
LEARNING_RATE = QuantityType(quantities.LEARNING_RATE)
EPOCHS = QuantityType(quantities.EPOCHS)
MINUTES = QuantityType(quantities.MINUTES)
VIEW_DEG = QuantityType(quantities.VIEW_DEG)
INTENSITY_MAX = QuantityType(quantities.INTENSITY_MAX)
TOLERANCE = QuantityType(quantities.TOLERANCE)


class QuantityRange(click.ParamType):
    """'LOW:HIGH': two numbers of one kind, LOW <= HIGH."""

    name = "LOW:HIGH"

    def __init__(self, quantity: quantities.Quantity):
        self.quantity = quantity

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        try:
            low, high = (float(part) for part in str(value).split(":"))
        except ValueError:
            self.fail(f"expected LOW:HIGH, got '{value}'", param, ctx)
        for number in (low, high):
            problem = self.quantity.problem(number)
            if problem is not None:
                self.fail(f"'{value}': {problem}", param, ctx)
        if low > high:
            self.fail(f"'{value}': expected LOW <= HIGH", param, ctx)
        return low, high


DISTANCE_RANGE = QuantityRange(quantities.DISTANCE_M)
"""'LOW:HIGH' distances from the sensor in metres."""


class CoreCount(click.ParamType):
    """Processes or threads of this machine: an integer from `low` to the cores this process may
    use (more would only oversubscribe it, or fork without end)."""

    name = "integer"

    def __init__(self, low: int = 1):
        self.low = low

    def convert(self, value, param, ctx):
        count = click.INT.convert(value, param, ctx)
        cores = available_cores()
        if not self.low <= count <= cores:
            self.fail(
                f"{count} is not in [{self.low}, {cores}]: this machine lets dali use {cores} "
                "cores",
                param,
                ctx,
            )
        return count


LOCAL_WORKERS = CoreCount(0)
"""Helper processes beside the main one (a training loader): 0 to the number of cores."""


def named_path(value: str, hint: str, directory: bool = False) -> tuple[str, Path]:
    """(name, path) of a `NAME=PATH` or `PATH` argument (named after the path's last part); a
    usage error naming `hint` when the name is empty or the path is missing (not a directory,
    with `directory`)."""
    name, sep, path = value.partition("=")
    if not sep:
        name, path = Path(value).name or value, value
    if not name:
        raise click.BadParameter(f"{value}: empty name", param_hint=hint)
    if not Path(path).exists():
        raise click.BadParameter(f"{path}: not found", param_hint=hint)
    if directory and not Path(path).is_dir():
        raise click.BadParameter(f"{path}: not a directory", param_hint=hint)
    return name, Path(path)

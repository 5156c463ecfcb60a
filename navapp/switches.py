"""A measured change's earlier path kept behind a switch, so that the benches run it beside
today's in one process and one sitting ("before" in ``navapp bench``; docs/benchmarks.md).

Process-wide: for benchmarks, not for code that runs beside other registrations."""

from collections.abc import Iterator
from contextlib import contextmanager


class Before:
    """Whether code takes its earlier path: false except within ``taken()``."""

    __slots__ = ("on",)

    def __init__(self) -> None:
        self.on = False

    def __bool__(self) -> bool:
        return self.on

    @contextmanager
    def taken(self) -> Iterator[None]:
        self.on = True
        try:
            yield
        finally:
            self.on = False

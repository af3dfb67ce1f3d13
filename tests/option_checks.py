"""An options class for the tests of options and of the flags made from them."""

import dataclasses
from collections.abc import Sequence

from gld import options


@dataclasses.dataclass
class Example:
    rate: float = options.option(0.5, "A rate.", above=0, at_most=1)
    count: int = options.option(3, "A count.", at_least=1)
    kind: str = options.option("a", "A kind.", ("a", "b"))
    choice: str | None = options.option(None, "The platform's unless given.", ("x", "y"))
    widths: Sequence[int] = options.option((4, 8), "Widths.", at_least=1)
    extras: Sequence[int] = options.option((), "Extras.", at_least=1, may_be_empty=True)
    switch: bool = options.option(False, "A switch.")
    name: str = ""  # no help: set by a launcher, not a flag

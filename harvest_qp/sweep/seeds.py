"""Seed lists from the command line: ``"0:100"``, ``"3"``, ``"1,2,5"``, ``"0:10:2"``."""

from __future__ import annotations

import re
from collections.abc import Sequence

from harvest_qp.exceptions import InvalidInputError

_INT = re.compile(r"[0-9]+")
_EXPECTED = (
    "a non-negative integer ('3'), a comma-separated list ('1,2,5'), "
    "or a half-open range START:STOP[:STEP] with STOP > START and STEP > 0 ('0:100', '0:10:2')"
)


def _seed_int(text: str, *, spec: str) -> int:
    text = text.strip()
    if not _INT.fullmatch(text):
        raise InvalidInputError(f"seeds: {text!r} in {spec!r} is not a non-negative integer; expected {_EXPECTED}")
    return int(text)


def parse_seeds(spec: str) -> list[int]:
    """The seeds named by ``spec``, in the order given, without duplicates.

    ``"A:B"`` is Python's half-open ``range(A, B)`` (so ``"0:100"`` is 100 seeds, 0..99),
    ``"A:B:S"`` is ``range(A, B, S)``; a comma-separated list may mix single seeds and ranges
    (``"0:5,10,20:22"``).

    Raises:
        InvalidInputError: ``spec`` is empty, has a negative or non-integer seed, an empty or
            reversed range, a zero step, or names the same seed twice (which would make a
            sweep count one scene twice).
    """
    if not isinstance(spec, str):
        raise InvalidInputError(f"seeds must be a string, got {spec!r} ({type(spec).__name__}); expected {_EXPECTED}")
    if not spec.strip():
        raise InvalidInputError(f"seeds must not be empty, got {spec!r}; expected {_EXPECTED}")
    seeds: list[int] = []
    for part in spec.split(","):
        fields = part.split(":")
        if len(fields) == 1:
            seeds.append(_seed_int(fields[0], spec=spec))
            continue
        if len(fields) > 3:
            raise InvalidInputError(f"seeds: range {part!r} in {spec!r} has {len(fields)} fields; expected {_EXPECTED}")
        start, stop = (_seed_int(f, spec=spec) for f in fields[:2])
        step = _seed_int(fields[2], spec=spec) if len(fields) == 3 else 1
        if step == 0:
            raise InvalidInputError(f"seeds: range {part!r} in {spec!r} has step 0; expected STEP > 0")
        if stop <= start:
            raise InvalidInputError(
                f"seeds: range {part!r} in {spec!r} is empty (STOP {stop} <= START {start}); "
                "ranges are half-open like Python's range, e.g. '0:100' is seeds 0..99"
            )
        seeds.extend(range(start, stop, step))
    return check_seeds(seeds)


def check_seeds(seeds: Sequence[int]) -> list[int]:
    """``seeds`` as a list of ``int`` after checking each is a non-negative integer and unique.

    Raises:
        InvalidInputError: naming the first bad or repeated seed.
    """
    checked: list[int] = []
    seen: set[int] = set()
    for seed in seeds:
        # bool is an int subclass: True as a seed is almost certainly a bug in the caller.
        if isinstance(seed, bool) or not hasattr(seed, "__index__") or int(seed.__index__()) < 0:
            raise InvalidInputError(f"seeds: every seed must be a non-negative integer, got {seed!r}")
        value = int(seed.__index__())
        if value in seen:
            raise InvalidInputError(f"seeds: seed {value} appears more than once; each seed is one episode")
        seen.add(value)
        checked.append(value)
    if not checked:
        raise InvalidInputError("seeds must name at least one seed, got an empty sequence")
    return checked

"""Building blocks of the configuration schema: value kinds with one-line expectations.

Every constrained value kind below (``Positive``, ``Fraction``, ...) is a pydantic type whose
validation failure is collapsed into ONE error ``expected`` carrying the human text of what
was expected (``"a number > 0"``), so that a config error fits on one line whatever the kind
(a union of a number and a list would otherwise report one error per branch).

Every section derives from :class:`Section`: unknown keys are rejected with the nearest valid
name (``difflib``), values are strict (``true`` is not a number, ``"1.5"`` is not a float) and
finite (no ``.inf``/``.nan``).
"""

# ruff: noqa: UP007 (unions built from tuples at run time, and Union[Annotated[...], ...] reads better here)
from __future__ import annotations

import difflib
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, ValidationError, WrapValidator, model_validator
from pydantic_core import PydanticCustomError

__all__ = [
    "Section", "expect", "Positive", "NonNegative", "Real", "Fraction", "PositiveInt", "NonNegativeInt", "Level",
    "HardLevel", "Weight", "Weights", "Weights6", "Vector3", "PositiveOrNull", "PositiveOrL", "Text", "suggest",
]


def _collapse(text: str) -> WrapValidator:
    def validate(value: Any, handler):
        try:
            return handler(value)
        except ValidationError:
            raise PydanticCustomError("expected", "expected {expected}", {"expected": text}) from None

    return WrapValidator(validate)


def expect(tp: Any, text: str, **constraints: Any) -> Any:
    """``tp`` with ``constraints`` (pydantic ``Field`` keywords) whose failure reads ``expected <text>``."""
    return Annotated[tp, Field(**constraints), _collapse(text)]


def suggest(name: str, valid: list[str]) -> str:
    """``" (did you mean 'x'?)"`` for the valid name nearest to ``name`` (empty when none is close)."""
    close = difflib.get_close_matches(str(name), valid, n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


_NonNegFloat = Annotated[float, Field(ge=0)]

Positive = expect(float, "a number > 0", gt=0)
NonNegative = expect(float, "a number >= 0", ge=0)
Real = expect(float, "a finite number")
Fraction = expect(float, "a number in [0, 1)", ge=0, lt=1)
PositiveInt = expect(int, "an integer >= 1", ge=1)
NonNegativeInt = expect(int, "an integer >= 0", ge=0)
Level = expect(int, "an integer >= 1 (1 is the highest soft priority)", ge=1)
HardLevel = expect(int, "an integer >= 0 (0: hard constraint, 1: the highest soft priority)", ge=0)
Weight = expect(float, "a number >= 0", ge=0)
Weights6 = expect(
    Union[_NonNegFloat, Annotated[list[_NonNegFloat], Field(min_length=6, max_length=6)]],
    "a number >= 0 or a list of 6 numbers >= 0",
)
Weights6OrNull = expect(
    Union[_NonNegFloat, Annotated[list[_NonNegFloat], Field(min_length=6, max_length=6)], None],
    "a number >= 0, a list of 6 numbers >= 0 or null",
)
Weights = expect(
    Union[_NonNegFloat, Annotated[list[_NonNegFloat], Field(min_length=1)]],
    "a number >= 0 or a list of numbers >= 0 (one per task row)",
)
Vector3 = expect(Annotated[list[float], Field(min_length=3, max_length=3)], "a list of 3 numbers")
PositiveOrNull = expect(Union[Annotated[float, Field(gt=0)], None], "a number > 0 or null")
#: An angle off a direction [deg] in (0, 90): 90 or more would admit its opposite side.
AcuteAngle = expect(float, "an angle in (0, 90) [deg]", gt=0, lt=90)
AcuteAngleOrNull = expect(Union[Annotated[float, Field(gt=0, lt=90)], None], "an angle in (0, 90) [deg] or null")
PositiveOrL = expect(
    Union[Annotated[float, Field(gt=0)], Literal["l"]], "a number > 0 or 'l' (the estimated stem length)"
)
Text = expect(str, "a string")


class Section(BaseModel):
    """A mapping of the configuration: strict, finite values; unknown keys rejected with a suggestion."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, validate_default=False)

    @model_validator(mode="before")
    @classmethod
    def _known_keys_only(cls, data: Any) -> Any:
        if not isinstance(data, (dict, BaseModel)):
            keys = [name for name in cls.model_fields if name != "type"]
            raise PydanticCustomError("expected", "expected {expected}",
                                      {"expected": "a mapping of: " + ", ".join(keys)})
        if isinstance(data, dict):
            valid = [name for name, info in cls.model_fields.items() if not info.exclude]
            for key in data:
                if key not in cls.model_fields:
                    raise PydanticCustomError(
                        "unknown_key",
                        "unknown key '{key}'{hint}; expected one of: {valid}",
                        {"key": str(key), "hint": suggest(str(key), valid), "valid": ", ".join(valid)},
                    )
        return data

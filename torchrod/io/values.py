"""Input values as the readings' messages name them, and the stand-in for an integer too long to convert.

Messages
    Every message about a reading names the field (``curvature[3][0]``, ``t``, ``id``) and quotes at most
    ``QUOTE_CHARS`` characters of the offending value (:func:`quote`, with its full length when cut), so a 10 MB
    value gives a short message; quoting never recurses, so deeply nested values are quoted safely too.

Long integers
    A JSON integer literal of more than :func:`int_digit_limit` digits is decoded as a :class:`HugeInteger`, which
    every check refuses with a message naming the field (converting it would cost time quadratic in its length).
"""

from __future__ import annotations

import math
import numbers
import sys
from collections.abc import Iterator
from typing import Any

import torch

__all__ = ["MAX_INT_DIGITS", "QUOTE_CHARS", "HugeInteger", "describe", "int_digit_limit", "kind", "quote"]

QUOTE_CHARS = 100
"""Characters of an offending value quoted in a message, at most (its length is added when it is cut)."""


class HugeInteger:
    """A JSON integer literal of more than :func:`int_digit_limit` digits (4300, Python's default limit). The JSON
    decoder of :mod:`torchrod.io.jsonl` yields it in place of the integer, so such a line fails with a message naming
    the field instead of aborting the run. Keeps only the head of the digits."""

    __slots__ = ("digits", "head", "negative")

    def __init__(self, text: str) -> None:
        self.negative = text.startswith("-")
        body = text.lstrip("+-")
        self.digits = len(body)
        self.head = body[:20]

    def __repr__(self) -> str:
        return f"{'-' if self.negative else ''}{self.head}... ({self.digits} digits)"


MAX_INT_DIGITS = 4300
"""The most digits of an integer read from JSON (Python's default int <-> str limit): converting longer ones costs
time quadratic in their length, and Python refuses to write them back."""


def int_digit_limit() -> int:
    """The most digits of an integer read or written: Python's int <-> str limit when it is set lower than
    :data:`MAX_INT_DIGITS`, else that."""
    get = getattr(sys, "get_int_max_str_digits", None)
    limit = int(get()) if get is not None else 0
    return min(limit, MAX_INT_DIGITS) if limit > 0 else MAX_INT_DIGITS


_END = object()


class _Piece(str):
    """Literal text in :func:`quote`'s work list (a plain ``str`` there is a value to render)."""


def _int_text(x: int) -> str:
    limit = int_digit_limit()
    approx = int(x.bit_length() * 0.30103) + 1
    if limit and approx > limit:
        return f"an integer of about {approx} digits"
    text = str(x)
    digits = len(text.lstrip("-"))
    return text if digits <= 24 else f"{text[:21]}... ({digits} digits)"


def _scalar_text(value: Any, limit: int) -> str | None:
    """JSON-like text of a scalar; None for a container."""
    if value is None:
        return "null"
    if value is True or value is False:
        return "true" if value else "false"
    if isinstance(value, HugeInteger):
        return repr(value)
    if isinstance(value, int):
        return _int_text(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "NaN"
        if math.isinf(value):
            return "Infinity" if value > 0 else "-Infinity"
        return repr(value)
    if isinstance(value, str):
        import json

        if len(value) > limit:
            cut = max(8, limit - 40)
            return json.dumps(value[:cut], ensure_ascii=False)[:-1] + f'..." ({len(value)} characters)'
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, (list, tuple, dict)):
        return None
    if isinstance(value, torch.Tensor):
        return f"a tensor of shape {tuple(value.shape)} and dtype {value.dtype}"
    if hasattr(value, "shape") and hasattr(value, "dtype"):
        return f"an array of shape {tuple(value.shape)} and dtype {value.dtype}"
    if isinstance(value, numbers.Number):
        return _scalar_text(float(value), limit) if isinstance(value, numbers.Real) else type(value).__name__
    return f"a {type(value).__name__}"


def _pieces(container: Any) -> Iterator[Any]:
    if isinstance(container, dict):
        yield _Piece("{")
        for k, (key, v) in enumerate(container.items()):
            if k:
                yield _Piece(", ")
            yield key if isinstance(key, str) else _Piece(repr(key))
            yield _Piece(": ")
            yield v
        yield _Piece("}")
    else:
        yield _Piece("[")
        for k, v in enumerate(container):
            if k:
                yield _Piece(", ")
            yield v
        yield _Piece("]")


def quote(value: Any, limit: int = QUOTE_CHARS) -> str:
    """``value`` as JSON-like text of at most about ``limit`` characters (cut with ``...``).

    Never raises and never recurses: nested arrays and objects are walked with an explicit stack that stops once
    ``limit`` characters are out, so a value nested 100 000 levels deep or 10 MB long costs ``limit`` steps.
    """
    out: list[str] = []
    size = 0
    stack: list[Iterator[Any]] = [iter((value,))]
    try:
        while stack and size <= limit:
            item = next(stack[-1], _END)
            if item is _END:
                stack.pop()
                continue
            if isinstance(item, _Piece):
                text = str(item)
            else:
                scalar = _scalar_text(item, limit)
                if scalar is None:
                    stack.append(_pieces(item))
                    continue
                text = scalar
            out.append(text)
            size += len(text)
    except Exception:  # noqa: BLE001 - a message must come out whatever the value holds
        out.append(" ?")
    text = "".join(out)
    # A lone scalar formats itself within about the limit (keeping its length note); only more is cut here.
    return text if len(text) <= limit + 40 and not stack else text[:limit] + "..."


def describe(value: Any) -> str:
    """``value``'s JSON kind and its quote, as ``a string "abc"``, for messages."""
    if value is None:
        return "null"
    if value is True or value is False:
        return f"a boolean {quote(value)}"
    if isinstance(value, str):
        return f"a string {quote(value)}"
    if isinstance(value, (list, tuple)):
        return f"an array {quote(value)}"
    if isinstance(value, dict):
        return f"an object {quote(value)}"
    if isinstance(value, (int, float, HugeInteger)):
        return f"a number {quote(value)}"
    return quote(value)


def kind(value: Any) -> str:
    """``value``'s JSON kind for messages (``"a string"``, ``"null"``; ``"a set"`` for a value JSON has no kind for)."""
    if value is None:
        return "null"
    if value is True or value is False:
        return "a boolean"
    if isinstance(value, (int, float, HugeInteger)):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, (list, tuple)):
        return "an array"
    if isinstance(value, dict):
        return "an object"
    return f"a {type(value).__name__}"

"""What `mrrig runs` filters with: `--since` (a span back from now, or a date) and `--where`, a
small expression language over the catalog's numeric columns that becomes a bound SQLAlchemy
expression, never SQL text:

    where   := or
    or      := and ("or" and)*
    and     := not ("and" not)*
    not     := "not" not | "(" or ")" | COLUMN OP NUMBER | NUMBER OP COLUMN
    OP      := < | <= | > | >= | == | = | !=
    COLUMN  := one of NUMERIC_COLUMNS (et, faults_count, latency_p99_us, ...)

A run without the number (Et of a constant target) matches no comparison of it. Parentheses
and `not` nest at most MAX_DEPTH deep.
"""

from __future__ import annotations

import math
import operator
import re
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from typing import Any

import sqlalchemy as sa

from mrrig.catalog.record import NUMERIC_COLUMNS
from mrrig.catalog.schema import runs
from mrrig.errors import MrrigError


class QueryError(MrrigError, ValueError):
    """A filter that the catalog does not understand; the message names the place."""


_OPS: dict[str, Callable[[Any, Any], Any]] = {
    "<": operator.lt,
    "<=": operator.le,
    ">": operator.gt,
    ">=": operator.ge,
    "==": operator.eq,
    "=": operator.eq,
    "!=": operator.ne,
}
# a comparison read right to left: 0.01 > et is et < 0.01
_MIRROR = {"<": ">", "<=": ">=", ">": "<", ">=": "<=", "==": "==", "=": "=", "!=": "!="}
_TOKEN = re.compile(
    r"\s*(?:(?P<number>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)"
    r"|(?P<op><=|>=|==|!=|<|>|=)|(?P<paren>[()])|(?P<word>[A-Za-z_][A-Za-z0-9_]*))"
)
_KEYWORDS = {"and", "or", "not"}
# how deep parentheses and `not` may nest (the parser recurses once per level)
MAX_DEPTH = 32


def parse_where(text: str) -> sa.ColumnElement[bool]:
    """The expression `text` (`"et < 0.01 and faults_count == 0"`) as a bound SQLAlchemy
    condition on the runs table; QueryError naming the position of anything else."""
    tokens = _tokenize(text)
    if not tokens:
        raise QueryError("--where: empty expression")
    parser = _Parser(text, tokens)
    clause = parser.parse_or()
    if parser.pos < len(tokens):
        kind, value, at = tokens[parser.pos]
        raise QueryError(f"--where: unexpected {value!r} at character {at + 1} of {text!r}")
    return clause


def _tokenize(text: str) -> list[tuple[str, str, int]]:
    tokens, pos = [], 0
    while pos < len(text):
        if text[pos:].strip() == "":
            break
        m = _TOKEN.match(text, pos)
        if m is None or m.end() == pos:
            at = len(text[pos:]) - len(text[pos:].lstrip()) + pos
            raise QueryError(
                f"--where: {text[at]!r} at character {at + 1} of {text!r} is not part of the"
                " language (columns, numbers, < <= > >= == != , and, or, not, parentheses)"
            )
        kind = m.lastgroup or ""
        tokens.append((kind, m.group(kind), m.start(kind)))
        pos = m.end()
    return tokens


class _Parser:
    def __init__(self, text: str, tokens: list[tuple[str, str, int]]) -> None:
        self.text, self.tokens, self.pos, self.depth = text, tokens, 0, 0

    def _peek(self) -> tuple[str, str, int] | None:
        return self.tokens[self.pos] if self.pos < len(self.tokens) else None

    def _take(self) -> tuple[str, str, int]:
        token = self._peek()
        if token is None:
            raise QueryError(f"--where: {self.text!r} ends too early")
        self.pos += 1
        return token

    def _is_word(self, word: str, pos: int | None = None) -> bool:
        pos = self.pos if pos is None else pos
        token = self.tokens[pos] if pos < len(self.tokens) else None
        return token is not None and token[0] == "word" and token[1].lower() == word

    def parse_or(self) -> sa.ColumnElement[bool]:
        terms = [self.parse_and()]
        while self._is_word("or"):
            self.pos += 1
            terms.append(self.parse_and())
        return terms[0] if len(terms) == 1 else sa.or_(*terms)

    def parse_and(self) -> sa.ColumnElement[bool]:
        terms = [self.parse_not()]
        while self._is_word("and"):
            self.pos += 1
            terms.append(self.parse_not())
        return terms[0] if len(terms) == 1 else sa.and_(*terms)

    def parse_not(self) -> sa.ColumnElement[bool]:
        kind, value, at = self._take()
        nested = kind == "paren" and value == "(" or self._is_word("not", self.pos - 1)
        if not nested:
            self.pos -= 1
            return self._comparison()
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise QueryError(
                f"--where: nested deeper than {MAX_DEPTH} levels (parentheses and not) at"
                f" character {at + 1}"
            )
        if kind == "paren":
            inner = self.parse_or()
            kind, value, at = self._take()
            if value != ")":
                raise QueryError(f"--where: expected ')' at character {at + 1} of {self.text!r}")
        else:
            inner = sa.not_(self.parse_not())
        self.depth -= 1
        return inner

    def _comparison(self) -> sa.ColumnElement[bool]:
        left, op, right = self._take(), self._take(), self._take()
        if op[0] != "op":
            raise QueryError(
                f"--where: expected a comparison (< <= > >= == !=) at character {op[2] + 1}"
                f" of {self.text!r}, got {op[1]!r}"
            )
        symbol = op[1]
        if left[0] == "number" and right[0] == "word":
            left, right, symbol = right, left, _MIRROR[symbol]
        column, number = self._column(left), self._number(right)
        return _OPS[symbol](runs.c[column], sa.literal(number, sa.Float()))

    def _column(self, token: tuple[str, str, int]) -> str:
        kind, value, at = token
        if kind != "word" or value.lower() in _KEYWORDS:
            raise QueryError(
                f"--where: expected a column at character {at + 1} of {self.text!r}, got {value!r}"
            )
        if value not in NUMERIC_COLUMNS:
            raise QueryError(
                f"--where: unknown column {value!r} at character {at + 1}; known: "
                + ", ".join(NUMERIC_COLUMNS)
            )
        return value

    def _number(self, token: tuple[str, str, int]) -> float:
        kind, value, at = token
        if kind != "number":
            raise QueryError(
                f"--where: expected a number at character {at + 1} of {self.text!r}, got {value!r}"
            )
        number = float(value)
        if not math.isfinite(number):
            raise QueryError(f"--where: {value} at character {at + 1} is not a finite number")
        return number


_SPAN = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([smhdw])\s*$")
_SPAN_S = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0, "w": 7 * 86400.0}


def parse_since(text: str, now: datetime | None = None) -> datetime:
    """The UTC time that `--since` means: a span back from `now` (`90s`, `30m`, `12h`, `7d`,
    `2w`) or an ISO 8601 date or time (`2026-12-01`, `2026-12-01T08:00`, UTC unless it says
    its zone). QueryError for anything else."""
    now = now or datetime.now(UTC)
    m = _SPAN.match(text)
    if m:
        try:
            return now - timedelta(seconds=float(m.group(1)) * _SPAN_S[m.group(2)])
        except OverflowError:  # beyond timedelta's 999999999 days, or before the year 1
            raise QueryError(
                f"--since: {text!r} reaches back before the year 1; give a shorter span"
            ) from None
    try:
        when = datetime.fromisoformat(text.strip())
    except ValueError:
        raise QueryError(
            f"--since: {text!r} is neither a span (90s, 30m, 12h, 7d, 2w) nor an ISO date"
            " (2026-12-01, 2026-12-01T08:00)"
        ) from None
    return when.replace(tzinfo=UTC) if when.tzinfo is None else when.astimezone(UTC)

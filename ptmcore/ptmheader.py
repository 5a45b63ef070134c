"""The text header of a ``.ptm`` file, read strictly.

A PTM header is lines of text (version, format) and white-space separated numbers (size,
scales, biases, and the JPEG formats' plane tables) before a binary payload. The reader here
refuses anything malformed with an :class:`~ptmcore.errors.InputError` that names the field, and
never reads past the line that ends the header (:meth:`HeaderCursor.end_header`).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

from .errors import InputError

__all__ = ["HeaderCursor"]

_HEADER_TOKEN_MAX = 40  # longer "numbers" in a header are garbage, not data
_INT_RE = re.compile(rb"[+-]?[0-9]+")
_FLOAT_RE = re.compile(rb"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_WHITESPACE = b" \t\r\n"


class HeaderCursor:
    """Reads the text header of a PTM held in memory, refusing anything malformed."""

    def __init__(self, data: bytes, path: Path) -> None:
        self.data = data
        self.pos = 0
        self.path = path

    def fail(self, problem: str) -> InputError:
        return InputError(problem, self.path)

    def line(self, what: str) -> str:
        end = self.data.find(b"\n", self.pos, self.pos + 256)
        if end < 0:
            raise self.fail(f"not a PTM file: no {what} line")
        raw = self.data[self.pos : end].strip(_WHITESPACE)
        self.pos = end + 1
        try:
            return raw.decode("ascii")
        except UnicodeDecodeError:
            raise self.fail(f"not a PTM file: the {what} line is not text") from None

    def token(self, what: str) -> bytes:
        data, n = self.data, len(self.data)
        i = self.pos
        while i < n and data[i] in _WHITESPACE:
            i += 1
        j = i
        while j < n and data[j] not in _WHITESPACE and j - i <= _HEADER_TOKEN_MAX:
            j += 1
        if i == j:
            raise self.fail(f"header ends before the {what}")
        if j - i > _HEADER_TOKEN_MAX:
            raise self.fail(f"the {what} field holds a value too long to be a number")
        self.pos = j
        return data[i:j]

    def _numbers(self, count: int, what: str, pattern: re.Pattern, convert: Callable, kind: str) -> list:
        values = []
        for k in range(count):
            tok = self.token(what)
            if not pattern.fullmatch(tok):
                shown = tok.decode("ascii", "backslashreplace")
                raise self.fail(f"the {what} must be {kind}; value {k + 1} is {shown!r}")
            values.append(convert(tok))
        return values

    def ints(self, count: int, what: str) -> list[int]:
        return self._numbers(count, what, _INT_RE, int, "integers")

    def floats(self, count: int, what: str) -> list[float]:
        return self._numbers(count, what, _FLOAT_RE, float, "numbers")

    def end_header(self) -> int:
        """Consume the rest of the last header line; the payload starts right after it.

        Only the rest of *that* line may be skipped: the payload is binary and may begin with
        bytes that look like white space.
        """
        end = self.data.find(b"\n", self.pos, self.pos + 256)
        if end < 0 or self.data[self.pos : end].strip(b" \t\r"):
            raise self.fail("the header's last line has unexpected content or no line end")
        self.pos = end + 1
        return self.pos


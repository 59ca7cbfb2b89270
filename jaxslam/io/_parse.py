"""Shared helpers of the text readers: load a file's data lines, check field counts and parse
columns with numpy, raising :class:`InputFormatError` with the file and line on any problem.

A *data line* is a line that is not blank once a ``#`` comment (to the end of the line) is
cut off. Readers group data lines (by tag, or all together), then parse each group's numeric
columns in one numpy call; only when that call fails does a Python loop look for the
offending field, so the error can name it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NoReturn

import numpy as np

from ..errors import InputFormatError

QUATERNION_NORM_TOLERANCE = 1e-2
"""Quaternions read from files whose norm is within this of 1 are normalised; others are
rejected (a norm far from 1 means the columns are in the wrong order or the data is broken)."""

_UNIT_ULPS = 4 * np.finfo(np.float64).eps
"""A norm this close to 1 is unit to float64 rounding: such rows are kept bit for bit, so a
full-precision write followed by a read reproduces the same numbers."""


@dataclasses.dataclass(frozen=True)
class DataLines:
    """The data lines of one text file: whitespace-split tokens and 1-based line numbers."""

    path: str
    tokens: list[list[str]]
    lines: np.ndarray  # (N,) int64

    def __len__(self) -> int:
        return len(self.tokens)

    def select(self, index: Sequence[int] | np.ndarray) -> DataLines:
        idx = np.asarray(index, dtype=np.int64)
        return DataLines(self.path, [self.tokens[k] for k in idx.tolist()], self.lines[idx])


def read_data_lines(path: str | Path) -> DataLines:
    """Read ``path`` as UTF-8 text and return its data lines.

    Raises InputFormatError for a missing file, a directory, a binary file (a NUL byte) or
    text that is not UTF-8, and for a file without any data line.
    """
    text = _read_text(Path(path))
    tokens: list[list[str]] = []
    lines: list[int] = []
    for number, raw in enumerate(text.split("\n"), start=1):
        fields = (raw.split("#", 1)[0] if "#" in raw else raw).split()
        if fields:
            tokens.append(fields)
            lines.append(number)
    if not tokens:
        raise InputFormatError("file is empty (no data lines, only blanks or # comments)", path)
    return DataLines(str(path), tokens, np.asarray(lines, dtype=np.int64))


def _read_text(path: Path) -> str:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputFormatError("file not found", path) from None
    except IsADirectoryError:
        raise InputFormatError("is a directory, expected a text file", path) from None
    except OSError as exc:
        raise InputFormatError(f"cannot read file: {exc.strerror or exc}", path) from None
    nul = data.find(b"\x00")
    if nul >= 0:
        raise InputFormatError(f"not a text file (NUL byte at offset {nul})", path, data.count(b"\n", 0, nul) + 1)
    try:
        return data.decode("utf-8-sig")  # a leading byte-order mark is dropped
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise InputFormatError(f"not UTF-8 text (bad byte at offset {exc.start})", path, line) from None


def check_field_count(rows: DataLines, what: str, expected: int, skip: int = 0) -> None:
    """Every row must hold ``skip + expected`` tokens (``skip`` leading tokens, e.g. a tag,
    are not counted as fields in the message)."""
    counts = np.fromiter((len(t) for t in rows.tokens), dtype=np.int64, count=len(rows))
    bad = np.flatnonzero(counts != expected + skip)
    if bad.size:
        k = int(bad[0])
        raise InputFormatError(
            f"{what} needs {expected} fields, found {int(counts[k]) - skip}", rows.path, int(rows.lines[k])
        )


def parse_floats(rows: DataLines, what: str, names: Sequence[str], start: int = 0) -> np.ndarray:
    """Columns ``start : start + len(names)`` of every row as finite float64, ``(N, len(names))``.

    Field counts must have been checked. A token that is not a number, NaN or infinity raises
    InputFormatError naming the line and the field.
    """
    block = [t[start : start + len(names)] for t in rows.tokens]
    try:
        values = np.array(block, dtype=np.float64).reshape(len(rows), len(names))
    except ValueError:
        _raise_first_unparsable(rows, what, names, block, float)
    finite = np.isfinite(values)
    if not finite.all():
        r, c = (int(v) for v in np.argwhere(~finite)[0])
        raise InputFormatError(
            f"{what} field {names[c]} is {block[r][c]!r}; NaN and infinity are not allowed",
            rows.path,
            int(rows.lines[r]),
        )
    return values


def parse_ids(rows: DataLines, what: str, names: Sequence[str], start: int = 0) -> np.ndarray:
    """Columns ``start : start + len(names)`` as non-negative int64 ids, ``(N, len(names))``."""
    block = [t[start : start + len(names)] for t in rows.tokens]
    try:
        ids = np.array(block, dtype=np.int64).reshape(len(rows), len(names))
    except (ValueError, OverflowError):
        _raise_first_unparsable(rows, what, names, block, _int64)
    negative = ids < 0
    if negative.any():
        r, c = (int(v) for v in np.argwhere(negative)[0])
        raise InputFormatError(
            f"{what} field {names[c]} is {block[r][c]!r}, expected a non-negative integer id",
            rows.path,
            int(rows.lines[r]),
        )
    return ids


def _int64(token: str) -> int:
    value = int(token)
    if not -(2**63) <= value < 2**63:
        raise OverflowError(token)
    return value


def _raise_first_unparsable(
    rows: DataLines, what: str, names: Sequence[str], block: list[list[str]], conv: Callable[[str], object]
) -> NoReturn:
    kind = "a number" if conv is float else "an integer id"
    for r, fields in enumerate(block):
        for c, token in enumerate(fields):
            try:
                conv(token)
            except (ValueError, OverflowError):
                raise InputFormatError(
                    f"{what} field {names[c]} is {token[:40]!r}, expected {kind}", rows.path, int(rows.lines[r])
                ) from None
    raise InputFormatError(f"{what}: a field could not be parsed", rows.path)  # not reached


def normalize_quaternions(q: np.ndarray, rows: DataLines, what: str) -> np.ndarray:
    """Rows of ``q`` (any component order) divided by their norm.

    Rows already unit to float64 rounding are returned unchanged (so write -> read round trips
    bit for bit); a norm off by more than :data:`QUATERNION_NORM_TOLERANCE` raises
    InputFormatError naming the line.
    """
    with np.errstate(all="ignore"):
        norm = np.linalg.norm(q, axis=-1)
    bad = np.flatnonzero(~(np.abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE))
    if bad.size:
        k = int(bad[0])
        raise InputFormatError(
            f"{what} quaternion has norm {norm[k]:.6g}; expected a unit quaternion "
            f"(within {QUATERNION_NORM_TOLERANCE:g})",
            rows.path,
            int(rows.lines[k]),
        )
    keep = np.abs(norm - 1.0) <= _UNIT_ULPS
    return np.where(keep[:, None], q, q / norm[:, None])


def format_rows(prefix: str, ids: np.ndarray, values: np.ndarray) -> list[str]:
    """One line per row: ``prefix``, the integer ``ids`` ``(N, k)``, then ``values`` ``(N, m)``
    each as the shortest decimal that reads back to the same float64 (Python's ``repr``)."""
    if len(values) == 0:
        return []
    head = [prefix] if prefix else []
    id_rows = np.asarray(ids, dtype=np.int64).reshape(len(values), -1).tolist()
    value_rows = np.asarray(values, dtype=np.float64).tolist()
    return [" ".join([*head, *map(str, i), *map(repr, v)]) for i, v in zip(id_rows, value_rows)]


def require_finite(what: str, array: np.ndarray) -> None:
    """Writers refuse NaN / infinity (the readers would reject the file): ValueError naming
    the first bad row."""
    rows = np.asarray(array, dtype=np.float64)
    if rows.size == 0:
        return
    bad = np.flatnonzero(~np.all(np.isfinite(rows.reshape(rows.shape[0], -1)), axis=1))
    if bad.size:
        raise ValueError(f"{what}: row {int(bad[0])} is not finite; refusing to write a file that cannot be read back")

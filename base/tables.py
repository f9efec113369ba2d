"""CSV tables read as text, with numeric access whose errors name the file, the column and the line."""
from __future__ import annotations

import csv
import os
from collections.abc import Sequence

import numpy as np

from base.errors import InputError, require_file


class CsvTable:
    """A CSV file (UTF-8, with or without a byte-order mark) read as text; numeric access with precise errors.

    The first row is the header, unless ``columns`` names the columns of a
    header-less file (every row is then data).  ``skip_row(cells) -> bool``
    drops data rows before validation (e.g. a tracker's "lost" rows); their
    line numbers are kept in ``skipped_lines``.  Errors name the file, the
    column and the line of the file.
    """

    def __init__(self, path: str | os.PathLike, skip_row=None, columns: Sequence[str] | None = None):
        self.path = require_file(path)
        try:
            with open(self.path, newline="", encoding="utf-8-sig") as f:
                numbered = [(n + 1, row) for n, row in enumerate(csv.reader(f)) if row and any(c.strip() for c in row)]
        except UnicodeDecodeError as e:
            raise InputError(f"{self.path}: not a text CSV (byte {e.start} is not UTF-8 text); expected a "
                             f"comma-separated table") from None
        except csv.Error as e:
            raise InputError(f"{self.path}: not a readable CSV ({e})") from None
        if columns is None:
            if not numbered:
                raise InputError(f"{self.path}: empty file, expected a header row and data rows")
            self.header = [h.strip() for h in numbered[0][1]]
            body = numbered[1:]
            where = "below the header"
            width = "the header has"
        else:
            self.header = list(columns)
            body = numbered
            where = "(a header-less table)"
            width = "expected"
        self.skipped_lines = [n for n, row in body if skip_row is not None and skip_row(row)]
        body = [(n, row) for n, row in body if skip_row is None or not skip_row(row)]
        if not body:
            raise InputError(f"{self.path}: no data rows {where}")
        self.lines = [n for n, _ in body]
        self.rows = [row for _, row in body]
        for n, row in body:
            if len(row) != len(self.header):
                raise InputError(f"{self.path}: line {n} has {len(row)} cells, {width} {len(self.header)}")
        self._index = {name: i for i, name in enumerate(self.header)}

    def __len__(self) -> int:
        return len(self.rows)

    def keep_rows(self, keep: np.ndarray) -> None:
        """Keep only the data rows where ``keep`` [rows] is True (their line numbers go with them)."""
        self.rows = [row for row, k in zip(self.rows, keep) if k]
        self.lines = [line for line, k in zip(self.lines, keep) if k]

    def has(self, name: str) -> bool:
        return name in self._index

    def text(self, name: str) -> list[str]:
        if name not in self._index:
            raise InputError(f"{self.path}: no column '{name}' (columns: {', '.join(self.header)})")
        j = self._index[name]
        return [row[j].strip() for row in self.rows]

    def numeric(self, name: str) -> np.ndarray:
        """Column ``name`` as float64; a non-number names its row."""
        values = self.text(name)
        out = np.empty(len(values))
        for i, v in enumerate(values):
            try:
                out[i] = float(v)
            except ValueError:
                raise InputError(
                    f"{self.path}: column '{name}', line {self.lines[i]}: expected a number, found '{v}'"
                ) from None
            if not np.isfinite(out[i]):
                raise InputError(f"{self.path}: column '{name}', line {self.lines[i]}: value is {v}, expected finite")
        return out

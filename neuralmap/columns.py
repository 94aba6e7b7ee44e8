"""Column files in: a CSV with one header line, or an NPZ of 1-D arrays, read into named
columns.

The one reader of the toolkit's logs (flight logs of the Navigator, the learning code's
flight logs). What it refuses, with the file, the column and the row:

* a CSV that is not UTF-8 (a byte-order mark is fine), an empty one, a header that names a
  column twice (which of the two would be meant?), a row with more or fewer fields than
  the header;
* an NPZ that is not a zip archive, a column of Python objects, a column that is not 1-D;
* a non-number in a numeric column (``text_columns`` may hold text).

Memory: a CSV is streamed row by row into one ``array('d')`` per numeric column (8 bytes a
value), so a log of a million rows and ten columns reads in about 80 MB; a text column
holds one string object per distinct value (flight ids repeat) and a pointer per row.
"""

from __future__ import annotations

import csv
import zipfile
from array import array
from pathlib import Path

import numpy as np

from neuralmap.exceptions import NeuralMapError

__all__ = ["read_columns"]


def _read_npz(path: Path, what: str, text: tuple[str, ...]) -> dict[str, np.ndarray]:
    if not zipfile.is_zipfile(path):
        raise NeuralMapError(
            f"{path}: not a readable .npz {what} (not a zip archive); write it with "
            "numpy.savez.")
    try:
        with np.load(path, allow_pickle=False) as data:
            columns = {k: np.asarray(data[k]) for k in data.files}
    except ValueError as exc:
        if "allow_pickle" in str(exc):
            raise NeuralMapError(
                f"{path}: a column holds Python objects (an object array); a {what} holds "
                "plain numbers. Save each column as a float array, e.g. "
                "np.savez(path, time=t.astype(float), ...).") from None
        raise NeuralMapError(f"{path}: not a readable .npz {what} ({exc}).") from None
    except Exception as exc:  # noqa: BLE001 - BadZipFile, EOFError, OSError: not an archive
        raise NeuralMapError(
            f"{path}: not a readable .npz {what} ({type(exc).__name__}: {exc}).") from None
    for name, values in columns.items():
        if values.ndim != 1:
            raise NeuralMapError(
                f"{path}: column {name!r} has shape {values.shape}; every column of a {what} "
                "is 1-D (one value per row): save one array per column.")
        if name not in text and not (np.issubdtype(values.dtype, np.number)
                                     or values.dtype == np.bool_):
            raise NeuralMapError(
                f"{path}: column {name!r} holds {values.dtype} values, not numbers.")
    return columns


def _read_csv(path: Path, what: str, text: tuple[str, ...]) -> dict[str, np.ndarray]:
    try:
        with path.open(newline="", encoding="utf-8-sig") as handle:
            reader = csv.reader(handle)
            header = next(reader, None)
            if header is None:
                raise NeuralMapError(f"{path}: empty {what} (no header line).")
            names = [n.strip() for n in header]
            seen: dict[str, int] = {}
            for col, name in enumerate(names, start=1):
                if name in seen:
                    raise NeuralMapError(
                        f"{path}, line 1: column {name!r} appears twice (columns {seen[name]} "
                        f"and {col}); rename or remove one, so that it is clear which one "
                        "is meant.")
                seen[name] = col
            numeric = {i: array("d") for i, n in enumerate(names) if n not in text}
            words: dict[int, list[str]] = {i: [] for i, n in enumerate(names) if n in text}
            seen_words: dict[str, str] = {}  # one object per distinct text (flight ids repeat)
            for line, row in enumerate(reader, start=2):
                if not row or (len(row) == 1 and not row[0].strip()):
                    continue  # a blank line
                if len(row) != len(names):
                    raise NeuralMapError(
                        f"{path}, line {line}: {len(row)} fields, the header has "
                        f"{len(names)}; every row holds one value per column.")
                for i, store in numeric.items():
                    value = row[i].strip()
                    try:
                        store.append(float(value) if value else np.nan)
                    except ValueError:
                        raise NeuralMapError(
                            f"{path}, line {line}, column {names[i]!r}: {value!r} is not a "
                            "number.") from None
                for i, store in words.items():
                    word = row[i].strip()
                    store.append(seen_words.setdefault(word, word))
    except UnicodeDecodeError as exc:
        raise NeuralMapError(
            f"{path}: not UTF-8 text (byte {exc.start} cannot be decoded: "
            f"{exc.object[exc.start:exc.start + 1]!r}); save the {what} as UTF-8 CSV."
        ) from None
    columns: dict[str, np.ndarray] = {names[i]: np.frombuffer(store, dtype=np.float64)
                                      for i, store in numeric.items()}
    columns.update({names[i]: np.asarray(store) for i, store in words.items()})
    return columns


def read_columns(path: str | Path, *, what: str = "log",
                 text_columns: tuple[str, ...] = ("flight",)) -> dict[str, np.ndarray]:
    """The columns of a CSV or NPZ file (module docstring).

    Args:
        path: A ``.csv`` or ``.npz`` file.
        what: What the file is, for messages ("flight log").
        text_columns: Columns that may hold text (ids); the others must be numbers (an
            empty CSV field is NaN).

    Returns:
        Column name → 1-D array (float64 for CSV numbers; the stored dtype for NPZ).

    Raises:
        NeuralMapError: The refusals of the module docstring, naming file, line, column.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return _read_npz(path, what, tuple(text_columns))
    if suffix == ".csv":
        return _read_csv(path, what, tuple(text_columns))
    raise NeuralMapError(f"{path}: a {what} must be a .csv or .npz file.")

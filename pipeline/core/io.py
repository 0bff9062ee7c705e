"""Atomic file output and the CSV tables of the clip-folder contract (:mod:`pipeline.core.clip`)."""

from __future__ import annotations

import contextlib
import csv
import itertools
import json
import os
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.errors import StereotrackError, first_line
from pipeline.core.interrupts import raise_if_interrupted


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; move it into place only if the block succeeds.

    The temporary name keeps the suffix (OpenCV and matplotlib pick the format from it), so an
    interrupted write leaves at worst a hidden ``.*.partial*`` file, never a half-written target.
    """
    tmp_path: Path | None = None
    try:  # made inside: an interrupt as the temporary file is made leaves it behind no more
        tmp_path = partial_beside(Path(path))
        yield tmp_path
        raise_if_interrupted()  # nothing is committed once a signal came
        os.replace(tmp_path, path)
    except OSError as exc:  # a full disk, a read-only one: named by the file it was writing
        if tmp_path is not None:
            tmp_path.unlink(missing_ok=True)
        if exc.filename is None or exc.filename == str(tmp_path):
            raise StereotrackError(f"cannot write ({exc.strerror or exc})", path) from None
        raise
    except BaseException:
        if tmp_path is not None:
            tmp_path.unlink(missing_ok=True)
        raise


def ensure_dir(path: str | Path) -> Path:
    """Create folder ``path`` (and parents), or fail with one line naming it: a read-only parent,
    a path under a file, a file in the way, /proc."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise StereotrackError("cannot create folder: a file of that name is in the way", path) from None
    except OSError as exc:
        raise StereotrackError(f"cannot create folder ({exc.strerror or exc})", path) from None
    if not path.is_dir():
        raise StereotrackError("cannot create folder: a file of that name is in the way", path)
    return path


def check_replaceable(folder: str | Path, ours: tuple[str, ...], what: str = "output") -> None:
    """Refuse to replace ``folder`` unless stereotrack made it: it is absent, empty, or holds one of
    the files only stereotrack writes there (``ours``: ``clip.json`` for a rendered clip,
    ``manifest.json`` for a batch's clip output). Otherwise one error naming the folder, so that no
    command, ``--force`` included, ever deletes a user's files."""
    folder = Path(folder)
    if not folder.exists():
        return
    if not folder.is_dir():
        raise StereotrackError(f"cannot write the {what} here: a file of that name is in the way", folder)
    if any(True for _ in folder.iterdir()) and not any((folder / n).exists() for n in ours):
        raise StereotrackError(f"folder exists, is not empty and was not written by stereotrack (no {' or '.join(ours)}); "
                               f"choose an empty or new folder for the {what}", folder)


def partial_beside(path: Path) -> Path:
    """A new empty temporary file beside ``path`` (a hidden ``.*.partial*`` name) with the
    permissions an ordinary new file gets (0666 less the umask, not mkstemp's 0600): whatever is
    renamed into place from it is readable like every other output."""
    fd, tmp = _mkstemp_beside(path)
    try:  # interrupted before it is handed over: removed here, as nobody else knows its name
        os.close(fd)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return Path(tmp)


def _mkstemp_beside(path: Path) -> tuple[int, str]:
    ensure_dir(path.parent)
    if path.is_dir():
        raise StereotrackError("cannot write file: a folder of that name is in the way", path)
    try:
        return tempfile.mkstemp(prefix=f".{path.stem}.partial-", suffix=path.suffix, dir=path.parent)
    except OSError as exc:
        raise StereotrackError(f"cannot write here ({exc.strerror or exc})", path) from None


def write_text(path: str | Path, text: str) -> None:
    """Write text atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write bytes atomically (the folder is made when missing)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_json(path: str | Path, data: Any) -> None:
    """Write JSON atomically (NaN written as null so every JSON reader accepts it)."""
    write_text(path, json.dumps(_jsonable(data), indent=2, allow_nan=False) + "\n")


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if np.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


@dataclass(frozen=True)
class Schema:
    """A CSV table of the file contract: its file, what one row is, who writes it, and each
    column's meaning in order (the docs' file-format tables are generated from these)."""

    file: str
    row: str
    written_by: str
    columns: dict[str, str]
    #: a table whose columns come first (``columns`` are added after them)
    extends: Schema | None = None

    @property
    def names(self) -> list[str]:
        """The header, in order."""
        return [*(self.extends.names if self.extends else []), *self.columns]


def write_csv(path: str | Path, header: Sequence[str], rows: Iterable[Sequence[Any]]) -> None:
    """Write a CSV table atomically; floats with 10 significant digits, NaN as ``nan``."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        for row in rows:
            writer.writerow([_fmt(v) for v in row])


def write_csv_columns(path: str | Path, header: Sequence[str], columns: Sequence[np.ndarray | Sequence[Any]]) -> None:
    """:func:`write_csv` of a table given column by column (float or integer arrays, or lists of
    names), the same bytes: each column is formatted at once instead of value by value."""
    cells = [_cells(c) for c in columns]
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        writer.writerows(zip(*cells, strict=True))


def _cells(c: np.ndarray | Sequence[Any]) -> list[Any]:
    """A column's cells as :func:`_fmt` makes them."""
    if isinstance(c, np.ndarray) and c.dtype.kind == "f":
        return [f"{v:.10g}" for v in c.tolist()]
    if isinstance(c, np.ndarray) and c.dtype.kind in "iub":
        return c.astype(int).tolist()
    return [_fmt(v) for v in c]


def _fmt(v: Any) -> Any:
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.10g}"
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (bool, np.bool_)):
        return int(v)
    return v


#: Columns that are names, never numbers (a marker called ``0`` stays ``"0"``).
TEXT_COLUMNS = frozenset({"marker", "group", "camera", "clip", "status", "method", "error"})


def read_csv(path: str | Path, required: Sequence[str] = (), numeric: Sequence[str] = (),
             finite: Sequence[str] = ()) -> dict[str, np.ndarray]:
    """Read a CSV table into columns; missing columns are an error.

    Text columns (:data:`TEXT_COLUMNS`) stay strings. Columns in ``numeric`` must hold numbers
    and those in ``finite`` finite numbers: a violation is one error naming the file, the row
    (as a text editor numbers it, the header being line 1) and the value. Other columns are
    numeric where every value parses, text otherwise. Rows are parsed in blocks of
    :data:`CSV_BLOCK`, so a long table never exists as one Python string per cell.
    """
    path = Path(path)
    if not path.is_file():
        raise StereotrackError("file not found", path)
    text = set(TEXT_COLUMNS)
    while True:  # once more with a column found to be text, which then keeps its strings from the first row
        parts = _read_blocks(path, required, set(numeric) | set(finite), set(finite), text)
        mixed = [name for name, p in parts.items() if any(a.dtype == object for a in p) and name not in text]
        if not mixed:
            return {name: np.concatenate(p) if p else np.zeros(0, dtype=object if name in text else float)
                    for name, p in parts.items()}
        text.update(mixed)


#: rows parsed at a time by :func:`read_csv`
CSV_BLOCK = 1024


def _read_blocks(path: Path, required: Sequence[str], must: set[str], finite: set[str],
                 text: set[str]) -> dict[str, list[np.ndarray]]:
    """Each column of ``path`` as arrays of up to :data:`CSV_BLOCK` rows (see :func:`read_csv`)."""
    try:
        with open(path, newline="") as fh:
            reader = csv.reader(fh)
            try:
                header = [h.strip() for h in next(reader)]
            except StopIteration:
                raise StereotrackError("empty file (no header row)", path) from None
            missing = [c for c in required if c not in header]
            if missing:
                raise StereotrackError(f"missing column(s) {', '.join(missing)}", path)
            parts: dict[str, list[np.ndarray]] = {name: [] for name in header}
            block: list[list[str]] = []
            lines: list[int] = []  # each row's line in the file (blank lines and quoted line breaks counted)
            for row in itertools.chain(reader, [None]):
                if row:
                    block.append(row)
                    lines.append(reader.line_num)
                if block and (row is None or len(block) == CSV_BLOCK):
                    for name, values in zip(header, _transposed(block, len(header)), strict=False):
                        values = list(map(str.strip, values))
                        parts[name].append(_column(values, name, lines, name in text, must, finite, path))
                    block, lines = [], []
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise StereotrackError(f"cannot read CSV ({getattr(exc, 'strerror', None) or exc})", path) from None
    return parts


def _column(values: list[str], name: str, lines: list[int], text: bool, must: set[str], finite: set[str],
            path: Path) -> np.ndarray:
    """One block of one column: numbers, or strings (``text``, or a value that is not a number in a
    column not bound to be numeric); ``lines``: each value's line in the file, for errors."""
    if text:
        return np.array(values, dtype=object)
    try:
        col = np.array(list(map(float, values)), dtype=float)  # the usual block: every cell a number
    except ValueError:  # an empty cell (NaN here), or one that is not a number
        try:
            col = np.array([float(v) if v != "" else np.nan for v in values], dtype=float)
        except ValueError:
            if name in must:
                row = next(j for j, v in enumerate(values) if not _is_number(v))
                raise StereotrackError(f"line {lines[row]}: column '{name}' is not a number ({values[row]!r})",
                                       path) from None
            return np.array(values, dtype=object)
    if name in finite and not np.all(np.isfinite(col)):
        row = int(np.flatnonzero(~np.isfinite(col))[0])
        raise StereotrackError(f"line {lines[row]}: column '{name}' is {values[row] or 'empty'!s}, not a finite "
                               "number", path)
    return col


def _transposed(block: list[list[str]], width: int) -> Iterable[Sequence[str]]:
    """A block of rows as its first ``width`` columns, a short row's missing cells empty: transposed
    by ``zip`` when no row is short (the usual), cell by cell otherwise."""
    if min(map(len, block)) >= width:
        return zip(*block, strict=False)
    return ([r[i] if i < len(r) else "" for r in block] for i in range(width))


def _is_number(v: str) -> bool:
    if v == "":
        return True
    try:
        float(v)
    except ValueError:
        return False
    return True


def check_frame_column(frames: np.ndarray, n_frames: int | None, path: str | Path) -> None:
    """Every ``frame`` value a whole number in ``0 .. n_frames − 1``; else an error naming the CSV line."""
    bad = (frames != np.round(frames)) | (frames < 0) | (frames >= (n_frames if n_frames is not None else np.inf))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        where = f"outside the clip's frames 0..{n_frames - 1}" if n_frames is not None else "not a frame index"
        raise StereotrackError(f"line {i + 2}: frame {frames[i]:g} is {where}", path)


def read_json_mapping(path: str | Path, what: str = "JSON file") -> dict:
    """A JSON file whose top level is an object; otherwise a one-line error naming the file."""
    path = Path(path)
    try:
        data = json.loads(path.read_bytes())
    except OSError as exc:
        raise StereotrackError(f"cannot read the {what} ({exc.strerror})", path) from None
    except ValueError as exc:
        raise StereotrackError(f"unreadable {what} (not JSON: {first_line(exc)})", path) from None
    if not isinstance(data, dict):
        raise StereotrackError(f"unreadable {what} (expected a JSON object, found {type(data).__name__})", path)
    return data


def safe_yaml_loader() -> type:
    """PyYAML's safe loader on libyaml's parser where PyYAML has it (the same values, ten times
    faster: `stereotrack scenarios` reads every scenario file), else its pure-Python one."""
    import yaml

    return getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def read_yaml_mapping(path: str | Path, error: type[StereotrackError] = StereotrackError) -> dict:
    """A YAML file whose top level is a mapping (empty file: ``{}``); otherwise a one-line
    ``error`` naming the file and the problem."""
    import yaml

    path = Path(path)
    try:
        data = yaml.load(path.read_text(encoding="utf-8"), Loader=safe_yaml_loader())
    except yaml.YAMLError as exc:
        raise error(f"not valid YAML ({first_line(exc)})", path) from None
    except UnicodeDecodeError:
        raise error("not a text file (not UTF-8): expected YAML", path) from None
    except OSError as exc:
        raise error(f"cannot read ({exc.strerror})", path) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise error(f"expected a mapping at the top level, found {type(data).__name__}", path)
    return data

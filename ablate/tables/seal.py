"""The seal of a table's records: what each records file beside a table (``runs/<table>.csv`` and the curves,
trials, frames and detections kept with it) held when it was written, so that one that arrives broken is caught
before a table is rendered from it.

The seal is ``runs/<table>.seal.json``: per file its lines and the SHA-256 of its text, and for a plain CSV its
header and a short digest of each line (8 hex digits of the line's SHA-256), from which a change is named by its
line. It is written by the one function that writes a records file (:func:`write_csv`). :func:`check` compares each
file with its seal and raises one :class:`BrokenRecords` naming the file, the line and what is wrong: cut short (a
bad merge), a line repeated, lines reordered, a column lost, a value edited by hand, a file missing or unsealed.

Reordered lines are broken records, caught rather than sorted away: rendering reads the runs in the order written,
and the order moves the last digits of a sum (chinet_table3's records reversed give a std of 0.24598252350637356
where the published CSV holds 0.2459825235063736), so a reorder a bad merge leaves would be a silently different
table; the seal names the first line out of place. A compressed file (the counts per test frame, thousands of
lines) keeps no digest per line: a change there is named by the file and its line count.

An intended edit is sealed again with ``python -m ablate.report --seal experiment=<table>``, after each file is
checked to parse (:func:`reseal`): a header with the columns its kind needs, every line as many fields as the
header, no key repeated, numbers where numbers belong.
"""

from __future__ import annotations

import csv
import gzip
import hashlib
import io
import json
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

#: A table's seal beside its records: ``<table>.seal.json``.
SEAL = ".seal.json"
#: How a broken file is sealed again once the edit is meant.
RESEAL = "python -m ablate.report --seal experiment={table}"
#: What the seal says of itself, in its first key.
ABOUT = (
    "What each records file of the table held when it was written (lines, SHA-256, per line of a plain CSV a digest); "
    "python -m ablate.report refuses a file that differs. After an intended edit: " + RESEAL
)


class BrokenRecords(ValueError):
    """A records file that is not what was written or does not parse: its path, the line (1 is the header; None
    where no line can be named) and what is wrong, in one line."""

    def __init__(self, path: Path, line: int | None, what: str) -> None:
        self.path, self.line, self.what = path, line, what
        super().__init__(f"{path}: {'' if line is None else f'line {line}: '}{what}")


@dataclass(frozen=True)
class Kind:
    """A kind of records file: its ``suffix`` after the table's name, the columns it needs, the columns that name
    one line (``key``, no two lines alike), and, where its numbers are checked line by line, its ``text`` columns
    (every other is a number or empty) and ``whole`` ones (whole numbers)."""

    suffix: str
    required: tuple[str, ...]
    key: tuple[str, ...] = ()
    text: tuple[str, ...] | None = None
    whole: tuple[str, ...] = ()


def seal_path(runs_dir: str | Path, table: str) -> Path:
    """The seal of ``table``'s records in ``runs_dir``."""
    return Path(runs_dir) / f"{table}{SEAL}"


def table_of(path: Path) -> str:
    """The table a records file belongs to: its name up to the first dot (``chinet_table2.curves.csv``)."""
    return path.name.split(".", 1)[0]


def write_csv(frame: pd.DataFrame, path: Path) -> Path:
    """Write ``frame`` as a records file at ``path`` (no index, ``\\n`` line ends; gzipped where the name ends in
    ``.gz``, the same bytes for the same rows) and seal it in its table's seal; the one function that writes
    records."""
    path.parent.mkdir(parents=True, exist_ok=True)
    compression = {"method": "gzip", "mtime": 0} if _compressed(path) else None
    frame.to_csv(path, index=False, lineterminator="\n", compression=compression)
    _write_seal(path.parent, table_of(path), {path.name: entry(path)}, keep=True)
    return path


def entry(path: Path) -> dict[str, object]:
    """What the seal keeps of one file: its lines and SHA-256, and for a plain CSV its header and line digests."""
    text = _text(path)
    lines = _lines(text)
    kept: dict[str, object] = {"lines": len(lines), "sha256": hashlib.sha256(text.encode()).hexdigest()}
    if not _compressed(path):
        kept |= {"header": lines[0] if lines else "", "digests": " ".join(_digest(line) for line in lines[1:])}
    return kept


def check(runs_dir: str | Path, table: str, suffixes: Iterable[str]) -> None:
    """Raise :class:`BrokenRecords` for the first of ``table``'s records files (one per suffix, where present)
    that differs from its seal, a seal missing or unreadable, or a sealed file missing."""
    runs_dir = Path(runs_dir)
    present = [runs_dir / f"{table}{s}" for s in suffixes if (runs_dir / f"{table}{s}").exists()]
    if not present:
        return
    files = _read_seal(runs_dir, table)
    for path in present:
        if path.name not in files:
            raise BrokenRecords(path, None, f"not in its seal ({seal_path(runs_dir, table).name}); {_hint(table)}")
        _compare(path, files[path.name], table)
    if lost := sorted(set(files) - {p.name for p in present}):
        raise BrokenRecords(runs_dir / lost[0], None, f"missing: its seal lists it (lost in a merge?); {_hint(table)}")


def reseal(runs_dir: str | Path, table: str, kinds: Sequence[Kind]) -> Path | None:
    """Check that each of ``table``'s records files parses (:func:`check_parses`), then seal them all again, the
    seal holding those files only; None where the table has no records files."""
    runs_dir = Path(runs_dir)
    present = [(runs_dir / f"{table}{k.suffix}", k) for k in kinds if (runs_dir / f"{table}{k.suffix}").exists()]
    if not present:
        return None
    for path, kind in present:
        check_parses(path, kind)
    return _write_seal(runs_dir, table, {path.name: entry(path) for path, _ in present}, keep=False)


def check_parses(path: Path, kind: Kind) -> None:
    """Raise :class:`BrokenRecords` for the first line of ``path`` that does not parse as ``kind``."""
    text = _text(path)
    if text and not text.endswith("\n"):
        raise BrokenRecords(path, len(_lines(text)), "cut short: the file ends inside this line")
    reader = csv.reader(io.StringIO(text))
    header = next(reader, None)
    if header is None:
        raise BrokenRecords(path, 1, "empty: no header")
    if lacking := [c for c in kind.required if c not in header]:
        raise BrokenRecords(path, 1, f"the header lacks column(s) {', '.join(lacking)}")
    if repeated := sorted({c for c in header if header.count(c) > 1}):
        raise BrokenRecords(path, 1, f"the header repeats column(s) {', '.join(repeated)}")
    key = [header.index(c) for c in kind.key if c in header]
    seen: dict[tuple[str, ...], int] = {}
    for fields in reader:
        line = reader.line_num
        if len(fields) != len(header):
            raise BrokenRecords(path, line, f"{len(fields)} fields where the header has {len(header)}")
        if key:
            named = tuple(fields[i] for i in key)
            if named in seen:
                shown = ", ".join(f"{header[i]}={fields[i]}" for i in key)
                raise BrokenRecords(path, line, f"repeats line {seen[named]} ({shown}): a duplicated row")
            seen[named] = line
        if "table" in header and fields[header.index("table")] != table_of(path):
            raise BrokenRecords(path, line, f"table={fields[header.index('table')]}, not {table_of(path)}")
        if kind.text is not None:
            _check_numbers(path, line, header, fields, kind)


def _check_numbers(path: Path, line: int, header: list[str], fields: list[str], kind: Kind) -> None:
    """Every field of a column not in ``kind.text`` a number or empty, of ``kind.whole`` a whole number."""
    assert kind.text is not None
    for column, value in zip(header, fields):
        if column in kind.text or value == "":
            continue
        try:
            float(value) if column not in kind.whole else int(value)
        except ValueError:
            want = "a whole number" if column in kind.whole else "a number"
            raise BrokenRecords(path, line, f"{column}={value!r} is not {want}") from None


def _compare(path: Path, sealed: dict, table: str) -> None:
    """Raise :class:`BrokenRecords` where ``path`` is not what its seal ``sealed`` says it was."""
    text = _text(path)
    if hashlib.sha256(text.encode()).hexdigest() == sealed.get("sha256"):
        return
    lines = _lines(text)
    if "digests" not in sealed:  # compressed: no line to name
        what = f"differs from its seal ({len(lines)} lines, {sealed.get('lines')} sealed): changed since it was written"
        raise BrokenRecords(path, None, f"{what}; {_hint(table)}")
    line, what = difference(lines, str(sealed.get("header", "")), str(sealed.get("digests", "")).split(), text)
    raise BrokenRecords(path, line, f"{what}; {_hint(table)}")


def difference(lines: list[str], header: str, sealed: list[str], text: str) -> tuple[int, str]:
    """The first line where a plain CSV's ``lines`` (its ``text``) differ from the sealed ``header`` and line
    digests ``sealed``, and what is wrong there."""
    if not lines:
        return 1, f"empty: the seal has a header and {len(sealed)} line(s)"
    if lines[0] != header:
        return 1, _header_change(header, lines[0])
    got = [_digest(line) for line in lines[1:]]
    if got == sealed:  # every line as sealed: the bytes between them differ
        return len(lines), "cut short: the file ends without its last line end" if not text.endswith("\n") else (
            "differs from its seal where no line shows it (line ends?)"
        )
    first = next((i for i, (g, s) in enumerate(zip(got, sealed)) if g != s), min(len(got), len(sealed)))
    at = first + 2  # the file's line: 1 is the header
    if first < len(got) and sorted(got) == sorted(sealed):
        return at, f"reordered: this line was line {sealed.index(got[first]) + 2} when sealed"
    if first == len(got):  # a sealed line and those after it are gone
        return at, f"cut short: the file ends before this line ({len(got) + 1} lines, {len(sealed) + 1} sealed)"
    if first == len(got) - 1 and not text.endswith("\n"):
        return at, "cut short: the file ends inside this line"
    if got[first] in got[:first]:
        return at, f"repeats line {got.index(got[first]) + 2}: a duplicated row"
    if first == len(sealed):
        return at, f"a line the seal does not have ({len(got) - len(sealed)} line(s) after the sealed {at - 1})"
    if got[first] in sealed[first + 1 :]:
        until = sealed.index(got[first], first + 1) + 1
        return at, f"line(s) {at}-{until} of the sealed file are missing here"
    return at, "differs from the line sealed: edited since it was written"


def _header_change(sealed: str, now: str) -> str:
    """What changed in a header: columns lost, columns added, or their order."""
    was, is_ = next(csv.reader([sealed])), next(csv.reader([now]))
    lost, added = [c for c in was if c not in is_], [c for c in is_ if c not in was]
    parts = ([f"lacks column(s) {', '.join(lost)}"] if lost else []) + (
        [f"has column(s) the seal does not: {', '.join(added)}"] if added else []
    )
    return "the header " + ("; ".join(parts) if parts else "has its columns in another order than sealed")


def _hint(table: str) -> str:
    return f"if the change is intended: {RESEAL.format(table=table)}"


def _read_seal(runs_dir: Path, table: str) -> dict[str, dict]:
    """The sealed files of ``table``: name -> what was sealed."""
    path = seal_path(runs_dir, table)
    if not path.exists():
        raise BrokenRecords(path, None, f"missing: {table}'s records are not sealed; {_hint(table)}")
    try:
        files = json.loads(path.read_text()).get("files")
    except (json.JSONDecodeError, UnicodeDecodeError, AttributeError) as err:
        raise BrokenRecords(path, None, f"not a seal ({type(err).__name__}); {_hint(table)}") from None
    if not isinstance(files, dict) or not all(isinstance(v, dict) for v in files.values()):
        raise BrokenRecords(path, None, f"not a seal (no files); {_hint(table)}")
    return files


def _write_seal(runs_dir: Path, table: str, entries: dict[str, dict], keep: bool) -> Path:
    """Write ``table``'s seal with ``entries``; ``keep``: beside the entries of the files it already seals."""
    path = seal_path(runs_dir, table)
    files: dict[str, dict] = {}
    if keep and path.exists():
        try:
            files = _read_seal(runs_dir, table)
        except BrokenRecords:
            files = {}  # an unreadable seal is replaced: the files it sealed fail the check until sealed again
    path.write_text(json.dumps({"about": ABOUT, "files": files | entries}, indent=1, sort_keys=True) + "\n")
    return path


def _compressed(path: Path) -> bool:
    return path.suffix == ".gz"


def _text(path: Path) -> str:
    """A records file's text (a gzipped one decompressed), its line ends ``\\n`` (a checkout that turned them into
    ``\\r\\n`` reads as written); a file that is no text is one :class:`BrokenRecords`."""
    try:
        if _compressed(path):
            with gzip.open(path, "rt", encoding="utf-8", newline="") as f:
                return f.read().replace("\r\n", "\n")
        with open(path, encoding="utf-8", newline="") as f:
            return f.read().replace("\r\n", "\n")
    except (EOFError, gzip.BadGzipFile, zlib.error):
        raise BrokenRecords(path, None, "not a whole gzip file: cut short or damaged") from None
    except UnicodeDecodeError as err:
        raise BrokenRecords(path, None, f"not UTF-8 text (byte {err.start})") from None


def _lines(text: str) -> list[str]:
    """The lines of ``text``, without their ``\\n`` (a last line without one is kept)."""
    lines = text.split("\n")
    return lines[:-1] if lines and lines[-1] == "" else lines


def _digest(line: str) -> str:
    return hashlib.sha256(line.encode()).hexdigest()[:8]

"""Records that arrive broken (ablate.tables.seal): a table's committed records cut short, reordered, with a line
repeated, a column lost or a value edited by hand are one error naming the file, the line and what is wrong, never
a silently different table; the report renders the other tables and ends with status 1; ``--seal`` seals an
intended edit again once the file parses. Reordered lines are caught, not sorted away: the writer's order is what
was published."""

from __future__ import annotations

import csv
import gzip
import io
import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from ablate.tables import published
from ablate.tables.records import check_records, read_records, reseal_records, write_records
from ablate.tables.seal import BrokenRecords, seal_path
from tests.scaleout import REPO

#: A committed table with records of every plain kind and counts per frame (gzipped): 10 runs, 11 lines.
TABLE = "chinet_table3"


@pytest.fixture
def results(tmp_path: Path) -> Path:
    """A results folder holding the committed records of :data:`TABLE` (and their seal) alone."""
    out = tmp_path / "results"
    (out / "runs").mkdir(parents=True)
    for path in (REPO / "results" / "runs").glob(f"{TABLE}.*"):
        shutil.copy(path, out / "runs" / path.name)
    return out


def edit(results: Path, change: Callable[[list[str]], list[str]], name: str = f"{TABLE}.csv") -> None:
    """Rewrite a records file's lines (each with its line end) by ``change``, as a hand or a merge would."""
    path = results / "runs" / name
    path.write_text("".join(change(path.read_text().splitlines(keepends=True))))


def broken(results: Path, name: str = f"{TABLE}.csv") -> BrokenRecords:
    """The one error the check raises, which must name ``name``."""
    with pytest.raises(BrokenRecords) as caught:
        check_records(results, TABLE)
    assert caught.value.path == results / "runs" / name, caught.value
    assert str(caught.value).startswith(f"{results / 'runs' / name}: ")
    return caught.value


def test_every_committed_table_is_sealed_as_its_writer_seals_it(results: Path) -> None:
    for name in published.experiments():
        if (REPO / "results" / "runs" / f"{name}.csv").exists():
            check_records(REPO / "results", name)
    seal = seal_path(results / "runs", TABLE)
    committed = seal.read_bytes()
    runs = read_records(results / "runs" / f"{TABLE}.csv")
    seal.unlink()
    write_records(runs, TABLE, results)  # the writer seals what it writes: the same bytes, the same entry
    assert (results / "runs" / f"{TABLE}.csv").read_bytes() == (REPO / "results" / "runs" / f"{TABLE}.csv").read_bytes()
    entry = json.loads(committed)["files"][f"{TABLE}.csv"]
    assert json.loads(seal.read_text())["files"] == {f"{TABLE}.csv": entry}
    assert reseal_records(results, TABLE) == seal and seal.read_bytes() == committed  # every file, sealed again


def test_a_file_cut_inside_a_line_names_that_line(results: Path) -> None:
    path = results / "runs" / f"{TABLE}.csv"
    path.write_bytes(path.read_bytes()[:-40])
    err = broken(results)
    assert err.line == 11 and "cut short: the file ends inside this line" in err.what
    assert f"python -m ablate.report --seal experiment={TABLE}" in err.what  # the way out, where the edit is meant


def test_a_file_cut_between_lines_names_the_first_line_lost(results: Path) -> None:
    edit(results, lambda lines: lines[:-3])
    err = broken(results)
    assert err.line == 9 and "cut short: the file ends before this line (8 lines, 11 sealed)" in err.what


def test_reordered_lines_are_caught_not_sorted_away(results: Path) -> None:
    edit(results, lambda lines: [*lines[:2], lines[4], lines[3], lines[2], *lines[5:]])
    err = broken(results)
    assert err.line == 3 and "reordered: this line was line 5 when sealed" in err.what


def test_a_duplicated_row_names_the_line_it_repeats(results: Path) -> None:
    edit(results, lambda lines: [*lines[:6], lines[3], *lines[6:]])
    err = broken(results)
    assert err.line == 7 and "repeats line 4: a duplicated row" in err.what


def test_lines_lost_in_the_middle_are_named(results: Path) -> None:
    edit(results, lambda lines: [*lines[:4], *lines[6:]])
    err = broken(results)
    assert err.line == 5 and "line(s) 5-6 of the sealed file are missing here" in err.what


def test_a_missing_column_is_named_on_the_header(results: Path) -> None:
    def drop(lines: list[str]) -> list[str]:
        rows = list(csv.reader(io.StringIO("".join(lines))))
        at = rows[0].index("made_cpu")
        out = io.StringIO()
        csv.writer(out, lineterminator="\n").writerows([r[:at] + r[at + 1 :] for r in rows])
        return out.getvalue().splitlines(keepends=True)

    edit(results, drop)
    err = broken(results)
    assert err.line == 1 and "the header lacks column(s) made_cpu" in err.what


def test_a_value_edited_by_hand_names_its_line(results: Path) -> None:
    def bump(lines: list[str]) -> list[str]:
        line = lines[5]
        at = max(i for i, c in enumerate(line) if c.isdigit())
        lines[5] = line[:at] + str((int(line[at]) + 1) % 10) + line[at + 1 :]
        return lines

    edit(results, bump)
    err = broken(results)
    assert err.line == 6 and "differs from the line sealed: edited since it was written" in err.what


def test_the_files_beside_the_records_are_sealed_too(results: Path) -> None:
    edit(results, lambda lines: [*lines, lines[-1]], f"{TABLE}.curves.csv")
    err = broken(results, f"{TABLE}.curves.csv")
    assert err.line == 42 and "repeats line 41" in err.what


def test_a_cut_or_changed_gzip_file_is_named(results: Path) -> None:
    path = results / "runs" / f"{TABLE}.frames.csv.gz"
    whole = path.read_bytes()
    path.write_bytes(whole[: len(whole) // 2])
    assert "not a whole gzip file" in broken(results, path.name).what
    text = gzip.decompress(whole).decode()
    path.write_bytes(gzip.compress(text[: text.rindex("\n", 0, -1) + 1].encode()))  # a line fewer, recompressed
    assert "differs from its seal (3000 lines, 3001 sealed)" in broken(results, path.name).what


def test_a_missing_seal_a_missing_file_and_an_unsealed_file_are_each_named(results: Path) -> None:
    runs = results / "runs"
    shutil.copy(runs / f"{TABLE}.frames.csv.gz", runs / f"{TABLE}.detections.csv.gz")
    assert "not in its seal" in broken(results, f"{TABLE}.detections.csv.gz").what
    (runs / f"{TABLE}.detections.csv.gz").unlink()
    (runs / f"{TABLE}.trials.csv").unlink()
    assert "missing: its seal lists it" in broken(results, f"{TABLE}.trials.csv").what
    seal_path(runs, TABLE).write_text('{"files": {"')  # a seal cut short
    with pytest.raises(BrokenRecords, match="not a seal") as caught:
        check_records(results, TABLE)
    assert caught.value.path == seal_path(runs, TABLE)
    seal_path(runs, TABLE).unlink()
    with pytest.raises(BrokenRecords, match=f"{TABLE}'s records are not sealed") as caught:
        check_records(results, TABLE)
    assert caught.value.path == seal_path(runs, TABLE)


def test_records_lost_beside_their_curves_are_broken_not_absent(results: Path) -> None:
    from ablate.config import compose
    from ablate.tables import render_records

    (results / "runs" / f"{TABLE}.csv").unlink()  # a merge that dropped the runs and kept what lies beside them
    with pytest.raises(BrokenRecords, match="missing: its seal lists it") as caught:
        render_records(compose([f"experiment={TABLE}"]), results)
    assert caught.value.path == results / "runs" / f"{TABLE}.csv" and not list(results.glob("*.md"))


def test_a_checkout_with_windows_line_ends_reads_as_written(results: Path) -> None:
    path = results / "runs" / f"{TABLE}.csv"
    path.write_bytes(path.read_bytes().replace(b"\n", b"\r\n"))
    check_records(results, TABLE)


def test_the_report_names_the_broken_file_renders_the_others_and_ends_with_status_1(
    results: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from ablate.report import main

    edit(results, lambda lines: [*lines[:6], lines[3], *lines[6:]])
    other = "chinet_table4"  # sound records, written (and sealed) by the writer; no targets: no fingerprint rebuilt
    write_records(read_records(REPO / "results" / "runs" / f"{other}.csv").drop(columns="targets"), other, results)
    monkeypatch.chdir(results.parent)
    assert main([f"experiment={TABLE}", f"experiment={other}"]) == 1
    out, err = capsys.readouterr()
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert errors == [
        f"error: results/runs/{TABLE}.csv: line 7: repeats line 4: a duplicated row; if the change is intended: "
        f"python -m ablate.report --seal experiment={TABLE}",
        f"error: 1 table(s) not rendered, their records broken (above): {TABLE}",
    ]
    assert f"results/{other}.md" in out.splitlines() and (results / f"{other}.md").is_file()
    assert not list(results.glob(f"{TABLE}*"))  # nothing of the broken table was written


def test_seal_accepts_an_intended_edit_once_the_file_parses(
    results: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from ablate.report import main

    edit(results, lambda lines: [*lines[:5], lines[5].replace(",FINISHED,cpu,", ",FINISHED,smoke,"), *lines[6:]])
    broken(results)
    monkeypatch.chdir(results.parent)
    assert main(["--seal", f"experiment={TABLE}"]) == 0
    assert capsys.readouterr().out.splitlines() == [f"results/runs/{TABLE}.seal.json"]
    check_records(results, TABLE)


@pytest.mark.parametrize(
    ("change", "line", "what"),
    [
        (lambda lines: [*lines, lines[3]], 12, "repeats line 4 (run_id="),
        (lambda lines: [*lines[:2], lines[2].replace(",FINISHED,", ",FINISHED,x,"), *lines[3:]], 3, "fields where"),
        (lambda lines: [*lines[:2], lines[2].replace("chinet_table3,", "chinet_table9,", 1), *lines[3:]], 3, "table="),
        (lambda lines: [*lines[:2], lines[2][: lines[2].rindex(",") + 1] + "abc\n", *lines[3:]], 3, "is not a number"),
    ],
    ids=["duplicated run", "a field too many", "another table's run", "a word for a number"],
)
def test_seal_refuses_records_that_do_not_parse_and_leaves_the_seal_as_it_was(
    change: Callable[[list[str]], list[str]],
    line: int,
    what: str,
    results: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from ablate.report import main

    sealed = seal_path(results / "runs", TABLE).read_bytes()
    edit(results, change)
    monkeypatch.chdir(results.parent)
    assert main(["--seal", f"experiment={TABLE}"]) == 1
    errors = [e for e in capsys.readouterr().err.splitlines() if e.startswith("error:")]
    assert errors[0].startswith(f"error: results/runs/{TABLE}.csv: line {line}: ") and what in errors[0], errors
    assert errors[1:] == [f"error: 1 table(s) not sealed: {TABLE}"]
    assert seal_path(results / "runs", TABLE).read_bytes() == sealed

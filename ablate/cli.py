"""How the commands read their arguments, one parser each: ``python -m ablate.report``, ``ablate.latency``,
``ablate.diagnose`` and ``ablate.check_paper`` take Hydra's overrides of ``conf/config.yaml`` (``key=value``) as
positional arguments, beside a command's own few options. ``--help`` prints the usage and exits 0. A bad option (an
unknown ``--flag``, an override that is no ``key=value``, a key the command needs and lacks, a value a command's own
key cannot take) is one line on stderr, ``error: ...``, and exit status 2 (:data:`USAGE`), before anything is
composed or imported: a command parses its arguments before it imports torch.

Both the thin command module (``ablate/latency.py``) and the function that does the work
(:func:`ablate.analysis.latency.main`) parse with the same function here, so that ``main(argv)`` called from Python
reads its arguments exactly as the command does."""

from __future__ import annotations

import argparse
import re
import sys
import textwrap
from collections.abc import Callable, Sequence
from functools import cache
from pathlib import Path
from typing import Any, NoReturn

#: The exit status of a bad option (argparse's own).
USAGE = 2
TRUE, FALSE = ("true", "1", "yes"), ("false", "0", "no")
OVERRIDES_HELP = "Hydra overrides of conf/config.yaml, e.g. experiment=chinet_table2 logger.tracking_uri=URI"
#: The documentation installed with the package (a checkout's docs/ folder).
DOCS = Path(__file__).resolve().parent / "docs"


class Formatter(argparse.HelpFormatter):
    """Help text from a module docstring: each paragraph and each ``-``/``*`` item filled to the terminal on its
    own."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        out = []
        for paragraph in re.split(r"\n\s*\n", text.strip()):
            items = []
            for item in re.split(r"\n(?=\s*[-*] )", paragraph):
                bullet = re.match(r"\s*[-*] ", item)
                lead = "- " if bullet else ""
                body = " ".join(item[bullet.end() if bullet else 0 :].split())
                items.append(
                    textwrap.fill(
                        body,
                        width,
                        initial_indent=indent + lead,
                        subsequent_indent=indent + " " * len(lead),
                        break_long_words=False,  # a path stays whole, to copy
                        break_on_hyphens=False,
                    )
                )
            out.append("\n".join(items))
        return "\n\n".join(out)


class Parser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose error is one line on stderr, ``error: <message> (see <prog>
    --help)``, and exit status :data:`USAGE`; options and overrides may come in any order."""

    def error(self, message: str) -> NoReturn:
        self.exit(USAGE, f"error: {' '.join(message.split())} (see {self.prog} --help)\n")

    def parse(self, argv: Sequence[str] | None) -> argparse.Namespace:
        """``argv`` (``sys.argv[1:]`` when None) parsed; ``--help`` and a bad option end the process
        (:class:`SystemExit`)."""
        return self.parse_intermixed_args(sys.argv[1:] if argv is None else list(argv))


def plain(doc: str | None) -> str | None:
    """A module docstring as help text: reStructuredText's ``code`` and :role:`target` as plain text."""
    if doc is None:
        return None
    return re.sub(r"``([^`]+)``", r"\1", re.sub(r":\w+:`~?([^`]+)`", r"\1", doc))


@cache
def _grammar() -> Any:
    from hydra.core.override_parser.overrides_parser import OverridesParser

    return OverridesParser.create()


def override(text: str) -> str:
    """``text`` where it is one of Hydra's overrides (``key=value``, ``+key=value``, ``~key``, ``key=a,b``, ...);
    else an :class:`argparse.ArgumentTypeError` with Hydra's reason."""
    from hydra.errors import HydraException

    try:
        parsed = _grammar().parse_override(text)
    except HydraException as err:
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise argparse.ArgumentTypeError(f"invalid override {text!r} ({reason})") from None
    if not parsed.key_or_group:
        raise argparse.ArgumentTypeError(f"invalid override {text!r} (no key)")
    return text


def key(text: str) -> str:
    """The key of an override: ``experiment`` of ``experiment=x``, ``+experiment=x`` and ``~experiment``."""
    return text.split("=", 1)[0].lstrip("+~").split("@", 1)[0]


def boolean(text: str) -> bool:
    """``true``/``1``/``yes`` or ``false``/``0``/``no`` (any case); ValueError otherwise."""
    if text.lower() in TRUE + FALSE:
        return text.lower() in TRUE
    raise ValueError("expected true or false")


def number(text: str) -> float:
    """A float; ValueError naming what it expected otherwise."""
    try:
        return float(text)
    except ValueError:
        raise ValueError("expected a number") from None


def names(text: str) -> list[str]:
    """A comma-separated list: ``a,b`` -> ``["a", "b"]``."""
    return [x for x in text.split(",") if x]


def as_typed(prog: str, argv0: str | None = None) -> str:
    """A command's name as the user typed it: the console script's (``ablate-report``) where that ran, else ``prog``
    (``python -m ablate.report``)."""
    name = Path(sys.argv[0] if argv0 is None else argv0).name
    return name if name.startswith("ablate") and not name.endswith(".py") else prog


def command(prog: str, doc: str | None, usage: str, epilog: str) -> Parser:
    """The parser of the command ``prog``: its ``usage`` (``%(prog)s`` for ``prog``; lines after the first indented
    under it), its description ``doc`` (its module's docstring), Hydra's overrides as positional arguments
    (``overrides``), the ``epilog`` after the options (its exit statuses), then where the installed documentation
    is (:data:`DOCS`)."""
    usage = usage.replace("\n", "\n" + " " * len("usage: "))
    epilog = f"{epilog.rstrip()}\n\ndocumentation: {DOCS / 'guide.md'} (installed with the package)\n"
    prog = as_typed(prog)
    parser = Parser(
        prog=prog, usage=usage, description=plain(doc), epilog=epilog, formatter_class=Formatter, allow_abbrev=False
    )
    parser.add_argument("overrides", nargs="*", type=override, metavar="key=value", help=OVERRIDES_HELP)
    return parser


def own(parser: Parser, args: argparse.Namespace, keys: dict[str, Callable[[str], Any]]) -> None:
    """Take a command's own ``key=value`` options out of ``args.overrides`` (they are no config keys) and set them
    on ``args``, each read by its function in ``keys`` (the last one given wins; None where not given); a value it
    cannot read is a bad option."""
    rest = []
    for name in keys:
        setattr(args, name, None)
    for text in args.overrides:
        name, _, value = text.partition("=")
        if name not in keys:
            rest.append(text)
            continue
        try:
            setattr(args, name, keys[name](value))
        except ValueError as err:
            parser.error(f"{text}: {err}")
    args.overrides = rest


def report(doc: str | None, argv: Sequence[str] | None = None) -> argparse.Namespace:
    """``python -m ablate.report [--publish | --load | --extend | --seal | --reproduce | --parity] [key=value ...]``:
    ``publish``, ``load``, ``extend``, ``seal``, ``reproduce`` and ``parity`` (bools),
    ``overrides``. ``--reproduce`` needs ``experiment=`` and ``row=``, ``--parity`` ``experiment=`` and one
    ``row=``, ``--extend`` one ``experiment=``."""
    parser = command(
        "python -m ablate.report",
        doc,
        usage="%(prog)s [-h] [experiment=<table>] [key=value ...]\n"
        "%(prog)s --publish [experiment=<table>] [key=value ...]\n"
        "%(prog)s --load [experiment=<table>] [key=value ...]\n"
        "%(prog)s --extend experiment=<table> [key=value ...]\n"
        "%(prog)s --seal [experiment=<table>]\n"
        "%(prog)s --reproduce experiment=<table> row=<row> [seed=N] [key=value ...]\n"
        "%(prog)s --parity experiment=<table> row=<row> [key=value ...]",
        epilog="exit status:\n"
        "- 0: written; --reproduce: the rerun lies inside the row's prediction interval\n"
        "- 1: a store that refuses this client, an override that does not compose, no runs of the table named "
        "(--reproduce, --parity: of the row), records that are not what was published (each named, with its line; "
        "the other tables rendered)\n"
        "- 2: a bad option, one error: line on stderr; --reproduce: also a rerun outside the row's prediction "
        "interval, its verdict on stdout and no error: line",
    )
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument(
        "--publish",
        action="store_true",
        help="publish from the store: write each table's run records (results/runs/<table>.csv) from the store's "
        "runs, then the table from them; without it the tables are rendered from the committed records alone",
    )
    mode.add_argument(
        "--load",
        action="store_true",
        help="load the published run records into your store (mlflow.db unless logger.tracking_uri or "
        "MLFLOW_TRACKING_URI says otherwise), marked as imported, so that `mlflow ui` shows the runs behind the tables",
    )
    mode.add_argument(
        "--extend",
        action="store_true",
        help="load a raced table's published records into your store as its own finished jobs, where this machine "
        "and today's code would make the same numbers (the others are named), so that `python -m ablate -m "
        "experiment=<table>` races on from its next look and trains only the seeds they lack: needs one "
        "experiment=<table>",
    )
    mode.add_argument(
        "--seal",
        action="store_true",
        help="after an intended edit of a table's run records (results/runs/<table>.*): check that each file parses "
        "and seal them again (results/runs/<table>.seal.json), so that the report renders from them; every table's "
        "without experiment=",
    )
    mode.add_argument(
        "--reproduce",
        action="store_true",
        help="rerun one seed of a row here and say whether it holds: needs experiment=<table> row=<row>; "
        "seed=N picks the seed (default: the first recorded)",
    )
    mode.add_argument(
        "--parity",
        action="store_true",
        help="write a row's bf16-against-fp32 section of results/precision_parity.md: needs experiment=<table> "
        "and one row=<row>",
    )
    args = parser.parse(argv)
    given = {key(o) for o in args.overrides}
    rows = [o.partition("=")[2] for o in args.overrides if key(o) == "row"]
    if args.reproduce and not {"experiment", "row"} <= given:
        parser.error("--reproduce needs experiment=<table> and row=<row>")
    if args.reproduce and not all(o.partition("=")[2].isdigit() for o in args.overrides if key(o) == "seed"):
        parser.error("--reproduce takes one seed=N, N a whole number")
    tables = [o.partition("=")[2] for o in args.overrides if key(o) == "experiment"]
    if args.extend and (len(tables) != 1 or "," in tables[0]):
        parser.error("--extend needs one experiment=<table>")
    if args.parity and ("experiment" not in given or len(rows) != 1 or "," in rows[0]):
        parser.error("--parity needs experiment=<table> and one row=<row>")
    return args


def latency(doc: str | None, argv: Sequence[str] | None = None) -> argparse.Namespace:
    """``python -m ablate.latency experiment=<table> [key=value ...]``: ``overrides``, ``experiment=`` among them."""
    parser = command(
        "python -m ablate.latency",
        doc,
        usage="%(prog)s [-h] experiment=<table> [key=value ...]",
        epilog="exit status:\n- 0: timed\n- 1: no runs of the table in the store\n"
        "- 2: a bad option, one error: line on stderr",
    )
    args = parser.parse(argv)
    if "experiment" not in {key(o) for o in args.overrides}:
        parser.error("experiment=<table> is required: the table whose rows are timed")
    return args


def diagnose(doc: str | None, argv: Sequence[str] | None = None) -> argparse.Namespace:
    """``python -m ablate.diagnose [experiment=<table>] [row=x,y] [experts_only=true] [key=value ...]``: ``row``
    (a list, empty: every row of the table), ``experts_only`` (bool) and ``overrides`` (``experiment=smoe_table1``
    added where none is given)."""
    parser = command(
        "python -m ablate.diagnose",
        doc,
        usage="%(prog)s [-h] [experiment=<table>] [row=x,y] [experts_only=true|false] [key=value ...]",
        epilog="exit status:\n- 0: written\n- 1: the table cannot be diagnosed here (a missing checkpoint is "
        "named with the command that makes it)\n- 2: a bad option, one error: line on stderr",
    )
    args = parser.parse(argv)
    own(parser, args, {"row": names, "experts_only": boolean})
    args.row, args.experts_only = args.row or [], bool(args.experts_only)
    if "experiment" not in {key(o) for o in args.overrides}:
        args.overrides.append("experiment=smoe_table1")
    return args


def check_paper(
    doc: str | None, argv: Sequence[str] | None = None, tables: Sequence[str] | None = None
) -> argparse.Namespace:
    """``python -m ablate.check_paper [experiment=a,b] [row=x,y] [budget_min=N] [force=true] [reuse=true]
    [key=value ...]``: ``experiment`` and ``row`` (lists, empty: all), ``budget_min`` (float or None), ``force``
    and ``reuse`` (bools), ``overrides`` (the rest); an experiment not in ``tables`` (where given) is a bad option."""
    parser = command(
        "python -m ablate.check_paper",
        doc,
        usage="%(prog)s [-h] [experiment=a,b] [row=x,y] [budget_min=N]\n"
        "[force=true|false] [reuse=true|false] [key=value ...]",
        epilog="exit status:\n- 0: every chosen row measured\n- 1: a row failed\n"
        "- 2: a bad option or an unknown experiment (one error: line on stderr); no row of the chosen tables "
        "has a chosen name, or a figures file is not JSON (one error: line on stdout)",
    )
    args = parser.parse(argv)
    own(parser, args, {"experiment": names, "row": names, "budget_min": number, "force": boolean, "reuse": boolean})
    args.experiment, args.row = args.experiment or [], args.row or []
    args.force, args.reuse = bool(args.force), bool(args.reuse)
    if tables is not None and (unknown := sorted(set(args.experiment) - set(tables))):
        parser.error(f"no experiment {', '.join(unknown)}; have {', '.join(tables)}")
    return args

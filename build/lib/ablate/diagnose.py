"""``python -m ablate.diagnose [experiment=<table>] [experts_only=true] [key=value ...]``: where fusion can gain over
the single-modal experts, and where its gates look (:mod:`ablate.analysis.diagnose`), from a two-stage table's
checkpoints (``checkpoints/``, kept by ``python -m ablate -m experiment=<table>``).

``experiment=<table>``: the table (default ``smoe_table1``). ``experts_only=true``: the single-modal rows only, the
data check before any fused row is trained (``results/<table>_experts.md`` and ``.png``); by default
``results/<table>_diagnosis.md`` and ``.png`` with the masks and gates figures. Any other override of
``conf/config.yaml`` applies too, e.g. ``scale=smoke``."""

import sys

from ablate import cli


def main(argv: list[str] | None = None) -> int:
    """Read the arguments (:func:`ablate.cli.diagnose`) before torch is imported, then diagnose the table."""
    argv = sys.argv[1:] if argv is None else argv
    cli.diagnose(__doc__, argv)
    from ablate.analysis.diagnose import main as run

    return run(argv)


if __name__ == "__main__":
    raise SystemExit(main())

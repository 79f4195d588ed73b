"""``python -m ablate.check_paper [experiment=a,b] [row=x,y] [budget_min=N] [force=true] [reuse=true] [key=value
...]``: every row of every table at ``scale=paper`` runs one training and one test step on the CPU, with its memory
and GPU-hours estimated; the figures go to ``results/paper_scale.md`` (:mod:`ablate.capacity.check`).

Its own options: ``experiment=a,b`` and ``row=x,y`` choose the tables and rows (default: all); ``budget_min=N`` stops
starting rows after N minutes, leaving the rest for a later run; rows measured before are kept unless
``force=true``. ``reuse=true`` times no step: it rewrites the markdown from ``results/paper_scale.json`` and today's
configs, counting only the frozen MACs that the stored figures lack. Any other override of ``conf/config.yaml``
applies to every row."""

import logging
import sys

from ablate import cli


def main(argv: list[str] | None = None) -> int:
    """Read the arguments (:func:`ablate.cli.check_paper`) before torch is imported, then check the rows."""
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s] %(message)s", datefmt="%H:%M:%S")
    argv = sys.argv[1:] if argv is None else argv
    cli.check_paper(__doc__, argv)
    from ablate.capacity.check import main as run

    return run(argv)


if __name__ == "__main__":
    raise SystemExit(main())

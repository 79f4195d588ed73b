"""``python -m ablate.latency experiment=<table> [key=value ...]``: time every row of a table side by side, in one
process after training, log the figures to the rows' runs and rewrite the table (:mod:`ablate.analysis.latency`).

The config's ``comp_time`` options apply as overrides: ``comp_time.repeats=N`` timed rounds (default 10) after
``comp_time.warmup=N`` untimed ones (3), with ``comp_time.threads=N`` intra-op threads (1), on ``comp_time.device``
(``auto``, the default: CUDA where there is one, else ``cpu``; or a torch device such as ``cpu``). A multirun times
its table by itself at its end unless ``comp_time.after_sweep=false``. Any other override of ``conf/config.yaml``
applies too, e.g. ``logger.tracking_uri=...``."""

import logging
import sys

from ablate import cli


def main(argv: list[str] | None = None) -> int:
    """Read the arguments (:func:`ablate.cli.latency`) before torch is imported, then time the table."""
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s] %(message)s", datefmt="%H:%M:%S")
    argv = sys.argv[1:] if argv is None else argv
    cli.latency(__doc__, argv)
    from ablate.analysis.latency import main as run

    return run(argv)


if __name__ == "__main__":
    raise SystemExit(main())

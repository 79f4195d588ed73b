"""``python -m ablate.latency experiment=<table>``: time every row of a table side by side (:mod:`ablate.analysis.latency`)."""

import logging

from ablate.analysis.latency import main

if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s] %(message)s", datefmt="%H:%M:%S")
    raise SystemExit(main())

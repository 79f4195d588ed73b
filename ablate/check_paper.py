"""``python -m ablate.check_paper [experiment=a,b] [row=x,y] [budget_min=N] [force=true] [reuse=true]``: every row of
every table at ``scale=paper`` runs one training and one test step on the CPU, with its memory and GPU-hours
estimated; the figures go to ``results/paper_scale.md`` (:mod:`ablate.capacity.check`). ``reuse=true`` times no
step: it rewrites the markdown from ``results/paper_scale.json`` and today's configs, counting only the frozen MACs
that the stored figures lack."""

import logging
import sys

from ablate.capacity.check import main

if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s] %(message)s", datefmt="%H:%M:%S")
    raise SystemExit(main(sys.argv[1:]))

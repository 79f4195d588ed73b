"""``python -m ablate.diagnose [experiment=<table>] [experts_only=true]``: where fusion can gain over the single-modal
experts, and where its gates look (:mod:`ablate.analysis.diagnose`)."""

from ablate.analysis.diagnose import main

if __name__ == "__main__":
    raise SystemExit(main())

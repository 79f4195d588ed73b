"""What is read from a table's trained runs after they ran: side-by-side latency (:mod:`~ablate.analysis.latency`),
the reproduction check (:mod:`~ablate.analysis.reproduce`) and the two-stage diagnosis
(:mod:`~ablate.analysis.diagnose`, whose per-family part lives beside its task family)."""

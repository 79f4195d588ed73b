"""A multirun's parts, which the racing sweeper (``hydra_plugins/ablate_racing_sweeper``) drives: its plan
(:mod:`~ablate.sweep.launches`: what it launches; :mod:`~ablate.sweep.plan`: the jobs' estimate), its start and end
(:mod:`~ablate.sweep.parent`, :mod:`~ablate.sweep.finish`), its tuning phase (:mod:`~ablate.sweep.tuning`), its one
state file (:mod:`~ablate.sweep.state`) and its progress lines (:mod:`~ablate.sweep.progress`, fed by each job's end
through :mod:`~ablate.sweep.callback`)."""

"""A multirun: the Hydra callback that opens its parent run and writes its table at the end
(:mod:`~ablate.sweep.callback`), and its progress and ETA (:mod:`~ablate.sweep.progress`). The racing sweeper
(``hydra_plugins/ablate_racing_sweeper``) launches its jobs."""

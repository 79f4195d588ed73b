"""Capacity planning for ``scale=paper``: every row's step time, memory and GPU-hours, measured on a few steps
(:mod:`~ablate.capacity.check`; rows :mod:`~ablate.capacity.rows`, measurements :mod:`~ablate.capacity.measure`,
estimates :mod:`~ablate.capacity.estimates`, the markdown :mod:`~ablate.capacity.report`)."""

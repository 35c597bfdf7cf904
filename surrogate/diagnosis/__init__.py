"""Measurement, diagnosis and advice below the stages: they take plain values and typed options
(never a stage's settings) and return what they measured; the stages read their settings, call
them, write the artefacts and log.

- :mod:`~surrogate.diagnosis.cost`: what a simulation costs (the estimate every budget shares).
- :mod:`~surrogate.diagnosis.probe`: a network's cost measured where its cells start.
- :mod:`~surrogate.diagnosis.options`: the inspection's typed options.
- :mod:`~surrogate.diagnosis.population`: the inputs the fields give; the grid of fixed inputs.
- :mod:`~surrogate.diagnosis.sensitivity`: the network and each input's effect.
- :mod:`~surrogate.diagnosis.fixed`, :mod:`~surrogate.diagnosis.exact`,
  :mod:`~surrogate.diagnosis.simulated`: occupancy, settling, relaxation and memory at fixed
  inputs, exactly or by simulation.
- :mod:`~surrogate.diagnosis.settling`: the settling time and the burn-in it calls for.
- :mod:`~surrogate.diagnosis.recommendation`: the abstraction recommended.
- :mod:`~surrogate.diagnosis.report`: the inspection's report and figures.
- :mod:`~surrogate.diagnosis.advice`: whether to trust a run's abstraction (``verdict``), and
  :mod:`~surrogate.diagnosis.remedies`: the remedies it prints.
"""

"""The pipeline's stages: collect -> train -> simulate -> evaluate (and reproduce, fidelity).

Each stage module has ``validate(cfg)`` (the typed settings, every check up front) and
``run(cfg)`` (Hydra configs, what the scripts call), and a function of the typed settings
(``collect``, ``train``, ``simulate``, ``evaluate``, ``reproduce``) for the Python API. Settings,
artefact directories and the commands that make them live in :mod:`surrogate.stages.settings`.
"""

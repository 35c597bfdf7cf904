"""Examples of models for the package (not installed with it).

``examples/python_model`` is a model written in Python, importable as
``examples.python_model.gene_switch`` when the repository root is on the import path (as it is
for ``python3 -m pytest`` run from the root, or with ``PYTHONPATH=.``). The other folders hold
models written as a yaml beside an SBML file, with no Python (``model=sbml``).
"""

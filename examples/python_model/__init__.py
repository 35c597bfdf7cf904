"""The template for a new Python model: see README.md in this folder and ``gene_switch.py``."""

"""Concrete internal models of agents (one subpackage per model)."""

"""Runnable studies: the paper's figures and tables, and studies beyond it (see studies/reproduce.py)."""

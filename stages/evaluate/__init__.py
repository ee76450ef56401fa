"""The `evaluate` stage: the papers' tables and figures."""

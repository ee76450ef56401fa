"""Commands that produce the results tables in ``docs/results/`` from finished run folders (``python -m
experiments.<name>``); they use the stages' algorithms and are not part of any stage."""

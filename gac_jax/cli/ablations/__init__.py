"""The ablation runner: ``python -m gac_jax.cli.ablations`` (see :mod:`.runner`).

``runner`` trains every (row, seed) of an ablation with ``train.py`` and evaluates it,
``report`` turns the finished runs into docs/ablations.md, ``rows`` holds what the report says
about each row (the paper's numbers, what each row changes).
"""

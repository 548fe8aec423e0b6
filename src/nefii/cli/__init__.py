"""The ``nefii`` console script: one small module per verb."""

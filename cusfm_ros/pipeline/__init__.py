"""Staged orchestration: the stage contract, the runner, one module per stage, options."""

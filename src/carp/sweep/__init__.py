"""Optuna sweep over scale schedules and codebook sizes, each trial one DVC experiment.

Overview in docs/architecture.md, "Sweeps and studies".
"""

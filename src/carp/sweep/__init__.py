"""Optuna sweep over scale schedules and codebook sizes, each trial one DVC experiment (DESIGN.md section 7)."""

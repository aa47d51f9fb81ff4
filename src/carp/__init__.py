"""carp: coarse-to-fine autoregressive prediction (CARP) for robot imitation learning."""

__version__ = "0.1.0"

"""training package of carp."""

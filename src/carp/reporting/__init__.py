"""reporting package of carp."""

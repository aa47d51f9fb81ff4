"""tracking package of carp."""

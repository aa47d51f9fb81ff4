"""policy package of carp."""

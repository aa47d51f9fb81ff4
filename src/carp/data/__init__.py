"""data package of carp."""

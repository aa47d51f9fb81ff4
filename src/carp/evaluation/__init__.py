"""evaluation package of carp."""
